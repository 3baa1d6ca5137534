"""graph.yaml: which operators run, how their ports are wired, with which parameters.

    name: umad                     # bus key prefix: umad/<name>/...
    hub: tcp/127.0.0.1:7447        # where the launcher's router listens
    operators:
      - id: diff_ssim
        kind: difference           # or `uses: mypkg.module:MyOperator`
        inputs: {frame: world_model/frame}
        params: {metric: ssim}
        replicas: 2
        python: .venv-sam/bin/python   # optional: run this operator in another environment

`load_graph` checks everything it can before a process starts and raises GraphError listing every
problem, each naming the operator id and key at fault.
"""

from __future__ import annotations

import fnmatch
import graphlib
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from umad_common import DEFAULT_GRAPH, LIVE_GRAPH, resolve_path
from umad_common.dataflow.api.assignments import GraphError, merge_params
from umad_common.dataflow.api.operator import Operator, Source, UnknownOperatorError, load_operator_class
from umad_common.dataflow.api.pacing import SourceParams
from umad_common.dataflow.transport.bus import DEFAULT_HUB, TlsConfig
from umad_common.dataflow.transport.certificates import bundle_paths, operator_identity
from umad_common.dataflow.transport.planes import PLANES, SharedPayloads

# The recorder's views unless a graph names others: a name, not an import (the engine stays below viz).
FOXGLOVE_VIEWS = "umad_common.viz.foxglove:FoxgloveViews"


class TlsSpec(BaseModel):
    """Mutual TLS: the hub and every process of the graph present a certificate signed by `root_ca`."""

    model_config = ConfigDict(extra="forbid")
    root_ca: str = Field(description="the graph's CA certificate (PEM): it signed every certificate of the graph")
    cert: str = Field(description="hub certificate (PEM); the launcher and its recorder present it too")
    key: str = Field(description="hub private key (PEM)")
    certs: str | None = Field(
        None,
        description="folder of the holders' bundles as `umad certs` writes them, one folder per holder (op-<id>/, "
        "control/, observer/), each with ca.pem and the holder's own <name>.pem/.key; a process given "
        "--cert/--key uses those instead (and the ca.pem beside them, if there is one)",
    )


ROLES = ("launcher", "control", "observer")  # and `operator:<id>`


class SecuritySpec(BaseModel):
    """Roles by certificate common name, which the hub enforces with Zenoh's access control."""

    model_config = ConfigDict(extra="forbid")
    roles: dict[str, str] = Field(
        description="certificate common name -> role: `launcher` (the hub certificate: the launcher and its "
        "recorder), `operator:<id>` (publishes that operator's outputs, reads its inputs), `control` "
        "(`umad set`, `umad op start|stop`), `observer` (reads every channel, publishes nothing)"
    )


class OperatorSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    id: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_\-]*$", description="unique name, used in bus keys")
    kind: str | None = Field(None, description="built-in operator kind")
    uses: str | None = Field(None, description="import path `package.module:Class` of a custom operator")
    inputs: dict[str, str | list[str]] = Field(
        default_factory=dict, description="port -> `operator/output` (wildcards allowed; a list for `many` ports)"
    )

    def sources_of(self, port: str) -> list[str]:
        """The wiring patterns of one input port, as a list."""
        value = self.inputs[port]
        return [value] if isinstance(value, str) else list(value)

    params: dict[str, Any] = Field(default_factory=dict)
    replicas: int = Field(
        1, description="processes sharing this operator's frames (an ordered operator's runs, each run to one replica)"
    )
    python: str | None = Field(None, description="interpreter of another environment to run this operator in")


class GraphSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = Field("umad", pattern=r"^[A-Za-z0-9_\-]+$")
    hub: str = DEFAULT_HUB
    shm_pool_mib: int | None = Field(
        None,
        ge=1,
        description="each replica's Zenoh shared-memory pool for large messages, MiB (default Zenoh's 16; "
        "with payloads in Zenoh's shared memory, `shared_payloads`, 64); a message that finds no room goes "
        "through the hub's socket",
    )
    shared_payloads: SharedPayloads = Field(
        True,
        description="large payloads are written once into shared memory on the publisher's host: on x86 into "
        "a ring of the publisher's, Zenoh carrying a reference (subscribers on other hosts fetch them), on "
        "other CPUs into Zenoh's shared memory; zenoh_shm: Zenoh's shared memory on every CPU; false: every "
        f"payload through Zenoh as it is; or a plane's name ({', '.join(PLANES)}: transport/planes)",
    )
    direct_links: bool = Field(
        True,
        description="replicas on the hub's host link to each other directly (Zenoh peers that find each other "
        "through the hub), so messages between them skip the hub; false, or a graph with tls: every message "
        "through the hub",
    )
    record_views: str | None = Field(
        FOXGLOVE_VIEWS,
        pattern=r"^[A-Za-z_][\w.]*:[A-Za-z_]\w*$",
        description="what a recorded run's log holds beside the exact payloads: views of the messages, made by "
        "this `LogViews` class (record/mcap_log.py), an import path `package.module:Class`; by default the "
        "Foxglove views (`viz/...` channels); null: none",
    )
    tls: TlsSpec | None = None
    security: SecuritySpec | None = None
    base_dir: str | None = Field(
        None, description="folder that relative paths in params resolve against (default: the graph file's)"
    )
    operators: list[OperatorSpec]


@dataclass
class Graph:
    """A validated graph: the spec, each operator's class, and the wiring resolved."""

    spec: GraphSpec
    classes: dict[str, type[Operator]]
    path: Path | None = None

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def base_dir(self) -> Path:
        return graph_base_dir(self.path, self.spec.base_dir)

    def tls_config(
        self, identity: str | None = None, cert: str | None = None, key: str | None = None
    ) -> TlsConfig | None:
        """The graph's TLS settings for one process, paths resolved against `base_dir`.

        The process presents `cert`/`key` where given (a host holding only its own certificate), and
        trusts the `ca.pem` beside `cert` if there is one; else the certificate named `identity`
        (`umad_common.dataflow.transport.certificates`) from its bundle in the graph's `tls.certs` folder, and
        the bundle's CA; `identity` None: the hub's, which the launcher presents too."""
        tls = self.spec.tls
        if tls is None:
            return None
        root_ca, hub_cert, hub_key = (str(self.base_dir / path) for path in (tls.root_ca, tls.cert, tls.key))
        if cert or key:
            client_cert, client_key = cert, key
            beside = Path(cert).parent / "ca.pem" if cert else None
            root_ca = str(beside) if beside is not None and beside.is_file() else root_ca
        elif identity is None:
            client_cert, client_key = hub_cert, hub_key
        elif tls.certs:
            paths = bundle_paths(self.base_dir / tls.certs, identity)
            root_ca, client_cert, client_key = (str(path) for path in paths)
        else:
            client_cert, client_key = None, None
        return TlsConfig(root_ca, hub_cert, hub_key, client_cert, client_key)

    def op(self, op_id: str) -> OperatorSpec:
        for spec in self.spec.operators:
            if spec.id == op_id:
                return spec
        raise GraphError([f"no operator with id {op_id!r}; the graph has {[o.id for o in self.spec.operators]}"])

    def producers(self, source: str) -> list[tuple[str, str]]:
        """The `(op, output)` pairs a wiring source such as `diff_*/map` matches."""
        op_pat, _, out_pat = source.partition("/")
        return [
            (spec.id, out)
            for spec in self.spec.operators
            if spec.id in self.classes
            for out in self.classes[spec.id].outputs
            if fnmatch.fnmatchcase(spec.id, op_pat) and fnmatch.fnmatchcase(out, out_pat)
        ]

    def consumers(self, op_id: str) -> list[str]:
        return [
            spec.id
            for spec in self.spec.operators
            if any(
                op == op_id for port in spec.inputs for src in spec.sources_of(port) for op, _ in self.producers(src)
            )
        ]

    def sources(self) -> list[str]:
        return [s.id for s in self.spec.operators if issubclass(self.classes[s.id], Source)]

    def upstream_sources(self, op_id: str) -> list[str]:
        """The sources whose frames reach `op_id`, directly or through other operators: those a
        restarted ordered operator asks to resend a run."""
        upstream: set[str] = set()
        todo = [op_id]
        while todo:
            spec = self.op(todo.pop())
            read = {op for port in spec.inputs for source in spec.sources_of(port) for op, _ in self.producers(source)}
            todo += read - upstream
            upstream |= read
        return [op for op in self.sources() if op in upstream]

    def topological_order(self) -> list[str]:
        """Operator ids, each after every operator it reads from (the graph has no cycles)."""
        reads_from = {
            spec.id: {
                op for port in spec.inputs for source in spec.sources_of(port) for op, _ in self.producers(source)
            }
            for spec in self.spec.operators
        }
        return list(graphlib.TopologicalSorter(reads_from).static_order())

    def sinks(self) -> list[str]:
        """Operators whose outputs nobody consumes: they acknowledge frames end to end."""
        return [
            s.id for s in self.spec.operators if not issubclass(self.classes[s.id], Source) and not self.consumers(s.id)
        ]

    def with_params(self, overrides: dict[str, dict[str, Any]]) -> Graph:
        """A copy with `{op_id: {param: value}}` merged in, validated again."""
        data = self.spec.model_dump()
        for op_id, params in overrides.items():
            matches = [o for o in data["operators"] if o["id"] == op_id]
            if not matches:
                raise GraphError([f"--set names operator {op_id!r}, which is not in the graph"])
            merge_params(matches[0]["params"], params)
        return validate_graph(data, self.path)


