"""Mutual TLS and access control: who may connect, who may command, who may speak.

Each refusal is shown next to its positive control (the same thing with the right certificate or
without the protection gets through), so every test can fail. Loopback only.
"""
import datetime as dt
import json
import socket
import subprocess
import sys
import time

import msgspec
import numpy as np
import pytest
import zenoh

from bench.bus import acl, data_auth, keys
from bench.bus import session as session_module
from bench.bus.certs import (
    CertificateError, Identity, check_identity, identity_files, issue, load_ca, make_ca, write_deployment_certs,
)
from bench.bus.schemas import ThrustCommand, TruthState, decode, encode, header
from bench.bus.session import SessionOptions, build_config, free_loopback_port, loopback_endpoint, open_session
from bench.scenario import load_scenario
from bench.launcher import make_local_certs
from bench.sim import simulate_in_process
from conftest import REPO, run_bench_cli

CONNECT_WAIT_S = 3.0   # how long a refused peer is given to get in anyway (a positive control connects in <1 s)


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    cert_dir = tmp_path_factory.mktemp("certs")
    return cert_dir, write_deployment_certs(cert_dir, "test", {n: ("127.0.0.1",) for n in acl.identities()})


@pytest.fixture
def hub(certs):
    _, ids = certs
    endpoint = loopback_endpoint(free_loopback_port(), "tls")
    session = open_session(SessionOptions(listen=(endpoint,), identity=ids["launcher"]))
    yield endpoint, session
    session.close()


def wait_until(predicate, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return predicate()


def peers(session) -> list:
    return list(session.info.peers_zid())


def open_unchecked(options: SessionOptions, monkeypatch):
    """A session whose own certificate check is skipped: what a careless or hostile peer runs."""
    monkeypatch.setattr(session_module, "check_identity", lambda identity: None)
    try:
        return open_session(options)
    finally:
        monkeypatch.undo()


# ------------------------------------------------------------------------------------------------
def test_session_without_certificate_cannot_connect(certs, hub):
    cert_dir, ids = certs
    endpoint, hub_session = hub
    # TLS, trusting the hub's CA, but presenting no certificate of its own.
    config = build_config(SessionOptions(connect=(endpoint,)))
    config.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(ids["controller"].ca_path)))
    anonymous = zenoh.open(config)
    try:
        assert not wait_until(lambda: peers(hub_session), CONNECT_WAIT_S)
        # Positive control: the same connection with the controller's certificate gets in.
        controller = open_session(SessionOptions(connect=(endpoint,), identity=ids["controller"]))
        try:
            assert wait_until(lambda: len(peers(hub_session)) == 1, 10.0)
        finally:
            controller.close()
    finally:
        anonymous.close()


def test_plain_tcp_endpoint_is_refused_by_a_secure_session(certs):
    _, ids = certs
    with pytest.raises(session_module.SessionConfigError, match="tls/ endpoints only"):
        build_config(SessionOptions(connect=("tcp/127.0.0.1:7447",), identity=ids["plant"]))


def test_certificate_of_another_authority_is_refused(certs, hub, tmp_path, monkeypatch):
    cert_dir, ids = certs
    endpoint, hub_session = hub
    foreign_ca = make_ca(tmp_path, "rogue")
    forged = issue(tmp_path, "controller", foreign_ca)   # CN = controller, wrong signer
    # It trusts the real CA (so only the hub's check of the client certificate can stop it).
    forged = Identity("controller", ids["controller"].ca_path, forged.cert_path, forged.key_path)
    with pytest.raises(CertificateError, match="not signed by the deployment's CA"):
        check_identity(forged)
    rogue = open_unchecked(SessionOptions(connect=(endpoint,), identity=forged), monkeypatch)
    try:
        assert not wait_until(lambda: peers(hub_session), CONNECT_WAIT_S)
    finally:
        rogue.close()


