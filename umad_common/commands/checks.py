"""What every verb checks before it starts anything long: its drives, model files and their JSON
records, recorded logs, the graph, the output folder, the hub's port.

A wrong input raises `InputError`: one line naming the input, what was wrong and what was expected;
`umad` prints it and exits 2 (`EXIT_BAD_INPUT`) before any process starts or any file is written.
The checks read folder listings, file headers, JSON records and recordings' indexes (their topics
and message times, and each role's topic chosen) only: no torch, no image decoding, so a verb
answers within seconds even on a busy machine. Each verb calls them first in `run`, before its heavy
imports.
"""

from __future__ import annotations

import errno
import json
import os
import socket
import struct
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from umad_common.dataflow.api.graph import Graph
    from umad_common.datasets.drive import Drive

DRIVES = (
    "drives: AnoVox Scenario_* folders, ROS 2 bags (a rosbag2 folder, .mcap or .db3), MCAPs with Foxglove "
    "schemas, or a folder of them; or anomalous/ and normal/ holding them as `umad generate synthetic` writes"
)
MCAP_MAGIC = b"\x89MCAP0\r\n"
SAFETENSORS_MAX_HEADER = 100_000_000  # bytes; larger is not a header


class InputError(Exception):
    """An input a verb was given that cannot work. The message: a line per problem, each naming the
    input, what was wrong and what was expected."""

    @classmethod
    def of(cls, name: object, problem: str, expected: str) -> InputError:
        return cls(f"{name}: {problem}; expected {expected}")


def existing_file(path: Path, name: str, expected: str) -> Path:
    """`path` when it is a file, else InputError naming `name` (the flag and the path)."""
    if not path.exists():
        raise InputError.of(f"{name} {path}", "no such file", expected)
    if not path.is_file():
        raise InputError.of(f"{name} {path}", "is a folder, not a file", expected)
    return path


def existing_folder(path: Path, name: str, expected: str) -> Path:
    """`path` when it is a folder, else InputError."""
    if not path.exists():
        raise InputError.of(f"{name} {path}", "no such folder", expected)
    if not path.is_dir():
        raise InputError.of(f"{name} {path}", "is a file, not a folder", expected)
    return path