def graph_base_dir(path: Path | None, base_dir: str | None) -> Path:
    """The folder a graph's relative paths resolve against: its `base_dir` (relative to the graph
    file's folder); else the working folder for a graph shipped with the package (the default and
    the live graph: `data/...` means the user's data, wherever the package is installed); else the
    graph file's folder. Shipped files (`umad_common/assets/...`) resolve from any of them."""
    here = path.parent if path else Path.cwd()
    if base_dir:
        return here / base_dir
    if path is not None and is_builtin_graph(path):
        return Path.cwd()
    return here


def is_builtin_graph(path: str | Path) -> bool:
    """Whether `path` is one of the graphs the package ships (in a checkout, also the top-level
    graph.yaml, which the package's default graph links to)."""
    real = Path(path).resolve()
    return any(real == graph.resolve() for graph in (DEFAULT_GRAPH, LIVE_GRAPH))


def load_graph(path: str | Path) -> Graph:
    """Read and validate a graph file. Custom operators (`uses:`) are imported from PYTHONPATH and
    from the graph file's folder."""
    path = Path(path)
    if str(path.resolve().parent) not in sys.path:
        sys.path.append(str(path.resolve().parent))
    return validate_graph(_read_yaml(path), path)


def graph_address(
    path: str | Path, identity: str, cert: str | None = None, key: str | None = None
) -> tuple[str, str, TlsConfig | None]:
    """A graph file's name, hub and TLS settings for a process presenting the certificate `identity`
    (or `cert`/`key`), read without importing its operators: what a command needs to reach the graph
    when it runs."""
    path = Path(path)
    spec = _graph_spec(_read_yaml(path), f"{path}: ")
    return spec.name, spec.hub, Graph(spec, {}, path).tls_config(identity, cert, key)


def _graph_spec(data: Any, where: str) -> GraphSpec:
    """The graph file's mapping validated as a GraphSpec; GraphError naming each problem otherwise."""
    if not isinstance(data, dict):
        raise GraphError([f"{where}expected a mapping with `operators:`, got {type(data).__name__}"])
    try:
        return GraphSpec.model_validate(data)
    except ValidationError as exc:
        raise GraphError([f"{where}{_describe(err, data)}" for err in exc.errors()]) from None


