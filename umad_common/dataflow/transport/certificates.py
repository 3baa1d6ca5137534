"""Who a process of a graph is to a TLS hub, and the certificates that say so.

Each process presents the certificate of its name (`operator_identity`, CONTROL, OBSERVER; the hub,
the launcher and its recorder: HUB), the name being the certificate's common name, which the
graph's `security.roles` map to roles. `make_certificates` writes, with the `openssl` command line
tool (`umad certs`, `umad bench bus`), a CA in a folder of its own, which the graph never names, and
one bundle per holder: a folder `<name>/` with the CA certificate (`ca.pem`) and the holder's own
`<name>.pem` and `<name>.key`, nothing else, so a worker host gets its bundle and can be no one
else. No Zenoh import: the command line's argument parsers use this module.
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import shutil
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


def bundle_paths(folder: Path, name: str) -> tuple[Path, Path, Path]:
    """The CA certificate, certificate and key in holder `name`'s bundle under `folder`."""
    bundle = folder / name
    return bundle / "ca.pem", bundle / f"{name}.pem", bundle / f"{name}.key"


def make_certificates(
    out: Path, ca_dir: Path, graph_name: str, op_ids: list[str], hub_names: list[str], days: int = VALID_DAYS
) -> list[str]:
    """A CA in `ca_dir` (kept if there is one, so what is added later is of the same CA), and in `out`
    a bundle per holder: the hub's, its certificate for `hub_names` (its host names and addresses),
    and one per operator, CONTROL and OBSERVER; bundles already there are kept. Returns what was
    made. ValueError where `ca_dir` lies in `out`, `out` holds a CA key, or `out` holds bundles that
    a CA other than `ca_dir`'s must have signed; RuntimeError where openssl fails."""
    out, ca_dir = out.resolve(), ca_dir.resolve()
    if ca_dir == out or out in ca_dir.parents:
        raise ValueError(f"the CA folder {ca_dir} is inside {out}, which the graph names: give a folder apart")
    if (out / "ca.key").exists():
        raise ValueError(
            f"{out / 'ca.key'}: a CA private key in the folder the graph names (an older `umad certs`); move "
            f"ca.pem and ca.key to {ca_dir}, delete the other files there, and run again"
        )
    holders = [HUB, *(operator_identity(op_id) for op_id in op_ids), CONTROL, OBSERVER]
    made = []
    if not (ca_dir / "ca.pem").exists():
        signed_elsewhere = [name for name in holders if (out / name).exists()]
        if signed_elsewhere:
            raise ValueError(
                f"{out} holds bundles ({', '.join(signed_elsewhere)}) but {ca_dir} no CA: give --ca the folder "
                "of the CA that signed them, or another --out"
            )
        ca_dir.mkdir(mode=0o700, parents=True, exist_ok=True)
        _openssl(
            "req", "-x509", *KEY_OPTIONS, "-keyout", "ca.key", "-out", "ca.pem", "-days", str(days),
            "-subj", f"/CN={graph_name}-ca", cwd=ca_dir,
        )  # fmt: skip
        os.chmod(ca_dir / "ca.key", 0o600)
        made.append("ca")
    for name in holders:
        usage, alt_names = ("serverAuth,clientAuth", hub_names) if name == HUB else ("clientAuth", [])
        if _issue(out, ca_dir, name, days, usage, alt_names):
            made.append(name)
    return made


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


def _issue(out: Path, ca_dir: Path, name: str, days: int, usage: str, alt_names: list[str]) -> bool:
    """Holder `name`'s bundle in `out`: the CA certificate, and `<name>.pem`/`<name>.key` signed by the
    CA in `ca_dir`, common name `name`; False if the bundle exists."""
    ca_pem, cert, key = bundle_paths(out, name)
    if cert.exists():
        return False
    cert.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as scratch:
        request, extensions = Path(scratch) / "request.csr", Path(scratch) / "extensions.cnf"
        lines = ["basicConstraints=CA:FALSE", "keyUsage=digitalSignature", f"extendedKeyUsage={usage}"]
        if alt_names:
            lines.append(f"subjectAltName={_subject_alt_names(alt_names)}")
        extensions.write_text("\n".join(lines) + "\n")
        _openssl("req", *KEY_OPTIONS, "-keyout", str(key), "-out", str(request), "-subj", f"/CN={name}", cwd=ca_dir)
        os.chmod(key, 0o600)
        _openssl(
            "x509", "-req", "-in", str(request), "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
            "-out", str(cert), "-days", str(days), "-extfile", str(extensions), cwd=ca_dir,
        )  # fmt: skip
    shutil.copyfile(ca_dir / "ca.pem", ca_pem)
    return True