def writable_output(path: Path, name: str, folder: bool = True) -> Path:
    """`path` when the verb can write it: an existing writable folder (or, for a file, an existing
    writable file), or a new one whose nearest existing parent is a writable folder. Creates nothing."""
    label = f"{name} {path}"
    kind = "folder" if folder else "file"
    if path.exists():
        if folder and not path.is_dir():
            raise InputError.of(label, "is a file", "a folder to write the output in (or a path to create one)")
        if not folder and path.is_dir():
            raise InputError.of(label, "is a folder", "a file path to write")
        if not os.access(path, os.W_OK):
            raise InputError.of(label, f"this user cannot write the {kind}", f"a writable {kind}")
        return path
    parent = path.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise InputError.of(label, f"{parent} is a file", f"a {kind} path under a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError.of(label, f"this user cannot create it in {parent}", f"a {kind} under a writable folder")
    return path


def model_file(path: Path, name: str, what: str) -> Path:
    """A weight file `NAME.safetensors` with its JSON record `NAME.json` beside it (a 'config'
    object), the safetensors header readable. Returns the .safetensors path."""
    stem = path.with_suffix("") if path.suffix in (".safetensors", ".json") else path
    weights, record = stem.with_name(stem.name + ".safetensors"), stem.with_name(stem.name + ".json")
    expected = f"the {what}: {weights.name} with its record {record.name} beside it"
    existing_file(weights, name, expected)
    existing_file(record, name, expected)
    try:
        config = json.loads(record.read_text()).get("config")
    except (ValueError, AttributeError) as exc:
        raise InputError.of(
            f"{name} {record}", f"not a JSON record ({exc})", f"the {what}'s config and training record"
        ) from None
    if not isinstance(config, dict):
        raise InputError.of(f"{name} {record}", "has no 'config' object", f"the {what}'s config and training record")
    safetensors_file(weights, name, what)
    return weights


def safetensors_file(path: Path, name: str, what: str) -> Path:
    """A file whose first bytes are a safetensors header (a length, then a JSON object)."""
    expected = f"the {what} as a safetensors file"
    with existing_file(path, name, expected).open("rb") as f:
        head = f.read(8)
        size = struct.unpack("<Q", head)[0] if len(head) == 8 else 0
        if not 0 < size < SAFETENSORS_MAX_HEADER:
            raise InputError.of(f"{name} {path}", "not a safetensors file (no header)", expected)
        try:
            json.loads(f.read(size))
        except ValueError:
            raise InputError.of(f"{name} {path}", "not a safetensors file (header is not JSON)", expected) from None
    return path


def recorded_log(path: Path, name: str) -> Path:
    """An MCAP file (by its magic bytes), as `umad launch --record` or `umad eval` write."""
    expected = "an MCAP log written by `umad launch --record` or `umad eval` (OUT/run.mcap)"
    with existing_file(path, name, expected).open("rb") as f:
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise InputError.of(f"{name} {path}", "not an MCAP file", expected)
    return path


def evaluation_run(path: Path, name: str) -> Path:
    """An evaluation folder holding results.json, or that results.json itself."""
    expected = "an evaluation folder of `umad eval` (or `umad sweep`) holding results.json, or that file"
    if path.is_dir():
        existing_file(path / "results.json", name, expected)
    else:
        existing_file(path, name, expected)
    return path


def drive_paths(data: Path, name: str) -> list[Path]:
    """The drives under `data` (a folder, or one recording file), found by listing; InputError when
    there are none."""
    from umad_common.datasets.formats import find_drives

    if not data.exists():
        raise InputError.of(f"{name} {data}", "no such folder or file", DRIVES)
    found = find_drives(data)
    if not found:
        raise InputError.of(f"{name} {data}", "holds no drive", DRIVES)
    return found


def opened(paths: list[Path], name: str, **options) -> list[Drive]:
    """Each drive opened (`umad_common.datasets.formats.open_drive` with `options`): its format read,
    a recording's topics chosen and its index read. InputError naming the first that cannot be."""
    from umad_common.datasets.drive import DatasetError
    from umad_common.datasets.formats import open_drive

    try:
        return [open_drive(path, **options) for path in paths]
    except DatasetError as exc:
        raise InputError(f"{name} {exc}") from None


def drives(data: Path, name: str, topics: str | None = None) -> list[Drive]:
    """The drives under `data`, opened; InputError when there are none or one cannot be read."""
    return opened(drive_paths(data, name), name, topics=topics)


def normal_drives(data: Path, name: str, topics: str | None = None) -> list[Drive]:
    """The drives a training verb reads: DATA/normal/ when it exists, else DATA's drives; opened
    without their labels."""
    from umad_common.datasets.drive import SENSOR_MODALITIES
    from umad_common.datasets.formats import normal_root

    return opened(drive_paths(normal_root(data), name), name, topics=topics, keep=SENSOR_MODALITIES)


def training_inputs(data: Path, out: Path, suffix: str, topics: str | None = None) -> None:
    """What a training verb reads and writes: normal drives in DATA, and `--out` a file name with
    `suffix` ("" for a name without one) that can be written, its JSON record beside it."""
    normal_drives(data, "DATA", topics)
    if out.suffix != suffix:
        raise InputError.of(
            f"--out {out}",
            f"has the suffix {out.suffix or 'none'!r}",
            f"a file name ending {suffix!r}"
            if suffix
            else "a path without suffix (MODEL: MODEL.safetensors and MODEL.json are written)",
        )
    writable_output(out, "--out", folder=False)


def evaluation_drives(
    data: Path, name: str, topics: str | None = None, allow_truncated: bool = False
) -> tuple[Path, list[Drive]]:
    """The folder or file `umad eval` scores (DATA/anomalous/ when it exists, else DATA) and its drives,
    none of them in DATA/normal/; each must carry anomaly labels (an AnoVox semantic camera, a
    recording's labels topic)."""
    from umad_common.datasets.formats import anomalous_root, find_drives

    if not data.exists():
        raise InputError.of(f"{name} {data}", "no such folder or file", DRIVES)
    source = anomalous_root(data)
    normal = find_drives(data / "normal") if (data / "normal").is_dir() else []
    paths = [d for d in find_drives(source) if d not in normal]
    if not paths:
        problem = f"no anomalous drives: only normal ones ({len(normal)} in normal/)" if normal else "holds no drive"
        raise InputError.of(f"{name} {data}", problem, f"{DRIVES}; its anomalous/ drives are scored")
    found = opened(paths, name, topics=topics, allow_truncated=allow_truncated)
    unlabelled = [d for d in found if "anomaly" not in d.modalities]
    if unlabelled:
        raise InputError.of(
            f"{name} {data}",
            f"{len(unlabelled)} of {len(found)} drives have no anomaly labels (e.g. {unlabelled[0].name})",
            "SEMANTIC_IMG/ (benchmark layout) or SEMANTIC-CAM(...)/ (generator layout) in every scored AnoVox drive, "
            "a labels topic (mono8, nonzero = anomaly; --topics labels=TOPIC) in every scored recording",
        )
    return source, found


def source_drives(graph: Graph) -> list[Drive]:
    """The drives the graph's replayers will publish, opened as they will open them (their `source`,
    `topics`, `every`, `allow_truncated`); a replayer of a recorded UMAD log is left to the replayer."""
    from umad_common import resolve_path
    from umad_common.datasets.drive import UMAD_LOG_PROFILE, mcap_profile

    found = []
    for spec in graph.spec.operators:
        if spec.kind != "replayer":
            continue
        params = graph.classes[spec.id].validate_params(spec.params)
        source = resolve_path(params.source, graph.base_dir)
        if source.suffix == ".mcap" and source.is_file() and mcap_profile(source) == UMAD_LOG_PROFILE:
            continue
        name = f"operator {spec.id!r}: source"
        options = {"every": params.every, "topics": params.topics, "allow_truncated": params.allow_truncated}
        found += opened(drive_paths(source, name), name, **options)
    return found


def lidar_notice(graph: Graph, scenarios: list[Drive], name: str) -> str | None:
    """A line saying which operators run without lidar when some drives have none, else None."""
    without = [d for d in scenarios if "lidar" not in d.modalities]
    if not without:
        return None
    readers = sorted(
        spec.id
        for spec in graph.spec.operators
        for port in spec.inputs
        for source in spec.sources_of(port)
        if source.split("/")[1:] == ["lidar"] and source.split("/")[0] in graph.sources()
    )
    who = ", ".join(dict.fromkeys(readers)) or "no operator"
    return (
        f"{name}: {len(without)} of {len(scenarios)} drives have no lidar (e.g. {without[0].name}); "
        f"these operators get empty point clouds there: {who}"
    )


def free_hub_port(endpoint: str, name: str) -> str:
    """`endpoint` when the hub can listen there: a tcp/ or tls/ endpoint whose port no process on this
    machine listens on. Other transports are left to the hub."""
    protocol, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    if protocol not in ("tcp", "tls") or not port.isdigit():
        return endpoint
    family = socket.AF_INET6 if host.startswith("[") else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # a port in TIME_WAIT is free
        try:
            probe.bind((host.strip("[]"), int(port)))
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise InputError.of(
                    f"{name} {endpoint}",
                    f"port {port} is in use (another graph's hub, or one that did not stop)",
                    "a free port: stop that graph, or pass --hub tcp/127.0.0.1:<another port>",
                ) from None
    return endpoint


def checked_graph(
    path: str | Path, sets: list[str] | None = None, local: bool = False, runs: bool = False, data: dict | None = None
) -> Graph:
    """The validated graph with `--set` overrides. `local`: the whole graph runs on this machine, so
    also its interpreters and TLS files; `runs`: it is about to run, so also the files and folders its
    operators read at start (the data, the models). `data`: the graph's contents, not yet written to
    `path`. InputError otherwise: one line per problem."""
    from umad_common.dataflow.api.assignments import GraphError, parse_sets
    from umad_common.dataflow.api.graph import load_graph, missing_input_files, missing_local_files, validate_graph

    try:
        graph = load_graph(path) if data is None else validate_graph(data, Path(path))
        overrides = parse_sets(sets or [])
        graph = graph.with_params(overrides) if overrides else graph
    except GraphError as exc:
        raise InputError("\n".join(exc.problems)) from None
    problems = (missing_local_files(graph) if local else []) + (missing_input_files(graph) if runs else [])
    if local:
        problems += record_views_problems(graph)
    if problems:
        raise InputError("\n".join(f"{path}: {p}" for p in problems))
    return graph


def record_views_problems(graph: Graph) -> list[str]:
    """The graph's `record_views` when its class cannot be loaded here, where the launcher records."""
    from umad_common.dataflow.record.recorder import UnknownViewsError, log_views

    try:
        log_views(graph)
    except UnknownViewsError as exc:
        return [str(exc)]
    return []


def print_notice(line: str | None) -> None:
    """A line about an input that works, but not as fully as it could (e.g. drives without lidar)."""
    if line:
        print(f"note: {line}", file=sys.stderr, flush=True)


def tls_hub(endpoint: str, name: str, graph: Graph) -> str:
    """`endpoint` when it fits the graph: a graph with `tls:` listens on a tls/HOST:PORT hub only."""
    if graph.spec.tls is not None and not endpoint.startswith("tls/"):
        raise InputError.of(
            f"{name} {endpoint}",
            "not a tls/ endpoint, so the graph's tls: would check no certificate and its messages travel in clear",
            f"tls/{endpoint.partition('/')[2]}",
        )
    return endpoint


def print_open_access_warning(graph: Graph, path: str | Path) -> None:
    """Warn, once per command, about a graph with `tls:` but no `security:`: mutual TLS lets only the
    graph's certificates in, and then every holder of one may do anything in the graph."""
    if graph.spec.tls is not None and graph.spec.security is None:
        print(
            f"warning: {path}: tls: without security:, so any holder of a certificate of the graph's CA may do "
            "anything in the graph (set parameters, stop it, publish as any operator, forge acks); add the "
            "security: block that `umad certs` prints",
            file=sys.stderr,
            flush=True,
        )
