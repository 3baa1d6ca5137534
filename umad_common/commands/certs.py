"""`umad certs GRAPH --out DIR [--ca CA_DIR]`: the certificates of a graph that runs over mutual TLS.

Writes a CA (`ca.pem`, `ca.key`) in CA_DIR (default: DIR's sibling `DIR-ca`), a folder the graph
never names: its key mints certificates, so it stays off the graph's hosts. In DIR it writes one
bundle per holder, `hub/`, `control/`, `observer/` and `op-<id>/` per operator, each with the CA
certificate and the holder's own certificate and key (0600), nothing else: a worker host gets the
bundle of its operator, and can be no one else. Then prints the graph's `tls:` and `security:`
blocks. An existing CA in CA_DIR is kept and signs what is missing, so an operator added later gets
a bundle of the same CA; existing bundles are kept. Uses the `openssl` command line tool.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import yaml

from umad_common.commands.checks import InputError, checked_graph
from umad_common.commands.common import add_graph_argument, add_out_argument
from umad_common.dataflow.transport.certificates import (
    CONTROL,
    HUB,
    OBSERVER,
    VALID_DAYS,
    bundle_paths,
    make_certificates,
    operator_identity,
)


def add_arguments(parser):
    add_graph_argument(parser, positional=True)
    add_out_argument(parser, help="folder for the holders' bundles (the graph's tls.certs)")
    parser.add_argument(
        "--ca",
        type=Path,
        default=None,
        help="folder for the CA's certificate and private key, outside --out (default: --out's sibling <out>-ca); "
        "keep it off the graph's hosts",
    )
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
    ca_dir = args.ca or out.absolute().with_name(out.absolute().name + "-ca")
    hub_host = graph.spec.hub.partition("/")[2].rpartition(":")[0].strip("[]")
    hub_names = ["localhost", "127.0.0.1", *([hub_host] if hub_host not in ("0.0.0.0", "::", "") else []), *args.host]
    ids = [op.id for op in graph.spec.operators]
    try:
        made = make_certificates(out, ca_dir, graph.name, ids, hub_names, args.days)
    except ValueError as exc:
        raise InputError(f"--out {out}, --ca {ca_dir}: {exc}") from None
    except RuntimeError as exc:
        print(f"umad certs: {exc}", file=sys.stderr)
        return 1
    print(f"{out}: {', '.join(made) if made else 'nothing new'}")
    print(
        f"  one bundle per holder, {out}/<holder>/: ca.pem, <holder>.pem, <holder>.key; a worker host gets only "
        f"its operator's (e.g. {out / operator_identity(ids[0])}/)"
    )
    print(
        f"  the CA's private key: {ca_dir / 'ca.key'}, in a folder the graph does not name: keep it off the "
        f"graph's hosts (it mints certificates); `umad certs --ca {ca_dir}` needs it to add certificates"
    )
    folder = os.path.relpath(out.resolve(), graph.base_dir.resolve())
    roles = {HUB: "launcher", CONTROL: "control", OBSERVER: "observer"}
    roles |= {operator_identity(op_id): f"operator:{op_id}" for op_id in ids}
    ca_pem, hub_pem, hub_key = bundle_paths(Path(folder), HUB)
    blocks = {
        "tls": {"root_ca": str(ca_pem), "cert": str(hub_pem), "key": str(hub_key), "certs": folder},
        "security": {"roles": roles},
    }
    print("# for the graph file (its hub must be a tls/HOST:PORT endpoint):")
    print(yaml.safe_dump(blocks, sort_keys=False), end="")
    return 0
