"""`umad certs GRAPH --out DIR`: the certificates of a graph that runs over mutual TLS.

Writes a CA (`ca.pem`, `ca.key`), the hub's certificate (`hub`, for the hub's host names), and one
client certificate per operator (`op-<id>`) and per role (`control`, `observer`), each named by its
common name, then prints the graph's `tls:` and `security:` blocks. An existing CA in DIR is kept
and signs what is missing, so an operator added later gets a certificate of the same CA; existing
certificates are kept. Uses the `openssl` command line tool.
"""

from __future__ import annotations

import ipaddress
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

from umad_common.commands.common import add_graph_argument, load_graph_or_exit
from umad_common.dataflow.identities import CONTROL, HUB, OBSERVER, operator_identity

VALID_DAYS = 365
KEY_OPTIONS = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]


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


def openssl(*args: str, cwd: Path) -> None:
    result = subprocess.run(["openssl", *args], cwd=cwd, capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"openssl {args[0]} failed: {result.stderr.strip()}")


def subject_alt_names(names: list[str]) -> str:
    entries = []
    for name in dict.fromkeys(names):
        try:
            entries.append(f"IP:{ipaddress.ip_address(name)}")
        except ValueError:
            entries.append(f"DNS:{name}")
    return ",".join(entries)


def issue(out: Path, name: str, days: int, usage: str, alt_names: list[str]) -> bool:
    """`<name>.pem`/`<name>.key` signed by the CA in `out`, common name `name`; False if it exists."""
    if (out / f"{name}.pem").exists():
        return False
    with tempfile.TemporaryDirectory() as scratch:
        request, extensions = Path(scratch) / "request.csr", Path(scratch) / "extensions.cnf"
        lines = ["basicConstraints=CA:FALSE", "keyUsage=digitalSignature", f"extendedKeyUsage={usage}"]
        if alt_names:
            lines.append(f"subjectAltName={subject_alt_names(alt_names)}")
        extensions.write_text("\n".join(lines) + "\n")
        openssl("req", *KEY_OPTIONS, "-keyout", f"{name}.key", "-out", str(request), "-subj", f"/CN={name}", cwd=out)
        openssl(
            "x509", "-req", "-in", str(request), "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
            "-out", f"{name}.pem", "-days", str(days), "-extfile", str(extensions), cwd=out,
        )  # fmt: skip
    os.chmod(out / f"{name}.key", 0o600)
    return True


def run(args) -> int:
    if shutil.which("openssl") is None:
        print(
            "umad certs needs the openssl command line tool; install it (e.g. apt-get install openssl)", file=sys.stderr
        )
        return 1
    graph = load_graph_or_exit(args.graph)
    if graph is None:
        return 1
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    made = []
    if not (out / "ca.pem").exists():
        openssl(
            "req", "-x509", *KEY_OPTIONS, "-keyout", "ca.key", "-out", "ca.pem", "-days", str(args.days),
            "-subj", f"/CN={graph.name}-ca", cwd=out,
        )  # fmt: skip
        os.chmod(out / "ca.key", 0o600)
        made.append("ca")
    hub_host = graph.spec.hub.partition("/")[2].rpartition(":")[0].strip("[]")
    hub_names = ["localhost", "127.0.0.1", *([hub_host] if hub_host not in ("0.0.0.0", "::", "") else []), *args.host]
    if issue(out, HUB, args.days, "serverAuth,clientAuth", hub_names):
        made.append(HUB)
    clients = [operator_identity(op.id) for op in graph.spec.operators] + [CONTROL, OBSERVER]
    made += [name for name in clients if issue(out, name, args.days, "clientAuth", [])]
    print(f"{out}: {', '.join(made) if made else 'nothing new'} (CA {out / 'ca.pem'})")
    folder = os.path.relpath(out.resolve(), graph.base_dir.resolve())
    roles = {HUB: "launcher", CONTROL: "control", OBSERVER: "observer"}
    roles |= {operator_identity(op.id): f"operator:{op.id}" for op in graph.spec.operators}
    blocks = {
        "tls": {
            "root_ca": f"{folder}/ca.pem",
            "cert": f"{folder}/hub.pem",
            "key": f"{folder}/hub.key",
            "certs": folder,
        },
        "security": {"roles": roles},
    }
    print("# for the graph file (its hub must be a tls/HOST:PORT endpoint):")
    print(yaml.safe_dump(blocks, sort_keys=False), end="")
    return 0
