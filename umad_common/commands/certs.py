"""`umad certs GRAPH --out DIR`: the certificates of a graph that runs over mutual TLS.

Writes a CA (`ca.pem`, `ca.key`), the hub's certificate (`hub`, for the hub's host names), and one
client certificate per operator (`op-<id>`) and per role (`control`, `observer`), each named by its
common name, then prints the graph's `tls:` and `security:` blocks. An existing CA in DIR is kept
and signs what is missing, so an operator added later gets a certificate of the same CA; existing
certificates are kept. Uses the `openssl` command line tool.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import yaml

from umad_common.commands.checks import checked_graph
from umad_common.commands.common import add_graph_argument
from umad_common.dataflow.certificates import CONTROL, HUB, OBSERVER, VALID_DAYS, make_certificates, operator_identity


def add_arguments(parser):
    add_graph_argument(parser, positional=True)
    parser.add_argument("--out", required=True, help="folder for the certificates (the graph's tls.certs)")
    parser.add_argument(
        "--host",
        action="append",
        default=[],
        help="another name or address clients reach the hub by (the graph's hub host, localhost and "
        "127.0.0.1 are always in its certificate)",
    )
    parser.add_argument("--days", type=int, default=VALID_DAYS, help=f"validity (default {VALID_DAYS})")


def run(args) -> int:
    graph = checked_graph(args.graph)
    out = Path(args.out)
    hub_host = graph.spec.hub.partition("/")[2].rpartition(":")[0].strip("[]")
    hub_names = ["localhost", "127.0.0.1", *([hub_host] if hub_host not in ("0.0.0.0", "::", "") else []), *args.host]
    ids = [op.id for op in graph.spec.operators]
    try:
        made = make_certificates(out, graph.name, ids, hub_names, args.days)
    except RuntimeError as exc:
        print(f"umad certs: {exc}", file=sys.stderr)
        return 1
    print(f"{out}: {', '.join(made) if made else 'nothing new'} (CA {out / 'ca.pem'})")
    folder = os.path.relpath(out.resolve(), graph.base_dir.resolve())
    roles = {HUB: "launcher", CONTROL: "control", OBSERVER: "observer"}
    roles |= {operator_identity(op_id): f"operator:{op_id}" for op_id in ids}
    blocks = {
        "tls": {
            "root_ca": f"{folder}/ca.pem",
            "cert": f"{folder}/{HUB}.pem",
            "key": f"{folder}/{HUB}.key",
            "certs": folder,
        },
        "security": {"roles": roles},
    }
    print("# for the graph file (its hub must be a tls/HOST:PORT endpoint):")
    print(yaml.safe_dump(blocks, sort_keys=False), end="")
    return 0
