"""The hub's access control as derived from a graph (`umad_common/dataflow/access.py`), and the hub's
log of what Zenoh refused (`hub.RefusalLog`), on Zenoh 1.10's own trace lines. The rules at work on a
real hub: tests/test_access_control.py."""

from __future__ import annotations

import io
import logging

from tests.test_graph import SCALE, SINK, SOURCE, TLS, graph
from umad_common.dataflow.access import access_control, role_rules
from umad_common.dataflow.graph import validate_graph
from umad_common.dataflow.hub import RefusalLog

ROLES = {"hub": "launcher", "ops": "control", "rec": "observer", "op-scale": "operator:scale", "op-src": "operator:src"}
SECURE = graph(SOURCE, SCALE, SINK, hub="tls/127.0.0.1:7447", tls=TLS, security={"roles": ROLES})


def allowed(rules: list[dict], message: str, flow: str) -> set[str]:
    return {key for r in rules if message in r["messages"] and flow in r["flows"] for key in r["key_exprs"]}


def test_an_operator_publishes_only_its_own_keys_and_reads_its_inputs():
    rules = role_rules(validate_graph(SECURE), "operator:scale")
    assert allowed(rules, "put", "ingress") == {
        "umad/t/scale/y",
        "umad/t/_stats/scale/*",
        "umad/t/_ack",
        "umad/t/_left",
    }
    assert allowed(rules, "declare_subscriber", "ingress") == {
        "umad/t/src/value",
        "umad/t/_ctl/scale",
        "umad/t/_ack",
        "umad/t/_left",
    }
    assert allowed(rules, "declare_queryable", "ingress") == {"umad/t/_ctl/scale", "umad/t/_payload/scale/*"}
    assert allowed(rules, "query", "ingress") == {"umad/t/_payload/src/*"}  # its input's payloads, nothing else
    assert allowed(rules, "liveliness_token", "ingress") == {"umad/t/_live/scale/*"}


def test_control_only_asks_and_an_observer_only_reads():
    g = validate_graph(SECURE)
    control, observer = role_rules(g, "control"), role_rules(g, "observer")
    assert allowed(control, "query", "ingress") == {"umad/t/_ctl/**", "umad/*/_graph"}
    for rules in (control, observer):
        for message in ("put", "reply", "declare_queryable", "liveliness_token"):
            assert allowed(rules, message, "ingress") == set(), message
    assert allowed(observer, "put", "egress") == {"umad/t/**"}


def test_the_hubs_access_control_denies_by_default_with_one_subject_per_role():
    acl = access_control(validate_graph(SECURE))
    assert acl["enabled"] and acl["default_permission"] == "deny"
    assert {s["id"]: s["cert_common_names"] for s in acl["subjects"]} == {role: [name] for name, role in ROLES.items()}
    ids = [r["id"] for r in acl["rules"]]
    assert len(ids) == len(set(ids))
    for policy in acl["policies"]:
        assert all(rule.startswith(f"{policy['id']}/") for rule in policy["rules"])


ZID = "82b59c511b549923a51213ed00db96a7"
PREFIX = "2026-12-06T04:49:56.779916Z TRACE rx-0 ThreadId(08) zenoh::net::routing::interceptor::access_control: "
SUBJECT = f"{ZID} on Interface(lo)+CertCommonName(op-double)+Transport(Tls)+{ZID}"
CACHE_KINDS = [
    "Query",
    "Reply",
    "Put",
    "Delete",
    "Declare/Undeclare Subscriber",
    "Declare/Undeclare Queryable",
    "Declare/Undeclare Liveliness Token",
    "Liveliness Query",
    "Declare Liveliness Subscriber",
]


def test_the_hub_logs_each_refusal_with_the_certificate_name_and_skips_zenohs_cache_lines(caplog):
    key = "umad/toy/triple/y"
    lines = ["hub listening on tls/127.0.0.1:7447\n", f"{PREFIX}ACL (ingress): caching permissions for `{key}` ...\n"]
    lines += [f"{PREFIX}{SUBJECT} is unauthorized to {kind} (ingress) on {key}\n" for kind in CACHE_KINDS]
    lines += [f"{PREFIX}Using cached result: {ZID} is unauthorized to Put (ingress) on {key}\n"] * 3
    lines += [f"{PREFIX}{SUBJECT} is unauthorized to Query (ingress) on umad/toy/_ctl/triple\n"]
    lines += [f"{PREFIX}{SUBJECT} is authorized to Put (ingress) on umad/toy/double/y\n"]
    out = io.StringIO()
    refusals = RefusalLog(out)
    with caplog.at_level(logging.WARNING, logger="umad.hub"):
        for line in lines:
            refusals.line(line)
    assert out.getvalue() == "hub listening on tls/127.0.0.1:7447\n"  # the hub's own output passes
    assert caplog.messages == [
        f"access control refused op-double: Put (ingress) on {key}",  # once, though refused three times
        "access control refused op-double: Query (ingress) on umad/toy/_ctl/triple",
    ]
