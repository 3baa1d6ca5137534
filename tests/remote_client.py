"""A bare Zenoh client of the toy graph, run on the other "host" of tests/test_access_control.py
with the certificate it is given: `intrude` publishes false frames on other operators' keys and
sends commands straight to their `_ctl` keys; `observe` subscribes to every channel and tries to
publish once. Prints what it saw as one JSON line.

    python -m tests.remote_client intrude|observe HUB CA CERT KEY SECONDS
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from umad_common.dataflow.api.messages import Message, encode
from umad_common.dataflow.transport.bus import Keys, TlsConfig, ask, close_session, open_client

GRAPH = "toy"


def intrude(session, keys: Keys, seconds: float) -> dict:
    """False frames as `triple` and as the source, then a parameter change and a stop sent straight
    to the operators' and the launcher's command keys."""
    targets = {key: session.declare_publisher(key) for key in (keys.data("triple", "y"), keys.data("source", "value"))}
    deadline = time.monotonic() + seconds
    sent = 0
    while time.monotonic() < deadline:
        for run in ("run0", "run1"):
            for seq in range(0, 100, 7):
                for publisher in targets.values():
                    publisher.put(encode(Message(run, seq, 0, "intruder", {}, {"x": np.full(4, -1.0, np.float32)})))
                    sent += 1
        time.sleep(0.05)
    set_answers = ask(session, keys.control("triple"), {"set": {"factor": 5.0}}, 3.0)
    stop_answers = ask(session, keys.launcher, {"stop": "triple"}, 3.0)
    return {"sent": sent, "set_answers": set_answers, "stop_answers": stop_answers}


def observe(session, keys: Keys, seconds: float) -> dict:
    seen: set[str] = set()
    subscriber = session.declare_subscriber(f"{keys.root}/**", lambda sample: seen.add(str(sample.key_expr)))
    time.sleep(seconds / 2)
    session.put(keys.data("source", "value"), encode(Message("run0", 0, 0, "observer", {}, {})))
    time.sleep(seconds / 2)
    subscriber.undeclare()
    return {"seen": sorted(seen)}


def main(argv: list[str]) -> int:
    mode, hub, ca, cert, key, seconds = argv
    session = open_client(hub, TlsConfig(ca, cert, key, cert, key), timeout_s=10.0, retry=False)
    assert session is not None, f"no hub at {hub}"
    keys = Keys(GRAPH)
    try:
        result = (intrude if mode == "intrude" else observe)(session, keys, float(seconds))
    finally:
        close_session(session)
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