def test_expired_certificate_is_refused_with_a_clear_log_line(certs, hub, tmp_path, monkeypatch, capfd, runs_dir):
    cert_dir, ids = certs
    endpoint, hub_session = hub
    long_ago = dt.datetime.now(dt.timezone.utc) - dt.timedelta(days=400)
    expired = issue(tmp_path, "controller", load_ca(cert_dir), days=30, not_before=long_ago)
    expired = Identity("controller", ids["controller"].ca_path, expired.cert_path, expired.key_path)
    # The bench's own check: one line naming the file and the date, before any socket opens.
    with pytest.raises(CertificateError, match=r"certificate .*controller.pem' expired on \d{4}-\d\d-\d\d"):
        check_identity(expired)
    # A peer that skips the check is refused by the hub, which logs why.
    rogue = open_unchecked(SessionOptions(connect=(endpoint,), identity=expired), monkeypatch)
    try:
        assert not wait_until(lambda: peers(hub_session), CONNECT_WAIT_S)
    finally:
        rogue.close()
    captured = capfd.readouterr()   # zenoh writes its log to stdout
    assert "invalid peer certificate: certificate expired" in captured.out + captured.err
    # `bench node` with the expired certificate: exit 2 and the line, nothing started.
    (tmp_path / "ca.pem").write_bytes(ids["controller"].ca_path.read_bytes())
    result = run_bench_cli("node", "controller", "--run-id", "expired", "--scenario", "rendezvous_lqr",
                           "--cert-dir", str(tmp_path), "--connect", endpoint, "--run-dir", str(runs_dir / "x"),
                           timeout_s=60)
    assert result.returncode == 2
    assert "expired on" in result.stderr and len(result.stderr.strip().splitlines()) == 1


def test_private_key_readable_by_others_is_refused(certs, tmp_path):
    _, ids = certs
    key = tmp_path / "plant.key"
    key.write_bytes(ids["plant"].key_path.read_bytes())
    key.chmod(0o644)
    loose = Identity("plant", ids["plant"].ca_path, ids["plant"].cert_path, key)
    with pytest.raises(CertificateError, match="readable by others"):
        check_identity(loose)
    key.chmod(0o600)
    check_identity(loose)


def test_keys_are_written_private(certs):
    cert_dir, _ = certs
    for key in cert_dir.glob("*.key"):
        assert key.stat().st_mode & 0o777 == 0o600, key


def _collect(session, key_expr):
    got = []
    subscriber = session.declare_subscriber(key_expr, lambda s: got.append(str(s.key_expr)))
    return got, subscriber


def test_recorder_cannot_publish(certs, hub, monkeypatch):
    """The recorder's certificate, on a session that does not enforce the table itself (a hostile
    or broken recorder): its puts on data topics reach nobody; its subscription still works."""
    _, ids = certs
    endpoint, _ = hub
    plant = open_session(SessionOptions(connect=(endpoint,), identity=ids["plant"]))
    estimator = open_session(SessionOptions(connect=(endpoint,), identity=ids["estimator"]))
    recorder = open_session(SessionOptions(connect=(endpoint,), identity=ids["recorder"], access_control=False))
    try:
        at_plant, s1 = _collect(plant, keys.key("r", keys.COMMAND_THRUST))
        at_estimator, s2 = _collect(estimator, keys.key("r", keys.TRUTH))
        at_recorder, s3 = _collect(recorder, keys.all_topics("r"))
        plant_puts = 0

        def plant_put() -> bool:
            nonlocal plant_puts
            plant.put(keys.key("r", keys.TRUTH), b"{}")
            plant_puts += 1
            return True

        # Positive control: the plant's truth reaches the recorder and the estimator (whose truth
        # mode reads it), so the links are up and routed.
        assert wait_until(lambda: plant_put() and at_recorder and at_estimator, 10.0)
        for _ in range(20):
            recorder.put(keys.key("r", keys.COMMAND_THRUST), b"{}")
            recorder.put(keys.key("r", keys.TRUTH), b"{}")
            time.sleep(0.01)
        # One more allowed put, after the recorder's on the same links: once it is in, so would be
        # anything of the recorder's that got through (each link delivers in order).
        before = len(at_estimator)
        assert wait_until(lambda: plant_put() and len(at_estimator) > before, 10.0)
        time.sleep(0.2)
        assert at_plant == []
        assert len(at_estimator) <= plant_puts
    finally:
        for s in (recorder, estimator, plant):
            s.close()


def test_acl_table_denies_what_no_role_lists():
    config = acl.access_control_config()
    assert config["enabled"] is True and config["default_permission"] == "deny"
    sends = {r["id"]: r["key_exprs"] for r in config["rules"] if r["id"].endswith("-sends")}
    commanders = [rid for rid, exprs in sends.items() if any("/command/" in e for e in exprs if "applied" not in e)]
    assert commanders == ["controller-sends"]
    assert "recorder-sends" in sends and sends["recorder-sends"] == ["bench/*/status/stats/recorder"]


