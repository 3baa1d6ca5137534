"""The hub's access control as derived from a graph (`umad_common/dataflow/launch/access.py`), and the hub's
log of what Zenoh refused (`hub.RefusalLog`), on Zenoh 1.10's own trace lines. The rules at work on a
real hub: tests/test_access_control.py."""

from __future__ import annotations

import io
import json
import logging
from pathlib import Path

from tests.test_graph import SCALE, SINK, SOURCE, TLS, graph
from umad_common.dataflow.api.graph import validate_graph
from umad_common.dataflow.launch.access import access_control, role_rules
from umad_common.dataflow.launch.launcher import Launcher
from umad_common.dataflow.transport.hub import RefusalLog

ROLES = {"hub": "launcher", "ops": "control", "rec": "observer", "op-scale": "operator:scale", "op-src": "operator:src"}
SECURE = graph(SOURCE, SCALE, SINK, hub="tls/127.0.0.1:7447", tls=TLS, security={"roles": ROLES})


def allowed(rules: list[dict], message: str, flow: str) -> set[str]:
    return {key for r in rules if message in r["messages"] and flow in r["flows"] for key in r["key_exprs"]}


def test_an_operator_publishes_only_its_own_keys_under_its_own_name_and_reads_its_inputs():
    rules = role_rules(validate_graph(SECURE), "operator:scale")
    assert allowed(rules, "put", "ingress") == {
        "umad/t/scale/y",
        "umad/t/_stats/scale/*",
        "umad/t/_ack/scale/*",
        "umad/t/_left/scale/*",
    }
    assert allowed(rules, "declare_subscriber", "ingress") == {"umad/t/src/value", "umad/t/_left/*/*"}
    assert allowed(rules, "declare_queryable", "ingress") == {"umad/t/_ctl/scale", "umad/t/_payload/scale/*"}
    assert allowed(rules, "query", "ingress") == {"umad/t/_payload/src/*"}  # its input's payloads, nothing else
    assert allowed(rules, "liveliness_token", "ingress") == {"umad/t/_live/scale/*"}


ORDERED = graph(
    {"id": "src", "uses": "tests.toy_ops:RewindableCounterSource"},
    {"id": "other", "uses": "tests.toy_ops:CounterSource"},
    {"id": "scale", "uses": "tests.toy_ops:Scale", "inputs": {"x": "src/value"}},
    {"id": "total", "uses": "tests.toy_ops:RunningSum", "inputs": {"x": "scale/y"}},
    {"id": "log", "uses": "tests.toy_ops:Logger", "inputs": {"x": "total/y"}},
    {"id": "log_other", "uses": "tests.toy_ops:Logger", "inputs": {"x": "other/value"}},
    hub="tls/127.0.0.1:7447",
    tls=TLS,
    security={"roles": {"hub": "launcher", **{f"op-{op}": f"operator:{op}" for op in ("src", "total", "scale")}}},
)


def test_an_ordered_operator_asks_only_its_upstream_sources_to_resend_and_no_operator_reaches_ctl():
    g = validate_graph(ORDERED)
    assert g.upstream_sources("total") == ["src"]  # through scale; `other` feeds another branch
    total, source = role_rules(g, "operator:total"), role_rules(g, "operator:src")
    assert allowed(total, "put", "ingress") == {
        "umad/t/total/y",
        "umad/t/_stats/total/*",
        "umad/t/_ack/total/*",
        "umad/t/_left/total/*",
        "umad/t/_resend/src",
    }
    assert allowed(source, "declare_subscriber", "ingress") == {
        "umad/t/_left/*/*",
        "umad/t/_ack/*/*",
        "umad/t/_resend/src",
    }
    assert allowed(source, "put", "egress") == {"umad/t/_left/*/*", "umad/t/_ack/*/*", "umad/t/_resend/src"}
    for op in ("src", "total", "scale"):
        rules = role_rules(g, f"operator:{op}")
        for message in ("put", "query"):
            assert not any("/_ctl/" in key for key in allowed(rules, message, "ingress")), (op, message)
        assert allowed(rules, "query", "egress") >= {f"umad/t/_ctl/{op}"}  # it is asked, by control and the launcher


def test_control_only_asks_and_an_observer_only_reads():
    g = validate_graph(SECURE)
    control, observer = role_rules(g, "control"), role_rules(g, "observer")
    assert allowed(control, "query", "ingress") == {"umad/t/_ctl/**", "umad/t/_graph"}  # its own graph only
    assert allowed(observer, "query", "ingress") == {"umad/t/_graph", "umad/t/_payload/**"}
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


def test_the_hub_gets_its_access_control_in_a_file_only_its_user_reads_never_on_its_command_line(tmp_path):
    g = validate_graph(SECURE, tmp_path / "g.yaml")
    launcher = Launcher(g, tmp_path / "g.yaml")
    command = launcher._hub_command()
    acl = Path(command[command.index("--access-control") + 1])
    assert not any("cert_common_names" in word or "key_exprs" in word for word in command)
    assert acl.stat().st_mode & 0o777 == 0o600
    assert json.loads(acl.read_text()) == access_control(g)
    launcher._stop_hub(grace_s=0)  # the hub stops for good: its rules go with it
    assert not acl.exists()


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
