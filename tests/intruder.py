"""An attacker on the other "host" of tests/test_least_privilege.py: a bare zenoh-python client that
presents the certificate of a bundle it holds and carries out a plan, as anyone holding that bundle
could, with nothing of UMAD imported. It listens on a key expression all along (to what comes from
the hub, not its own puts), asks the plan's queries, sends the plan's puts again and again for
SECONDS, and prints what came back as one JSON line: `{"sent", "answers", "seen"}`.

    python -m tests.intruder HUB BUNDLE SECONDS PLAN.json

PLAN: `{"listen": key expression, "puts": [[key, payload hex], ...], "queries": [[key, payload hex], ...]}`.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import zenoh


def open_session(hub: str, bundle: Path) -> zenoh.Session:
    """A client of `hub` presenting the certificate of `bundle` (`<name>/`: ca.pem, <name>.pem, <name>.key)."""
    conf = zenoh.Config()
    for path, value in (
        ("mode", "client"),
        ("scouting/multicast/enabled", False),
        ("connect/endpoints", [hub]),
        ("transport/link/tls/root_ca_certificate", str(bundle / "ca.pem")),
        ("transport/link/tls/enable_mtls", True),
        ("transport/link/tls/connect_certificate", str(bundle / f"{bundle.name}.pem")),
        ("transport/link/tls/connect_private_key", str(bundle / f"{bundle.name}.key")),
    ):
        conf.insert_json5(path, json.dumps(value))
    return zenoh.open(conf)


def main(argv: list[str]) -> int:
    hub, bundle, seconds, plan_file = argv
    plan = json.loads(Path(plan_file).read_text())
    puts = [(key, bytes.fromhex(payload)) for key, payload in plan["puts"]]
    seen: set[str] = set()
    answers: list[str] = []
    sent = 0
    with open_session(hub, Path(bundle)) as session:
        listener = session.declare_subscriber(  # what the hub lets through, not this session's own puts
            plan["listen"], lambda sample: seen.add(str(sample.key_expr)), allowed_origin=zenoh.Locality.REMOTE
        )
        for key, payload in plan["queries"]:
            for reply in session.get(key, payload=bytes.fromhex(payload), timeout=1.0):
                if reply.ok is not None:
                    answers.append(reply.ok.payload.to_bytes().decode(errors="replace"))
        deadline = time.monotonic() + float(seconds)
        while time.monotonic() < deadline:
            for key, payload in puts:
                session.put(key, payload)
                sent += 1
            time.sleep(0.02)
        listener.undeclare()
    print(json.dumps({"sent": sent, "answers": answers, "seen": sorted(seen)}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