def _read_yaml(path: Path) -> Any:
    try:
        return yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise GraphError(
            [f"{path}: graph file not found; expected a graph YAML file (see `umad graph check --help`)"]
        ) from None
    except yaml.YAMLError as exc:
        raise GraphError([f"{path}: not valid YAML ({exc})"]) from None


def validate_graph(data: Any, path: Path | None = None) -> Graph:
    where = f"{path}: " if path else ""
    spec = _graph_spec(data, where)

    problems: list[str] = []
    classes: dict[str, type[Operator]] = {}
    seen: set[str] = set()
    for op in spec.operators:
        if op.id in seen:
            problems.append(f"duplicate operator id {op.id!r}")
        seen.add(op.id)
        if op.replicas < 1:
            problems.append(f"operator {op.id!r}: replicas must be >= 1, got {op.replicas}")
        if (op.kind is None) == (op.uses is None):
            problems.append(f"operator {op.id!r}: give exactly one of `kind` or `uses`")
            continue
        try:
            classes[op.id] = load_operator_class(op.kind, op.uses)
        except UnknownOperatorError as exc:
            problems.append(f"operator {op.id!r}: {exc}")
    graph = Graph(spec, classes, path)

    for op in spec.operators:
        cls = classes.get(op.id)
        if cls is None:
            continue
        try:
            params = cls.validate_params(op.params)
        except ValidationError as exc:
            for err in exc.errors():
                loc = ".".join(str(x) for x in err["loc"]) or "params"
                problems.append(f"operator {op.id!r}: parameter {loc!r}: {err['msg']}")
        else:
            problems += [f"operator {op.id!r}: {p}" for p in cls.wiring_problems(params, set(op.inputs))]
        if issubclass(cls, Source) and not issubclass(cls.Params, SourceParams):
            problems.append(
                f"operator {op.id!r}: a source's Params must extend umad_common.dataflow.api.pacing.SourceParams (its pacing)"
            )
        ports = {p.name: p for p in cls.inputs}
        for name in sorted(set(op.inputs) - set(ports)):
            problems.append(
                f"operator {op.id!r}: unknown input port {name!r}; {cls.kind or cls.__name__} has {sorted(ports)}"
            )
        for name in sorted({p.name for p in cls.inputs if not p.optional} - set(op.inputs)):
            problems.append(f"operator {op.id!r}: input port {name!r} is not wired")
        for name in op.inputs:
            if name not in ports:
                continue
            sources = op.sources_of(name)
            if len(sources) > 1 and not ports[name].many:
                problems.append(f"operator {op.id!r}: input {name!r} takes one source, got a list {sources}")
            for source in sources:
                if "/" not in source:
                    problems.append(f"operator {op.id!r}: input {name!r} = {source!r}; expected `operator/output`")
                    continue
                matches = [m for m in graph.producers(source) if m[0] in classes]
                if not matches:
                    problems.append(
                        f"operator {op.id!r}: input {name!r} = {source!r} names an output no operator declares"
                    )
                elif len(matches) > 1 and not ports[name].many:
                    problems.append(
                        f"operator {op.id!r}: input {name!r} = {source!r} matches {len(matches)} outputs but the port takes one"
                    )
    problems += _security_problems(spec)
    if not problems:
        cycle = _find_cycle(graph)
        if cycle:
            problems.append("cycle: " + " -> ".join(cycle))
    if problems:
        raise GraphError([where + p for p in problems])
    return graph


