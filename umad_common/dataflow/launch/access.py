"""A graph's `security:` block as Zenoh access control: the hub enforces who may do what, by the
common name of the certificate each process presented (mutual TLS), and denies everything else.

What each role may do, in Zenoh's terms (`ingress`: from that process into the hub, `egress`: from
the hub to it; key layout in docs/design.md):

- every role learns the graph's declarations (who subscribes, answers, is alive: egress
  `declare_subscriber`, `declare_queryable`, `liveliness_token`), which Zenoh needs to route at all;
- `operator:<id>` publishes that operator's outputs, and its stats, acks and goodbyes under its
  own name (`_stats/<id>/*`, `_ack/<id>/*`, `_left/<id>/*`); an ordered operator also asks the
  sources upstream of it to resend a run (`_resend/<source>`); reads its declared inputs, every
  goodbye and liveliness, and a source also every ack and its own `_resend` key; answers commands on
  its own `_ctl` key and payload fetches under its own `_payload` prefix; fetches payloads of its
  inputs' producers. No operator may command another, nor itself: `_ctl` is asked by `control` and
  the launcher only;
- `control` asks `_ctl` (`umad set`, `umad op start|stop`) and the graph's own `_graph`;
- `observer` reads every channel, liveliness, the graph's own `_graph`, and fetches payloads;
  publishes nothing;
- `launcher` (the hub certificate, which the launcher and its recorder present) may do everything
  in the graph.

Every key a certificate may write names its operator, so it can pass for no other; the receivers of
acks and goodbyes check that the key names the sender the message claims (`service_messages.py`).
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

from umad_common.dataflow.api.graph import Graph
from umad_common.dataflow.transport.bus import Keys

ALL_MESSAGES = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
]
DECLARATIONS = ["declare_subscriber", "declare_queryable", "liveliness_token"]


def _rule(name: str, messages: list[str], flow: str, key_exprs: list[str]) -> dict:
    flows = ["ingress", "egress"] if flow == "both" else [flow]
    return {"id": name, "messages": messages, "flows": flows, "permission": "allow", "key_exprs": key_exprs}


def role_rules(graph: Graph, role: str) -> list[dict]:
    """What one role may do in `graph`, as Zenoh ACL rules (ids unique within the role)."""
    keys = Keys(graph.name)
    everything = [f"{keys.root}/**"]
    if role == "launcher":
        return [_rule("all", ALL_MESSAGES, "both", everything)]
    rules = [_rule("declarations", DECLARATIONS, "egress", everything)]
    graph_info = [
        _rule("ask_graph", ["query"], "ingress", [keys.graph_info]),
        _rule("graph", ["reply"], "egress", [keys.graph_info]),
    ]
    if role == "control":
        return [
            *rules,
            *graph_info,
            _rule("command", ["query"], "ingress", [keys.control_all]),
            _rule("answer", ["reply"], "egress", [keys.control_all]),
        ]
    liveliness = [
        _rule("live", ["declare_liveliness_subscriber", "liveliness_query"], "ingress", [keys.live_all]),
        _rule("live_answer", ["reply"], "egress", [keys.live_all]),
    ]
    if role == "observer":
        channels, payloads = [f"{keys.root}/**"], [f"{keys.root}/_payload/**"]
        return [
            *rules,
            *graph_info,
            *liveliness,
            _rule("subscribe", ["declare_subscriber"], "ingress", channels),
            _rule("receive", ["put"], "egress", channels),
            _rule("fetch", ["query"], "ingress", payloads),
            _rule("fetched", ["reply"], "egress", payloads),
        ]
    op_id = role.partition(":")[2]
    spec, cls = graph.op(op_id), graph.classes[op_id]
    sources = [source for port in spec.inputs for source in spec.sources_of(port)]
    producers = sorted({op for source in sources for op, _ in graph.producers(source)})
    reads = [keys.pattern(source) for source in sources] + [keys.left_all]
    if op_id in graph.sources():  # acks of every sink, and rewinds of its ordered consumers
        reads += [keys.ack_all, keys.resend(op_id)]
    own_names = [keys.stats(op_id, "*"), keys.ack(op_id, "*"), keys.left(op_id, "*")]
    publishes = [keys.data(op_id, out) for out in cls.outputs] + own_names
    if cls.ordered:  # an ordered operator that restarts mid-run asks its sources to resend the run
        publishes += [keys.resend(source) for source in graph.upstream_sources(op_id)]
    own_services = [keys.control(op_id), f"{keys.payload(op_id)}/*"]
    fetches = [f"{keys.payload(op)}/*" for op in producers]
    rules += [
        *liveliness,
        _rule("token", ["liveliness_token"], "ingress", [keys.live(op_id, "*")]),
        _rule("publish", ["put"], "ingress", publishes),
        _rule("subscribe", ["declare_subscriber"], "ingress", reads),
        _rule("receive", ["put"], "egress", reads),
        _rule("serve", ["declare_queryable", "reply"], "ingress", own_services),
        _rule("served", ["query"], "egress", own_services),
    ]
    if fetches:
        rules += [_rule("fetch", ["query"], "ingress", fetches), _rule("fetched", ["reply"], "egress", fetches)]
    return rules


def access_control(graph: Graph) -> dict:
    """The hub's Zenoh `access_control` for `graph.spec.security`: default deny, one subject per role
    holding its certificates' common names, each with that role's rules."""
    assert graph.spec.security is not None
    names_by_role: dict[str, list[str]] = {}
    for name, role in graph.spec.security.roles.items():
        names_by_role.setdefault(role, []).append(name)
    rules, subjects, policies = [], [], []
    for role, names in sorted(names_by_role.items()):
        own = [{**rule, "id": f"{role}/{rule['id']}"} for rule in role_rules(graph, role)]
        rules += own
        subjects.append({"id": role, "cert_common_names": sorted(names)})
        policies.append({"id": role, "rules": [rule["id"] for rule in own], "subjects": [role]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def access_control_file(graph: Graph) -> Path:
    """The graph's Zenoh access control (`access.py`) as JSON in a new file of mode 0600."""
    handle, path = tempfile.mkstemp(prefix=f"umad-{graph.name}-access-", suffix=".json")
    with os.fdopen(handle, "w") as out:
        json.dump(access_control(graph), out)
    return Path(path)
