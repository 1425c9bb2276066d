"""Deployment files, and the default rendezvous across three hosts (network namespaces) with
mutual TLS and access control."""
import json
import textwrap

import numpy as np
import pytest

from bench.bus.deployment import DeploymentError, load_deployment
from bench.runtime.netns import NetnsLab, deployment_toml, netns_available, run_deployment
from bench.scenario import load_scenario
from bench.sim import simulate_in_process
from conftest import run_bench_cli

GOOD = """
name = "lab"
certs = "certs"
launcher = "sim"
[hosts.sim]
endpoints = ["tls/10.9.0.1:7447"]
nodes = ["plant", "recorder"]
[hosts.flight]
endpoints = ["tls/10.9.0.2:0"]
nodes = ["controller"]
[hosts.est]
endpoints = ["tls/10.9.0.3:0"]
nodes = ["estimator"]
"""


def write(tmp_path, text, name="deploy.toml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def test_good_file_resolves_hosts_and_sessions(tmp_path):
    d = load_deployment(write(tmp_path, GOOD))
    assert d.is_secure   # several hosts: secure unless the file says otherwise
    assert d.host_of("controller") == "flight" and d.host_of("canbus") == "sim"   # unplaced: launcher's host
    assert d.rendezvous == "tls/10.9.0.1:7447"
    flight = d.node_options("controller", "flight")
    assert flight.listen == ("tls/10.9.0.2:0",) and flight.connect == ("tls/10.9.0.1:7447",)
    assert flight.identity.cert_path == tmp_path / "certs" / "controller.pem"
    assert d.hub_options().listen == ("tls/10.9.0.1:7447",)


@pytest.mark.parametrize("edit, message", [
    (lambda t: t.replace('endpoints = ["tls/10.9.0.3:0"]\n', ""), "hosts.est.endpoints: host 'est' has no endpoints"),
    (lambda t: t.replace('nodes = ["estimator"]', 'nodes = ["estimator", "plant"]'), "node 'plant' is on two hosts"),
    (lambda t: t.replace('nodes = ["estimator"]', 'nodes = ["estimater"]'), "unknown node 'estimater'"),
    (lambda t: t.replace("tls/10.9.0.2:0", "tcp/10.9.0.2:0"), "must use tls/"),
    (lambda t: t.replace("tls/10.9.0.1:7447", "tls/10.9.0.1:0"), "needs a fixed port"),
    (lambda t: t.replace('launcher = "sim"', 'launcher = "moon"'), "launcher: 'moon' is not one of the hosts"),
    (lambda t: t + "colour = 1\n", "colour"),
])
def test_bad_file_names_the_field(tmp_path, edit, message):
    with pytest.raises(DeploymentError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load_deployment(write(tmp_path, edit(GOOD)))


def _bad_run(tmp_path, runs_dir, deployment) -> str:
    result = run_bench_cli("run", "--deployment", str(deployment), "--run-id", "bad", "--runs-dir", str(runs_dir),
                           "--no-progress", timeout_s=60)
    assert result.returncode == 2, result.stderr + result.stdout
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert not (runs_dir / "bad").exists()   # nothing started, nothing written
    return result.stderr


@pytest.mark.parametrize("edit, message", [
    (lambda t: t.replace('endpoints = ["tls/10.9.0.3:0"]\n', ""), "has no endpoints"),
    (lambda t: t.replace('nodes = ["estimator"]', 'nodes = ["estimator", "recorder"]'), "is on two hosts"),
])
def test_bad_deployment_is_one_line_and_exit_2(tmp_path, runs_dir, edit, message):
    assert message in _bad_run(tmp_path, runs_dir, write(tmp_path, edit(GOOD)))


def test_missing_certificate_and_loose_key_are_one_line_and_exit_2(tmp_path, runs_dir):
    deployment = write(tmp_path, GOOD)
    assert "certificate" in _bad_run(tmp_path, runs_dir, deployment) and "missing" in _bad_run(tmp_path, runs_dir, deployment)
    assert run_bench_cli("certs", str(deployment), timeout_s=60).returncode == 0
    (tmp_path / "certs" / "plant.key").chmod(0o644)
    assert "readable by others" in _bad_run(tmp_path, runs_dir, deployment)


def test_certs_command_writes_private_keys_and_refuses_to_replace_a_ca(tmp_path):
    deployment = write(tmp_path, GOOD)
    assert run_bench_cli("certs", str(deployment), timeout_s=60).returncode == 0
    keys = sorted(p.name for p in (tmp_path / "certs").glob("*.key"))
    assert "controller.key" in keys and "ca.key" in keys
    assert all((tmp_path / "certs" / k).stat().st_mode & 0o777 == 0o600 for k in keys)
    again = run_bench_cli("certs", str(deployment), timeout_s=60)
    assert again.returncode == 2 and "--force" in again.stderr


# ------------------------------------------------------------------------------------------------
# Three hosts
# ------------------------------------------------------------------------------------------------
PLACEMENT = {"sim": ["plant", "recorder"], "flight": ["controller"], "est": ["estimator"]}


@pytest.fixture
def lab():
    reason = netns_available()
    if reason:
        pytest.skip(reason)
    with NetnsLab(list(PLACEMENT)) as lab:   # namespaces deleted on the way out, also on failure
        yield lab


def test_rendezvous_across_three_namespaces_with_mtls_and_acl_equals_single_host(lab, tmp_path, runs_dir):
    deployment = tmp_path / "deploy.toml"
    deployment.write_text(deployment_toml(lab, PLACEMENT, launcher="sim", secure=True))
    assert run_bench_cli("certs", str(deployment), timeout_s=60).returncode == 0
    result, remote_codes = run_deployment(lab, deployment, PLACEMENT, "sim", "three-hosts", runs_dir,
                                          run_args=["--no-report"])
    assert result.returncode == 0, result.stderr + result.stdout
    assert remote_codes == {"controller": 0, "estimator": 0}   # stopped cleanly when the launcher left
    run_dir = runs_dir / "three-hosts"
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["processes"]["controller"]["host"] == "flight"
    assert metrics["process_stats"]["controller"]["published"]["command/thrust"] == 288
    with np.load(run_dir / "trajectory.npz") as data:
        trajectory = {k: data[k] for k in data.files}
    reference, _ = simulate_in_process(load_scenario("rendezvous_lqr"))
    scale = np.abs(reference["state_m_mps"]).max(axis=0)
    np.testing.assert_allclose(trajectory["state_m_mps"] / scale, reference["state_m_mps"] / scale, rtol=0, atol=1e-9)
    np.testing.assert_allclose(trajectory["thrust_n"], reference["thrust_n"], rtol=1e-9, atol=1e-15)
    # Every link was TLS: the logs of the remote nodes show the secure endpoints, never tcp/.
    # Clock offsets were measured per host; the namespaces share one kernel clock, so the true
    # offset is 0 and each estimate must contain it within its stated uncertainty.
    offsets = json.loads((run_dir / "clock_offsets.json").read_text())
    assert {offsets[n]["host"] for n in ("controller", "estimator", "plant")} == {"flight", "est", "sim"}
    for name in ("controller", "estimator"):
        assert abs(offsets[name]["offset_ns"]) <= offsets[name]["uncertainty_ns"], offsets[name]
    # The report moves the controller's and estimator's stamps (other hosts) by their offsets and
    # leaves the plant's (the recorder's host) alone.
    from bench.report.latency import merged_stamps, stamps_from_messages
    from bench.report.rundata import load_run

    run = load_run(run_dir)
    raw, corrected = stamps_from_messages(run), merged_stamps(run)
    k = max(raw)
    assert corrected[k]["commanded"] == raw[k]["commanded"] - offsets["controller"]["offset_ns"]
    assert corrected[k]["estimated"] == raw[k]["estimated"] - offsets["estimator"]["offset_ns"]
    assert corrected[k]["sensed"] == raw[k]["sensed"]


def test_router_deployment_runs_the_loop_through_a_router(lab, tmp_path, runs_dir):
    """`bench router` on the plant's host, every session connects to it, TLS and the ACL on every
    link including the router's (20 steps)."""
    deployment = tmp_path / "deploy.toml"
    deployment.write_text(deployment_toml(lab, PLACEMENT, launcher="sim", secure=True, router="sim"))
    assert run_bench_cli("certs", str(deployment), timeout_s=60).returncode == 0
    result, remote_codes = run_deployment(lab, deployment, PLACEMENT, "sim", "routed", runs_dir,
                                          run_args=["--no-report", "--steps", "20"], router="sim")
    assert result.returncode == 0, result.stderr + result.stdout
    assert remote_codes == {"controller": 0, "estimator": 0}
    metrics = json.loads((runs_dir / "routed" / "metrics.json").read_text())
    assert metrics["process_stats"]["plant"]["published"]["truth"] == 20


def test_node_on_the_wrong_host_and_router_without_one_are_one_line_and_exit_2(tmp_path, runs_dir):
    deployment = write(tmp_path, GOOD)
    assert run_bench_cli("certs", str(deployment), timeout_s=60).returncode == 0
    wrong = run_bench_cli("node", "controller", "--run-id", "r", "--scenario", "rendezvous_lqr", "--deployment",
                          str(deployment), "--host", "est", "--run-dir", str(runs_dir / "r"), timeout_s=60)
    assert wrong.returncode == 2 and "not placed on host 'est'" in wrong.stderr
    assert len(wrong.stderr.strip().splitlines()) == 1
    router = run_bench_cli("router", "--deployment", str(deployment), timeout_s=60)
    assert router.returncode == 2 and "names no router" in router.stderr