def _security_problems(spec: GraphSpec) -> list[str]:
    problems = []
    if spec.tls is not None and not spec.hub.startswith("tls/"):
        problems.append(
            f"tls: the hub {spec.hub!r} is not a tls/HOST:PORT endpoint, so no certificate is checked and every "
            f"message travels in clear; write `hub: tls/{spec.hub.partition('/')[2]}`"
        )
    if spec.security is None:
        return problems
    if spec.tls is None:
        return [
            "security: roles are given by certificate, so the graph needs a tls: block (root_ca, cert, key, "
            "certs) and a tls/HOST:PORT hub; `umad certs GRAPH --out DIR` makes the certificates"
        ]
    ids = {op.id for op in spec.operators}
    for name, role in spec.security.roles.items():
        op_id = role.partition(":")[2] if role.startswith("operator:") else None
        if op_id is None and role not in ROLES:
            problems.append(
                f"security.roles.{name}: unknown role {role!r}; expected one of {', '.join(ROLES)} or operator:<id>"
            )
        elif op_id is not None and op_id not in ids:
            problems.append(f"security.roles.{name}: {role!r} names no operator of the graph; it has {sorted(ids)}")
    if "launcher" not in spec.security.roles.values():
        problems.append(
            "security.roles: no common name has the role launcher; give the hub certificate's common name "
            "(the launcher and its recorder present it)"
        )
    return problems


def missing_local_files(graph: Graph) -> list[str]:
    """What a launcher on this machine would miss: operators' `python:` interpreters and TLS files.
    Not part of `validate_graph`, because a worker on another machine loads the same graph without
    the other operators' environments."""
    problems = []
    for op in graph.spec.operators:
        if op.python:
            path = Path(op.python) if Path(op.python).is_absolute() else graph.base_dir / op.python
            if not path.is_file():
                problems.append(
                    f"operator {op.id!r}: python interpreter {path} not found (build its environment first)"
                )
    tls = graph.tls_config()
    for name in ("root_ca", "cert", "key"):
        path = getattr(tls, name) if tls else None
        if path and not Path(path).is_file():
            problems.append(f"tls.{name}: {path} not found; expected a PEM file")
    if graph.spec.tls is not None and graph.spec.tls.certs:
        for op in graph.spec.operators:
            own = graph.tls_config(operator_identity(op.id))
            if not Path(own.client_cert).is_file():
                problems.append(
                    f"operator {op.id!r}: certificate {own.client_cert} not found (its bundle in tls.certs)"
                )
    return problems


def missing_input_files(graph: Graph) -> list[str]:
    """The files and folders the operators read at start (`Operator.input_paths`) that do not exist,
    each resolved as the operator will resolve it. Checked by the verbs that run the whole graph here
    (`umad launch`, `umad eval`), not by `umad graph check`: the data is the run's, not the graph's."""
    problems = []
    for op in graph.spec.operators:
        cls = graph.classes[op.id]
        for param, path in cls.input_paths(cls.validate_params(op.params)).items():
            resolved = resolve_path(path, graph.base_dir)
            if not resolved.exists():
                problems.append(f"operator {op.id!r}: {param} {path}: not found at {resolved}")
    return problems


def _find_cycle(graph: Graph) -> list[str] | None:
    edges = {op.id: [c for c in graph.consumers(op.id)] for op in graph.spec.operators}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in edges[node]:
            if state.get(nxt) == 1:
                return stack[stack.index(nxt) :] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        stack.pop()
        state[node] = 2
        return None

    for node in edges:
        if node not in state:
            found = visit(node)
            if found:
                return found
    return None


def _describe(err: dict, data: dict) -> str:
    loc = list(err["loc"])
    if len(loc) >= 2 and loc[0] == "operators" and isinstance(loc[1], int):
        ops = data.get("operators") or []
        op_id = (
            ops[loc[1]].get("id", f"#{loc[1]}") if loc[1] < len(ops) and isinstance(ops[loc[1]], dict) else f"#{loc[1]}"
        )
        field = ".".join(str(x) for x in loc[2:]) or "entry"
        return f"operator {op_id!r}: key {field!r}: {err['msg']}"
    return f"key {'.'.join(str(x) for x in loc)!r}: {err['msg']}"
