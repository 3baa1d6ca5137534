"""The project's import structure, held by the suite (grimp reads every import statement, those
under TYPE_CHECKING and inside functions included):

- no import circle anywhere in `umad_common`, `umad_operators` and `umad_replay`;
- the engine's rooms (`umad_common/dataflow/`) are layers: a module imports its own room and the
  rooms below it, never one above (top to bottom: launch, process, record, delivery, api, transport);
- the engine is below everything else in the project: of the three packages it imports only its own
  modules and the package root `umad_common` (path helpers: DEFAULT_GRAPH, resolve_path), which
  imports nothing of the project. viz, datasets, segmentation, differences, benchmarks, commands,
  training, the operators and replay may import the engine, never the reverse; what the engine
  needs of them it names by import path (`package.module:Class`, e.g. the recorder's views).
"""

from __future__ import annotations

import grimp
import pytest

PACKAGES = ("umad_common", "umad_operators", "umad_replay")
ENGINE = "umad_common.dataflow"
ROOMS = ("transport", "api", "delivery", "record", "process", "launch")  # bottom to top
ENGINE_MAY_IMPORT = {"umad_common"}  # outside the engine: the package root only


@pytest.fixture(scope="module")
def graph() -> grimp.ImportGraph:
    return grimp.build_graph(*PACKAGES, cache_dir=None)


def import_lines(graph: grimp.ImportGraph, importer: str, imported: str) -> list[str]:
    """`importer:line: statement` for each import of `imported` in `importer`."""
    return [
        f"{importer}:{detail['line_number']}: {detail['line_contents']}"
        for detail in graph.get_import_details(importer=importer, imported=imported)
    ] or [f"{importer}: imports {imported}"]


def circles(graph: grimp.ImportGraph) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's, without recursion)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in sorted(graph.modules):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.find_modules_directly_imported_by(root))))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            module, imports = work[-1]
            for imported in imports:
                if imported not in index:
                    index[imported] = low[imported] = len(index)
                    stack.append(imported)
                    on_stack.add(imported)
                    work.append((imported, iter(sorted(graph.find_modules_directly_imported_by(imported)))))
                    break
                if imported in on_stack:
                    low[module] = min(low[module], index[imported])
            else:
                work.pop()
                if work:
                    parent = work[-1][0]
                    low[parent] = min(low[parent], low[module])
                if low[module] == index[module]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == module:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))
    return found


def room_of(module: str) -> str:
    """The room of an engine module; the package itself re-exports the operator API, so it is `api`."""
    if module == ENGINE:
        return "api"
    room = module.removeprefix(f"{ENGINE}.").split(".")[0]
    assert room in ROOMS, f"{module} is in no room of the engine; expected one of {ROOMS}"
    return room


def engine_modules(graph: grimp.ImportGraph) -> list[str]:
    return sorted(m for m in graph.modules if m == ENGINE or m.startswith(f"{ENGINE}."))


def test_no_import_circle_in_the_project(graph):
    found = circles(graph)
    report = []
    for component in found:
        members = set(component)
        report.append(f"circle of {len(component)} modules: {', '.join(component)}")
        for module in component:
            for imported in sorted(graph.find_modules_directly_imported_by(module) & members):
                report += [f"    {line}" for line in import_lines(graph, module, imported)]
    assert not found, "import circles (each module reaches the others; break every circle):\n" + "\n".join(report)


def test_the_circle_finder_finds_a_circle():
    """The finder itself, on a graph made by hand: a -> b -> c -> a is one circle, d and e are not."""
    made = grimp.ImportGraph()
    for module in "abcde":
        made.add_module(module)
    for importer, imported in (("a", "b"), ("b", "c"), ("c", "a"), ("d", "a"), ("d", "e")):
        made.add_import(importer=importer, imported=imported)
    assert circles(made) == [["a", "b", "c"]]


def test_each_engine_room_imports_only_its_own_and_the_rooms_below(graph):
    rank = {room: level for level, room in enumerate(ROOMS)}
    offending = []
    for module in engine_modules(graph):
        for imported in sorted(graph.find_modules_directly_imported_by(module)):
            if imported.startswith(f"{ENGINE}.") and rank[room_of(imported)] > rank[room_of(module)]:
                offending.append(f"{room_of(module)} imports {room_of(imported)}:")
                offending += [f"    {line}" for line in import_lines(graph, module, imported)]
    assert not offending, (
        f"an engine room imports a room above it (top to bottom: {', '.join(reversed(ROOMS))}):\n"
        + "\n".join(offending)
    )


def test_the_engine_imports_nothing_of_the_project_above_it(graph):
    offending = []
    for module in engine_modules(graph):
        for imported in sorted(graph.find_modules_directly_imported_by(module)):
            if not imported.startswith(f"{ENGINE}.") and imported != ENGINE and imported not in ENGINE_MAY_IMPORT:
                offending += import_lines(graph, module, imported)
    assert not offending, (
        f"the engine ({ENGINE}) imports, of the project, only itself and {sorted(ENGINE_MAY_IMPORT)}; name "
        "anything else by import path (`package.module:Class`):\n" + "\n".join(offending)
    )
    for module in ENGINE_MAY_IMPORT:
        assert not graph.find_modules_directly_imported_by(module), (
            f"{module} imports {sorted(graph.find_modules_directly_imported_by(module))}: the engine imports it, "
            "so it must import nothing of the project"
        )
