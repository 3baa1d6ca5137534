"""Acks, goodbyes and resend requests (`umad_common/dataflow/delivery/service_messages.py`): each is taken only
from the sender its key names, a source takes nothing but a resend on its resend key, and what is
ignored is counted and logged once per key. On a real hub with intruders: tests/test_least_privilege.py."""

from __future__ import annotations

import json
import logging
import time

import msgpack
import pytest

from tests.test_keyed_replicas import AckingHost
from umad_common.dataflow.api.graph import validate_graph
from umad_common.dataflow.delivery.service_messages import (
    Ack,
    IgnoredMessages,
    ServiceMessageError,
    encode_ack,
    encode_goodbye,
    encode_resend,
    read_ack,
    read_goodbye,
    read_resend,
)
from umad_common.dataflow.delivery.stats import Stats
from umad_common.dataflow.process.source_driver import SourceDriver
from umad_common.dataflow.transport.bus import Keys

KEYS = Keys("g")


def test_an_ack_is_taken_only_on_a_key_that_names_the_operator_it_claims():
    assert read_ack(KEYS, "umad/g/_ack/sink/r1", encode_ack("run0", 3, "sink")) == Ack("run0", 3, "sink")
    with pytest.raises(ServiceMessageError, match=r"claims to come from sink, but its key names \('double', 'r0'\)"):
        read_ack(KEYS, "umad/g/_ack/double/r0", encode_ack("run0", 3, "sink"))
    for key in ("umad/g/_ack", "umad/other/_ack/sink/r0", "umad/g/_left/sink/r0"):
        with pytest.raises(ServiceMessageError, match="its key names no sender"):
            read_ack(KEYS, key, encode_ack("run0", 3, "sink"))
    for raw in (b'{"stop": true}', msgpack.packb([1, 2]), msgpack.packb({"run": "run0", "op": "sink"})):
        with pytest.raises(ServiceMessageError, match="not an ack"):
            read_ack(KEYS, "umad/g/_ack/sink/r0", raw)


def test_a_goodbye_is_taken_only_on_the_key_of_the_replica_it_names():
    assert read_goodbye(KEYS, "umad/g/_left/triple/r0", encode_goodbye("triple", "r0")) == ("triple", "r0")
    for key in ("umad/g/_left/double/r0", "umad/g/_left/triple/r1"):
        with pytest.raises(ServiceMessageError, match="claims to come from triple.r0"):
            read_goodbye(KEYS, key, encode_goodbye("triple", "r0"))


def test_the_resend_key_takes_a_resend_request_and_nothing_else():
    assert read_resend(encode_resend("run0", 0, 7, "world_model")) == {
        "run": "run0",
        "from": 0,
        "to": 7,
        "for": "world_model",
    }
    request = {"run": "run0", "from": 0, "to": 7, "for": "world_model"}
    refused = [
        {"stop": True},
        {"set": {"window": 1}},
        {"resend": request, "stop": True},
        {"resend": {**request, "set": {"window": 1}}},
        {"resend": {k: v for k, v in request.items() if k != "for"}},
        {"resend": {**request, "from": True}},
        {"resend": {**request, "from": 8}},
        {"resend": {**request, "from": -1}},
        ["resend"],
    ]
    for body in refused:
        with pytest.raises(ServiceMessageError, match="not a resend request"):
            read_resend(json.dumps(body).encode())
    with pytest.raises(ServiceMessageError, match="not a resend request"):
        read_resend(b"\xff not json")


def test_what_is_ignored_is_counted_and_logged_once_per_key(caplog):
    stats = Stats()
    ignored = IgnoredMessages(logging.getLogger("test.ignored"), stats)
    with caplog.at_level(logging.WARNING, logger="test.ignored"):
        for key in ("umad/g/_resend/src", "umad/g/_resend/src", "umad/g/_ack/x/r0"):
            ignored.ignore(key, ServiceMessageError("not a resend request"))
    assert stats.bad_messages == 3
    assert [m.split(":")[0] for m in caplog.messages] == [
        "ignored a message on umad/g/_resend/src",
        "ignored a message on umad/g/_ack/x/r0",
    ]


def test_a_source_keeps_a_frame_in_flight_when_its_ack_comes_on_another_senders_key():
    graph = validate_graph(
        {
            "name": "sbs",
            "operators": [
                {"id": "source", "uses": "tests.toy_ops:RewindableCounterSource"},
                {"id": "log", "uses": "tests.toy_ops:Logger", "inputs": {"x": "source/value"}},
            ],
        }
    )
    host = AckingHost(graph)
    driver = SourceDriver(host, graph.classes["source"](graph.op("source").params), graph)
    keys = Keys("sbs")
    driver.inflight[("run0", 0)] = ([], time.monotonic(), time.monotonic())
    for _ in range(2):  # `log` is the sink; this ack comes on the key of `source`'s own replica
        driver.ack_q.put((keys.ack("source", "r0"), encode_ack("run0", 0, "log")))
    driver._service(0.0)
    assert ("run0", 0) in driver.inflight and host.stats.bad_messages == 2
    driver.ack_q.put((keys.ack("log", "r0"), encode_ack("run0", 0, "log")))
    driver._service(0.0)
    assert ("run0", 0) not in driver.inflight and host.stats.acked == 1
