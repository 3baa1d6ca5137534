import subprocess
import sys

import pytest
import yaml

from tests.conftest import REPO, run_umad, umad_env
from umad_common.dataflow.api.graph import GraphError, load_graph, validate_graph

SOURCE = {"id": "src", "uses": "tests.toy_ops:CounterSource"}
SCALE = {"id": "scale", "uses": "tests.toy_ops:Scale", "inputs": {"x": "src/value"}}
SINK = {"id": "sink", "uses": "tests.toy_ops:JoinSink", "inputs": {"a": "src/value", "b": "scale/y"}}


def graph(*ops, **top):
    return {"name": "t", "operators": [dict(o) for o in ops], **top}


def problems(data) -> str:
    with pytest.raises(GraphError) as info:
        validate_graph(data)
    return "\n".join(info.value.problems)


def test_valid_graph_resolves_sources_and_sinks():
    g = validate_graph(graph(SOURCE, SCALE, SINK))
    assert g.sources() == ["src"] and g.sinks() == ["sink"]
    assert g.producers("sca*/y") == [("scale", "y")]


def test_unknown_kind_names_the_operator():
    assert "operator 'x': unknown operator kind 'warp_drive'" in problems(
        graph(SOURCE, {"id": "x", "kind": "warp_drive"})
    )


def test_unimportable_custom_operator():
    assert "cannot import module 'nope.mod'" in problems(graph(SOURCE, {"id": "x", "uses": "nope.mod:Op"}))


def test_input_naming_an_undeclared_output():
    bad = {**SCALE, "inputs": {"x": "src/nothing"}}
    assert "operator 'scale': input 'x' = 'src/nothing' names an output no operator declares" in problems(
        graph(SOURCE, bad)
    )


def test_unwired_and_unknown_ports():
    text = problems(graph(SOURCE, {**SCALE, "inputs": {"y": "src/value"}}))
    assert "unknown input port 'y'" in text and "input port 'x' is not wired" in text


def test_cycle_is_reported_with_its_path():
    a = {"id": "a", "uses": "tests.toy_ops:Scale", "inputs": {"x": "b/y"}}
    b = {"id": "b", "uses": "tests.toy_ops:Scale", "inputs": {"x": "a/y"}}
    text = problems(graph(SOURCE, a, b))
    assert "cycle:" in text and "a -> b -> a" in text or "b -> a -> b" in text


def test_duplicate_ids():
    assert "duplicate operator id 'scale'" in problems(graph(SOURCE, SCALE, SCALE))


def test_bad_parameter_is_checked_against_the_schema():
    text = problems(graph(SOURCE, {**SCALE, "params": {"factor": "lots", "colour": 1}}))
    assert "operator 'scale': parameter 'factor'" in text and "parameter 'colour'" in text


def test_replicas_below_one():
    assert "operator 'scale': replicas must be >= 1, got 0" in problems(graph(SOURCE, {**SCALE, "replicas": 0}))


def test_shared_memory_pool_is_checked_and_reaches_the_zenoh_config():
    from umad_common.dataflow.transport.bus import zenoh_config

    assert "shm_pool_mib" in problems(graph(SOURCE, shm_pool_mib=0))
    assert validate_graph(graph(SOURCE, shm_pool_mib=4)).spec.shm_pool_mib == 4
    pool = zenoh_config("client", shm_pool_mib=4).get_json("transport/shared_memory/transport_optimization/pool_size")
    assert int(pool) == 4 << 20


def test_unknown_keys_are_refused():
    assert "operator 'scale': key 'replica'" in problems(graph(SOURCE, {**SCALE, "replica": 2}))
    assert "key 'operatorz'" in problems({"operatorz": []})


def test_set_overrides_are_validated():
    g = validate_graph(graph(SOURCE, SCALE))
    assert g.with_params({"scale": {"factor": 5}}).op("scale").params["factor"] == 5
    with pytest.raises(GraphError, match="'ghost'"):
        g.with_params({"ghost": {"factor": 5}})


def test_graph_check_cli_exit_codes(tmp_path):
    good = tmp_path / "good.yaml"
    good.write_text(yaml.safe_dump(graph(SOURCE, SCALE, SINK)))
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(graph(SOURCE, {**SCALE, "replicas": 0}, {"id": "y", "kind": "warp_drive"})))
    ok = run_umad("graph", "check", str(good))
    assert ok.returncode == 0, ok.stderr
    fail = run_umad("graph", "check", str(bad))
    assert fail.returncode == 2
    assert "replicas must be >= 1" in fail.stderr and "'warp_drive'" in fail.stderr


def test_missing_file_and_bad_yaml(tmp_path):
    with pytest.raises(GraphError, match="not found"):
        load_graph(tmp_path / "none.yaml")
    (tmp_path / "bad.yaml").write_text("operators: [")
    with pytest.raises(GraphError, match="not valid YAML"):
        load_graph(tmp_path / "bad.yaml")


def test_check_names_missing_interpreters_and_tls_files_but_workers_load_the_graph(tmp_path):
    tls = {"root_ca": "ca.pem", "cert": "hub.pem", "key": "hub.key", "certs": "certs"}
    data = graph(SOURCE, {**SCALE, "python": "nowhere/bin/python"}, SINK, hub="tls/127.0.0.1:7447", tls=tls)
    path = tmp_path / "g.yaml"
    path.write_text(yaml.safe_dump(data))
    load_graph(path)  # a worker elsewhere needs neither the other environment nor this machine's files
    result = run_umad("graph", "check", str(path))
    assert result.returncode == 2
    assert f"python interpreter {tmp_path / 'nowhere/bin/python'} not found" in result.stderr
    assert f"tls.root_ca: {tmp_path / 'ca.pem'} not found" in result.stderr
    own = tmp_path / "certs/op-scale/op-scale.pem"
    assert f"operator 'scale': certificate {own} not found (its bundle in tls.certs)" in result.stderr


