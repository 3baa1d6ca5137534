"""Who a process of a graph is to a TLS hub: the name of the certificate it presents.

`umad certs` writes `<name>.pem`/`<name>.key` for each name here into a graph's `tls.certs` folder,
with the name as the certificate's common name, which the graph's `security.roles` map to roles.
No Zenoh import: the command line's argument parsers use this module.
"""

from __future__ import annotations

import argparse

HUB = "hub"  # the hub's certificate, which the launcher and its recorder present too
CONTROL = "control"  # `umad set`, `umad op start|stop`
OBSERVER = "observer"  # a reader on another host: a recorder, a Foxglove bridge


def operator_identity(op_id: str) -> str:
    """The certificate of every replica of operator `op_id`."""
    return f"op-{op_id}"


def add_certificate_arguments(parser: argparse.ArgumentParser) -> None:
    """`--cert/--key`: the certificate a process presents to a TLS hub, instead of its own in the
    graph's `tls.certs` folder (a host that holds only its own)."""
    parser.add_argument("--cert", default=None, help="certificate (PEM) to present to a TLS hub")
    parser.add_argument("--key", default=None, help="private key (PEM) of --cert")
