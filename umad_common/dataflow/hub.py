"""The hub: a router-mode Zenoh session in a process of its own, so the launcher can restart it.

Clients reconnect to a restarted hub by themselves; frames lost meanwhile are re-sent by the
sources' retransmission, so a hub restart costs time, not frames.
"""

from __future__ import annotations

import argparse
import sys

from umad_common.dataflow.bus import ShutdownSignal, TlsConfig, open_hub


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Run the UMAD hub (Zenoh router).")
    parser.add_argument("--listen", required=True, help="endpoint, e.g. tcp/127.0.0.1:7447 or tls/0.0.0.0:7447")
    parser.add_argument("--root-ca", default=None)
    parser.add_argument("--cert", default=None)
    parser.add_argument("--key", default=None)
    args = parser.parse_args(argv)
    shutdown = ShutdownSignal()
    tls = TlsConfig(args.root_ca, args.cert, args.key) if (args.cert or args.root_ca) else None
    session = open_hub(args.listen, tls)
    try:
        print(f"hub listening on {args.listen}", flush=True)
        shutdown.event.wait()
    finally:
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