TLS = {"root_ca": "ca.pem", "cert": "hub.pem", "key": "hub.key"}


def test_security_without_tls_is_refused_naming_what_is_missing():
    found = problems(graph(SOURCE, SCALE, SINK, security={"roles": {"hub": "launcher"}}))
    assert "security: roles are given by certificate, so the graph needs a tls: block" in found
    assert "tls/HOST:PORT hub" in found


def test_security_roles_name_known_roles_and_operators_and_the_launcher():
    roles = {"alice": "admin", "op-x": "operator:nope", "op-src": "operator:src"}
    found = problems(graph(SOURCE, SCALE, SINK, hub="tls/127.0.0.1:7447", tls=TLS, security={"roles": roles}))
    assert (
        "security.roles.alice: unknown role 'admin'; expected one of launcher, control, observer or operator:<id>"
        in found
    )
    assert "security.roles.op-x: 'operator:nope' names no operator of the graph" in found
    assert "security.roles: no common name has the role launcher" in found


def test_tls_with_a_tcp_hub_is_refused_naming_the_fix_with_or_without_security(tmp_path):
    for security in (None, {"roles": {"hub": "launcher"}}):
        tcp = graph(SOURCE, SCALE, SINK, hub="tcp/10.0.0.5:7447", tls=TLS, security=security)
        assert (
            "tls: the hub 'tcp/10.0.0.5:7447' is not a tls/HOST:PORT endpoint, so no certificate is checked "
            "and every message travels in clear; write `hub: tls/10.0.0.5:7447`" in problems(tcp)
        )
    path = tmp_path / "g.yaml"
    path.write_text(yaml.safe_dump(graph(SOURCE, SCALE, SINK, tls=TLS)))
    for command in (["graph", "check"], ["launch"]):
        result = run_umad(*command, str(path))
        assert result.returncode == 2 and "write `hub: tls/127.0.0.1:7447`" in result.stderr, result.stderr


def test_tls_without_security_passes_the_check_with_one_warning_and_launch_refuses_a_tcp_hub(tmp_path):
    (tmp_path / "certs").mkdir()
    for name in ("ca.pem", "hub.pem", "hub.key"):
        (tmp_path / name).write_text("")
    path = tmp_path / "g.yaml"
    path.write_text(yaml.safe_dump(graph(SOURCE, SCALE, SINK, hub="tls/127.0.0.1:7447", tls=TLS)))
    checked = run_umad("graph", "check", str(path))
    assert checked.returncode == 0, checked.stderr
    warnings = [line for line in checked.stderr.splitlines() if line.startswith("warning:")]
    assert warnings == [
        f"warning: {path}: tls: without security:, so any holder of a certificate of the graph's CA may do anything "
        "in the graph (set parameters, stop it, publish as any operator, forge acks); add the security: block that "
        "`umad certs` prints"
    ]
    refused = run_umad("launch", str(path), "--hub", "tcp/127.0.0.1:7447")
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1, refused.stderr
    assert (
        "--hub tcp/127.0.0.1:7447: not a tls/ endpoint" in refused.stderr
        and "expected tls/127.0.0.1:7447" in refused.stderr
    )


REPLAYER = {"id": "replayer", "kind": "replayer", "params": {"source": "."}}


def test_a_segmenter_method_names_the_optional_input_it_needs():
    frame_only = {"id": "seg", "kind": "segmenter", "inputs": {"frame": "replayer/camera"}}
    validate_graph(graph(REPLAYER, {**frame_only, "params": {"method": "slic"}}))  # truth, lidar optional
    text = problems(graph(REPLAYER, {**frame_only, "params": {"method": "geometry"}}))
    assert "operator 'seg': method 'geometry' needs input 'lidar'" in text and "not wired" in text
    text = problems(graph(REPLAYER, {**frame_only, "params": {"method": "geometry", "options": {"rest": "gt"}}}))
    assert "needs input 'truth'" in text and "needs input 'lidar'" in text
    wired = {**frame_only, "inputs": {"frame": "replayer/camera", "lidar": "replayer/lidar"}}
    validate_graph(graph(REPLAYER, {**wired, "params": {"method": "geometry"}}))


def test_segmenter_options_are_checked_against_the_method_schema():
    seg = {"id": "seg", "kind": "segmenter", "inputs": {"frame": "replayer/camera"}}
    text = problems(graph(REPLAYER, {**seg, "params": {"method": "felzenszwalb", "options": {"scale": -1}}}))
    assert "operator 'seg'" in text and "method 'felzenszwalb' options: scale" in text


def test_a_segmenter_option_is_set_by_its_dotted_name():
    seg = {"id": "seg", "kind": "segmenter", "inputs": {"frame": "replayer/camera"}, "params": {"method": "slic"}}
    g = validate_graph(graph(REPLAYER, seg))
    assert g.with_params({"seg": {"options.n_segments": 50}}).op("seg").params["options"] == {"n_segments": 50}
    with pytest.raises(GraphError, match="method 'slic' options: n_segments"):
        g.with_params({"seg": {"options.n_segments": 0}})


def test_checking_the_default_graph_imports_neither_torch_nor_scikit_learn():
    """Every replica loads the whole graph to check its wiring: what an operator module imports at
    its top, all 14 replicas pay at start-up (torch and scikit-learn were 3 s of CPU each)."""
    probe = (
        "import sys; from umad_common.dataflow.api.graph import load_graph; load_graph('graph.yaml'); "
        "print(sorted(m for m in ('torch', 'sklearn') if m in sys.modules))"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, env=umad_env(), cwd=REPO
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"
