"""`umad certs`: the CA's key apart, in a folder the graph never names, and one bundle per holder
with the CA certificate and that holder's own certificate and key, nothing else (the certificates at
work on a real hub: tests/test_access_control.py, tests/test_least_privilege.py)."""

from __future__ import annotations

import subprocess

import yaml

from tests.conftest import run_umad
from tests.test_runtime_e2e import toy_graph

HOLDERS = ["control", "hub", "observer", "op-double", "op-sink", "op-source", "op-triple"]


def openssl(*args: str) -> str:
    return subprocess.run(["openssl", *args], capture_output=True, text=True, check=True).stdout


def test_the_ca_key_lies_apart_and_each_bundle_holds_the_ca_and_its_own_certificate_and_key_only(tmp_path):
    graph = toy_graph(tmp_path, "tls/10.1.2.3:7447")
    made = run_umad("certs", str(graph), "--out", str(tmp_path / "certs"))
    assert made.returncode == 0, made.stderr
    ca = tmp_path / "certs-ca"
    assert f"the CA's private key: {ca / 'ca.key'}, in a folder the graph does not name" in made.stdout
    assert sorted(p.name for p in ca.iterdir()) == ["ca.key", "ca.pem", "ca.srl"]
    bundles = {p.name: sorted(f.name for f in p.iterdir()) for p in (tmp_path / "certs").iterdir()}
    assert bundles == {name: ["ca.pem", f"{name}.key", f"{name}.pem"] for name in HOLDERS}
    for key in [ca / "ca.key", *(tmp_path / "certs").rglob("*.key")]:
        assert key.stat().st_mode & 0o777 == 0o600, key
    for name in HOLDERS:
        bundle = tmp_path / "certs" / name
        assert (bundle / "ca.pem").read_bytes() == (ca / "ca.pem").read_bytes()
        assert openssl("verify", "-CAfile", str(bundle / "ca.pem"), str(bundle / f"{name}.pem")).strip().endswith("OK")
        assert f"CN = {name}" in openssl("x509", "-noout", "-subject", "-in", str(bundle / f"{name}.pem"))
    blocks = yaml.safe_load(made.stdout.partition("\n# for the graph file")[2].partition("\n")[2])
    assert blocks["tls"] == {
        "root_ca": "certs/hub/ca.pem",
        "cert": "certs/hub/hub.pem",
        "key": "certs/hub/hub.key",
        "certs": "certs",
    }
    again = run_umad("certs", str(graph), "--out", str(tmp_path / "certs"))
    assert again.returncode == 0 and again.stdout.startswith(f"{tmp_path / 'certs'}: nothing new"), again.stdout


def test_a_ca_folder_inside_the_graphs_folder_or_bundles_of_an_unknown_ca_are_refused(tmp_path):
    graph = toy_graph(tmp_path, "tls/10.1.2.3:7447")
    inside = run_umad("certs", str(graph), "--out", str(tmp_path / "certs"), "--ca", str(tmp_path / "certs/ca"))
    assert inside.returncode == 2 and inside.stderr.count("\n") == 1, inside.stderr
    assert "is inside" in inside.stderr and "which the graph names: give a folder apart" in inside.stderr
    assert run_umad("certs", str(graph), "--out", str(tmp_path / "certs")).returncode == 0
    other = run_umad("certs", str(graph), "--out", str(tmp_path / "certs"), "--ca", str(tmp_path / "other-ca"))
    assert other.returncode == 2 and "give --ca the folder of the CA that signed them" in other.stderr, other.stderr
    assert not (tmp_path / "other-ca").exists()