def test_only_the_plant_may_publish_the_attitude_sensors_and_the_estimator_reads_them():
    import zenoh

    from bench.bus import keys

    def matches(patterns, topic):
        return any(zenoh.KeyExpr(keys.key("*", p)).intersects(zenoh.KeyExpr(keys.key("run", topic))) for p in patterns)

    for topic in keys.SENSE_ATTITUDE_TOPICS:
        assert [name for name in acl.identities() if matches(acl.publications(name), topic)] == ["plant"], topic
        assert matches(acl.subscriptions("estimator"), topic) and not matches(acl.subscriptions("controller"), topic)


# ------------------------------------------------------------------------------------------------
# A rogue with the estimator's certificate tries to command the plant during a run.
# ------------------------------------------------------------------------------------------------
# Long enough for the rogue to be connected to the plant while the loop runs: it joins through the
# launcher's endpoint after the run has started, and a 60-step lock-step loop (about 0.1 s) was
# once over before it heard a truth sample (CI96, three test workers on two cores); 2000 steps
# (about 1.3 s) leave it that long (tests/test_forged_data.py's rogue the same).
STEPS = 2000


def _wait_port(port: int, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.05)
    raise TimeoutError(f"nothing listens on port {port}")


class RogueCommander:
    """Answers every truth sample of step k with its own thrust command for step k, at once:
    it wins the race against the real controller whenever its command is delivered first. signer:
    the run's data key (bench/bus/data_auth.py), for a rogue that could read the run's bus.key.
    It stops once the plant has applied max_applied of its commands (it reads command/applied): a
    plant flown by it for hundreds of steps diverges and ends the run. It counts what the plant
    applied, not what it sent: a rogue held up by a loaded host answers truth samples the plant has
    long passed, and once capped what it sent, it had given up before any of its commands could win
    (the CI run of stop 51)."""

    def __init__(self, session, run_id: str, signer=None, max_applied: int = 30):
        self.session, self.run_id, self.sent, self.applied, self.signer = session, run_id, 0, 0, signer
        self.max_applied = max_applied
        self.publisher = session.declare_publisher(keys.key(run_id, keys.COMMAND_THRUST))
        self.applied_subscriber = session.declare_subscriber(keys.key(run_id, keys.COMMAND_APPLIED), self._on_applied)
        self.subscriber = session.declare_subscriber(keys.key(run_id, keys.TRUTH), self._on_truth)

    def _on_applied(self, sample) -> None:
        if decode(sample.payload.to_bytes(), ThrustCommand).status == "rogue":
            self.applied += 1

    def _on_truth(self, sample) -> None:
        if self.applied >= self.max_applied:
            return
        k = decode(sample.payload.to_bytes(), TruthState).header.seq
        payload = encode(ThrustCommand(header(self.run_id, k, 0.0), [0.9, -0.9, 0.9], True, "rogue", 0.0))
        attachment = self.signer(str(self.publisher.key_expr), payload) if self.signer else None
        self.publisher.put(payload, attachment=attachment)
        self.sent += 1


def _run_key_signer(run_dir, timeout_s: float = 60.0):
    """A signer with the run's data key, read from its bus.key as soon as the launcher writes it."""
    deadline = time.monotonic() + timeout_s
    while not (run_dir / data_auth.KEY_FILE).is_file():
        assert time.monotonic() < deadline, f"no {data_auth.KEY_FILE} in {run_dir}"
        time.sleep(0.02)
    time.sleep(0.05)
    return data_auth.Signer(data_auth.read_key_file(run_dir / data_auth.KEY_FILE), "rogue")


