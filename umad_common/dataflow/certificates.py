"""Who a process of a graph is to a TLS hub, and the certificates that say so.

Each process presents the certificate of its name (`operator_identity`, CONTROL, OBSERVER; the hub,
the launcher and its recorder: HUB), the name being the certificate's common name, which the
graph's `security.roles` map to roles. `make_certificates` writes a CA and `<name>.pem`/`<name>.key`
for each name with the `openssl` command line tool (`umad certs`, `umad bench bus`). No Zenoh
import: the command line's argument parsers use this module.
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import subprocess
import tempfile
from pathlib import Path

HUB = "hub"  # the hub's certificate, which the launcher and its recorder present too
CONTROL = "control"  # `umad set`, `umad op start|stop`
OBSERVER = "observer"  # a reader on another host: a recorder, a Foxglove bridge
VALID_DAYS = 365
KEY_OPTIONS = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]  # ECDSA P-256


def operator_identity(op_id: str) -> str:
    """The certificate of every replica of operator `op_id`."""
    return f"op-{op_id}"


def add_certificate_arguments(parser: argparse.ArgumentParser) -> None:
    """`--cert/--key`: the certificate a process presents to a TLS hub, instead of its own in the
    graph's `tls.certs` folder (a host that holds only its own)."""
    parser.add_argument("--cert", default=None, help="certificate (PEM) to present to a TLS hub")
    parser.add_argument("--key", default=None, help="private key (PEM) of --cert")


def make_certificates(
    out: Path, graph_name: str, op_ids: list[str], hub_names: list[str], days: int = VALID_DAYS
) -> list[str]:
    """A CA in `out` (kept if there is one, so what is added later is of the same CA), the hub's
    certificate for `hub_names` (its host names and addresses), and a client certificate per
    operator, CONTROL and OBSERVER; certificates already there are kept. Returns what was made."""
    out.mkdir(parents=True, exist_ok=True)
    made = []
    if not (out / "ca.pem").exists():
        _openssl(
            "req", "-x509", *KEY_OPTIONS, "-keyout", "ca.key", "-out", "ca.pem", "-days", str(days),
            "-subj", f"/CN={graph_name}-ca", cwd=out,
        )  # fmt: skip
        os.chmod(out / "ca.key", 0o600)
        made.append("ca")
    if _issue(out, HUB, days, "serverAuth,clientAuth", hub_names):
        made.append(HUB)
    clients = [operator_identity(op_id) for op_id in op_ids] + [CONTROL, OBSERVER]
    return made + [name for name in clients if _issue(out, name, days, "clientAuth", [])]


def _openssl(*args: str, cwd: Path) -> None:
    try:
        result = subprocess.run(["openssl", *args], cwd=cwd, capture_output=True, text=True)
    except FileNotFoundError:
        raise RuntimeError("making certificates needs the openssl command line tool; install it") from None
    if result.returncode != 0:
        raise RuntimeError(f"openssl {args[0]} failed: {result.stderr.strip()}")


def _subject_alt_names(names: list[str]) -> str:
    entries = []
    for name in dict.fromkeys(names):
        try:
            entries.append(f"IP:{ipaddress.ip_address(name)}")
        except ValueError:
            entries.append(f"DNS:{name}")
    return ",".join(entries)


def _issue(out: Path, name: str, days: int, usage: str, alt_names: list[str]) -> bool:
    """`<name>.pem`/`<name>.key` signed by the CA in `out`, common name `name`; False if it exists."""
    if (out / f"{name}.pem").exists():
        return False
    with tempfile.TemporaryDirectory() as scratch:
        request, extensions = Path(scratch) / "request.csr", Path(scratch) / "extensions.cnf"
        lines = ["basicConstraints=CA:FALSE", "keyUsage=digitalSignature", f"extendedKeyUsage={usage}"]
        if alt_names:
            lines.append(f"subjectAltName={_subject_alt_names(alt_names)}")
        extensions.write_text("\n".join(lines) + "\n")
        _openssl("req", *KEY_OPTIONS, "-keyout", f"{name}.key", "-out", str(request), "-subj", f"/CN={name}", cwd=out)
        _openssl(
            "x509", "-req", "-in", str(request), "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
            "-out", f"{name}.pem", "-days", str(days), "-extfile", str(extensions), cwd=out,
        )  # fmt: skip
    os.chmod(out / f"{name}.key", 0o600)
    return True