def _run_with_rogue(runs_dir, run_id: str, identity, extra: list[str], with_run_key: bool = False) -> tuple[dict, int]:
    port = free_loopback_port()
    cmd = [sys.executable, "-m", "bench.cli", "run", "--run-id", run_id, "--runs-dir", str(runs_dir), "--steps",
           str(STEPS), "--port", str(port), "--no-progress", "--no-report", *extra]
    run = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    rogue_session = None
    try:
        _wait_port(port, 60.0)
        protocol = "tls" if identity else "tcp"
        rogue_session = open_session(SessionOptions(connect=(loopback_endpoint(port, protocol),), identity=identity,
                                                    access_control=False))
        rogue = RogueCommander(rogue_session, run_id, _run_key_signer(runs_dir / run_id) if with_run_key else None)
        out, err = run.communicate(timeout=300)
        assert run.returncode == 0, err + out
    finally:
        if run.poll() is None:
            run.kill()
        if rogue_session is not None:
            rogue_session.close()
    with np.load(runs_dir / run_id / "trajectory.npz") as data:
        return {k: data[k] for k in data.files}, rogue.sent


def _reference():
    scenario = load_scenario("rendezvous_lqr")
    scenario = msgspec.structs.replace(scenario, run=msgspec.structs.replace(scenario.run, steps=STEPS))
    reference, _ = simulate_in_process(scenario)
    return reference


def test_estimator_certificate_cannot_command_the_plant(runs_dir, tmp_path):
    """Secure run: the rogue holds the estimator's certificate (from the run's own CA) and reads
    truth, which the estimator may, but its commands never reach the plant: the trajectory is the
    clean one to 1e-9."""
    # The rogue needs the estimator's certificate before the run starts: make the run's CA here
    # (the same function `bench run --secure` uses) and hand it to the run with --cert-dir.
    run_id = "secure-rogue"
    cert_dir = make_local_certs(runs_dir / ".certs" / run_id)   # not in runs/<run_id>: the run claims it new
    trajectory, sent = _run_with_rogue(runs_dir, run_id, identity_files(cert_dir, "estimator"),
                                       ["--secure", "--cert-dir", str(cert_dir)])
    assert sent > 0   # the rogue saw the run (it may read truth) and tried
    reference = _reference()
    scale = np.abs(reference["state_m_mps"]).max(axis=0)
    np.testing.assert_allclose(trajectory["state_m_mps"] / scale, reference["state_m_mps"] / scale, rtol=0, atol=1e-9)
    np.testing.assert_allclose(trajectory["thrust_n"], reference["thrust_n"], rtol=1e-9, atol=1e-15)


def test_without_security_the_same_rogue_with_the_run_key_takes_over(runs_dir):
    """The control: a plain run, the same rogue without any certificate but holding the run's data
    key (any process of the user who started the run can read runs/<id>/bus.key), and the plant
    flies its commands (the trajectory leaves the clean one). Without the key its commands are
    dropped: tests/test_forged_data.py."""
    trajectory, sent = _run_with_rogue(runs_dir, "plain-rogue", None, [], with_run_key=True)
    assert sent > 0
    assert np.any(np.all(np.isclose(trajectory["thrust_n"], [0.9, -0.9, 0.9]), axis=1))
    reference = _reference()
    assert np.abs(trajectory["state_m_mps"] - reference["state_m_mps"]).max() > 1.0


def test_every_node_has_an_access_control_role():
    """A node without a role would be denied everything in a secure run: fail here instead."""
    from bench.runtime.node import NODES

    assert set(NODES) <= set(acl.ROLES)


def test_attitude_loop_with_the_can_board_runs_secure_and_equals_the_plain_run(runs_dir):
    """The attitude loop's topics (sense/gyro, sense/mag, sense/star, truth/attitude, estimate/attitude,
    command/dipole, actuator/mtq) and the CAN channels over Zenoh pass the access-control table:
    a secure lock-step run is the plain run, sample for sample."""
    trajectories = {}
    for name, extra in (("plain", []), ("secure", ["--secure"])):
        result = run_bench_cli("run", "attitude_quick", "--run-id", f"att-{name}", "--runs-dir", str(runs_dir),
                               "--no-progress", "--no-report", *extra, timeout_s=300)
        assert result.returncode == 0, result.stderr + result.stdout
        with np.load(runs_dir / f"att-{name}" / "trajectory.npz") as data:
            trajectories[name] = {k: data[k] for k in ("att_omega_radps", "att_q_wxyz", "att_dipole_applied_am2")}
    assert np.abs(trajectories["plain"]["att_dipole_applied_am2"]).max() > 0   # the board applied commands
    for key, plain in trajectories["plain"].items():
        np.testing.assert_array_equal(trajectories["secure"][key], plain)
