"""The control plane authenticated: liveliness, readiness and clock readings are presence answers
signed under the run's key (bench/bus/presence.py), so nothing without the key can declare a node
ready, hide a stopped one, or time one.

The attacks of issue 44, each rerun: a process without any key answered `ready` for the estimator
and the plant started before it subscribed (4 runs of 5 failed); a rogue holding the liveliness
token of a SIGSTOPped controller hid it (110 of 120 real-time steps missed, then "exited with code
-9"); one forged clock reply made metrics.json say plant -> estimator 7000.6 ms.
"""
import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from bench.bus import clock_sync, data_auth, keys
from bench.bus.presence import NONCE_HEX, PRESENCE, PresenceQuery, PresenceResponder, PresenceWatcher
from bench.bus.session import SessionOptions, free_loopback_port, loopback_endpoint, open_session
from conftest import REPO, assert_rendezvous_lqr_run_equals_in_process, bench_processes, node_pid
from recording_helpers import session_pair

RUN = "cp-test"
KEY = bytes(range(32))
OTHER_KEY = bytes(32)


class RogueAnswer:
    """A queryable on a node's presence key that answers what a rogue chooses: ready, a clock
    7 s ahead, with no tag, another key's tag, or a genuine answer recorded earlier."""

    def __init__(self, session, run_id: str, name: str, key: bytes | None = None, recorded: tuple | None = None,
                 clock_offset_ns: int = 0):
        self.key_expr = keys.key(run_id, f"{PRESENCE}/{name}")
        self.name, self.key, self.recorded, self.offset = name, key, recorded, clock_offset_ns
        self.queryable = session.declare_queryable(self.key_expr, self.answer)

    def answer(self, query) -> None:
        if self.recorded is not None:
            payload, attachment = self.recorded
        else:
            nonce = query.payload.to_bytes().decode()
            payload = json.dumps({"process": self.name, "host": "rogue", "ready": True,
                                  "monotonic_ns": time.monotonic_ns() + self.offset, "nonce": nonce}).encode()
            attachment = (data_auth.tag(self.key, self.key_expr, payload, self.name.encode(), 1)
                          if self.key is not None else None)
        query.reply(self.key_expr, payload, attachment=attachment)


def test_only_answers_signed_under_the_run_key_for_this_query_count():
    with session_pair() as (node_session, asker_session):
        genuine = PresenceResponder(node_session, RUN, "estimator", KEY)
        query = PresenceQuery(asker_session, RUN, KEY)
        time.sleep(0.3)
        answers = query.ask()
        assert set(answers) == {"estimator"} and answers["estimator"].ready is False
        genuine.ready = True
        assert query.ask()["estimator"].ready is True

        # Capture a genuine answer as a rogue on the bus could, then replay it to a new query.
        captured = []
        asker_session.get(keys.key(RUN, f"{PRESENCE}/estimator"),
                          lambda reply: captured.append((reply.ok.payload.to_bytes(), reply.ok.attachment.to_bytes())),
                          payload=b"0" * NONCE_HEX, timeout=1.0)
        time.sleep(0.5)
        assert captured
        genuine.undeclare()
        rogues = [RogueAnswer(node_session, RUN, "controller"),                        # no tag
                  RogueAnswer(node_session, RUN, "planner", key=OTHER_KEY),            # another run's key
                  RogueAnswer(node_session, RUN, "estimator", recorded=captured[0]),   # a replay
                  RogueAnswer(node_session, RUN, "recorder", key=KEY)]                 # a genuine tag, but
        rogues[-1].name = "plant"    # ... for another name than its key's: the recorder's key answering as the plant
        time.sleep(0.3)
        before = query.refused
        assert query.ask() == {}
        assert query.refused - before == 4


def test_a_rogue_holding_a_stopped_node_s_token_and_key_does_not_hide_it():
    """The watcher sees a node silent once it stops answering, whatever answers without the key
    (and whatever liveliness token anyone holds) on its behalf."""
    with session_pair() as (node_session, watcher_session):
        genuine = PresenceResponder(node_session, RUN, "controller", KEY)
        watcher = PresenceWatcher(watcher_session, RUN, KEY, ["controller"], lease_s=0.4).start()
        try:
            time.sleep(0.6)
            assert watcher.silent_since("controller") is None
            token = node_session.liveliness().declare_token(keys.key(RUN, f"{keys.ALIVE}/controller"))
            rogue = RogueAnswer(node_session, RUN, "controller")
            genuine.undeclare()                   # what a SIGSTOPped process answers: nothing
            stopped = time.monotonic()
            deadline = stopped + 5.0
            while watcher.silent_since("controller") is None and time.monotonic() < deadline:
                time.sleep(0.02)
            assert watcher.silent_since("controller") is not None, "the rogue hid the silent node"
            assert time.monotonic() - stopped < 0.4 + 2 * watcher.period_s + 0.5
            assert watcher.query.refused > 0
            rogue.queryable.undeclare()
            token.undeclare()
        finally:
            watcher.stop()


def test_a_forged_clock_reply_moves_no_offset():
    with session_pair() as (node_session, recorder_session):
        PresenceResponder(node_session, RUN, "estimator", KEY)
        RogueAnswer(node_session, RUN, "plant", clock_offset_ns=7_000_000_000)
        RogueAnswer(node_session, RUN, "controller", key=OTHER_KEY, clock_offset_ns=7_000_000_000)
        time.sleep(0.3)
        query = PresenceQuery(recorder_session, RUN, KEY)
        offsets = clock_sync.estimate_offsets(query, rounds=3)
        assert set(offsets) == {"estimator"}
        # One host, one CLOCK_MONOTONIC: the true offset is 0, inside the stated uncertainty.
        assert abs(offsets["estimator"].offset_ns) <= offsets["estimator"].uncertainty_ns < 50_000_000
        assert query.refused == 6


def _rogue_session(port: int):
    deadline = time.monotonic() + 60
    while True:
        try:
            return open_session(SessionOptions(connect=(loopback_endpoint(port),)))
        except Exception:   # noqa: BLE001 - the hub is not up yet
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def test_fake_readiness_without_the_key_changes_nothing(runs_dir):
    """The controller is external and not started yet; a rogue answers `ready` for it (and
    declares its old liveliness tokens). Nothing starts: the plant and the launcher wait for the
    real controller, refusing the rogue's answers; once it comes, the lock-step run equals the
    in-process loop."""
    port = free_loopback_port()
    run_id = "fake-ready"
    steps = 30
    run_dir = runs_dir / run_id
    cmd = [sys.executable, "-m", "bench.cli", "run", "--steps", str(steps), "--run-id", run_id, "--port", str(port),
           "--runs-dir", str(runs_dir), "--no-progress", "--no-report", "--external", "controller"]
    launcher = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    session = _rogue_session(port)
    controller = None
    try:
        rogue = RogueAnswer(session, run_id, "controller")
        tokens = [session.liveliness().declare_token(keys.key(run_id, f"{kind}/controller")) for kind in ("alive", "ready")]
        plant_log = run_dir / "logs" / "plant.log"
        deadline = time.monotonic() + 90
        while not (plant_log.exists() and "bench.presence WARNING" in plant_log.read_text()):
            assert time.monotonic() < deadline and launcher.poll() is None, "the plant never asked"
            time.sleep(0.1)
        time.sleep(1.0)
        assert "peers ready" not in plant_log.read_text() and launcher.poll() is None
        controller = subprocess.Popen([sys.executable, "-m", "bench.cli", "node", "controller", "--run-id", run_id,
                                       "--scenario", str(run_dir / "scenario.json"), "--connect", loopback_endpoint(port),
                                       "--run-dir", str(run_dir)], cwd=REPO, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL)
        _, stderr = launcher.communicate(timeout=180)
        assert controller.wait(timeout=60) == 0
    finally:
        session.close()
        for process in (launcher, controller):
            if process is not None and process.poll() is None:
                process.kill()
    assert rogue is not None and tokens
    assert launcher.returncode == 0, stderr
    assert_rendezvous_lqr_run_equals_in_process(run_dir, steps)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["process_stats"]["plant"]["unauthentic"]["forged"]["presence"] > 0


def test_a_stopped_controller_is_named_while_a_rogue_answers_for_it(runs_dir):
    """The SIGSTOPped controller of a real-time run, with a rogue holding `alive/controller` and
    answering its presence without the key: the launcher names the controller, exit 1."""
    port = free_loopback_port()
    run_id = "hidden-hang"
    cmd = [sys.executable, "-m", "bench.cli", "run", "--mode", "real-time", "--steps", "2000", "--run-id", run_id,
           "--port", str(port), "--runs-dir", str(runs_dir), "--no-progress", "--no-report"]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    session = _rogue_session(port)
    pid = None
    try:
        token = session.liveliness().declare_token(keys.key(run_id, f"{keys.ALIVE}/controller"))
        deadline = time.monotonic() + 90
        log = runs_dir / run_id / "logs" / "plant.log"
        while not (log.exists() and "peers ready" in log.read_text()):
            assert time.monotonic() < deadline and proc.poll() is None, "the run did not start"
            time.sleep(0.1)
        rogue = RogueAnswer(session, run_id, "controller")
        pid = node_pid(str(runs_dir / run_id), "controller")
        os.kill(pid, signal.SIGSTOP)
        _, stderr = proc.communicate(timeout=120)
    finally:
        if pid is not None:
            try:
                os.kill(pid, signal.SIGCONT)
            except ProcessLookupError:
                pass
        session.close()
        if proc.poll() is None:
            proc.kill()
    assert token is not None and rogue is not None
    assert proc.returncode == 1, stderr
    assert "process 'controller'" in stderr and "is stopped" in stderr, stderr
    deadline = time.monotonic() + 10
    while bench_processes(str(runs_dir / run_id)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert bench_processes(str(runs_dir / run_id)) == []


def test_an_outside_node_without_the_key_is_named_with_its_refused_answers(runs_dir, tmp_path):
    """An outside estimator that cannot read the run's key answers presence unsigned: the run never
    starts, and the launcher says why instead of only "not alive"."""
    import msgspec

    from bench.scenario import load_scenario

    scenario = msgspec.to_builtins(load_scenario("rendezvous_smoother"))
    scenario["run"]["liveliness"]["startup_timeout_s"] = 5.0
    scenario["run"]["steps"] = 5
    scenario_path = tmp_path / "short_start.json"
    scenario_path.write_text(json.dumps(scenario))
    port = free_loopback_port()
    run_id = "unsigned-outside"
    run_dir = runs_dir / run_id
    launcher = subprocess.Popen([sys.executable, "-m", "bench.cli", "run", str(scenario_path), "--run-id", run_id,
                                 "--port", str(port), "--runs-dir", str(runs_dir), "--no-progress", "--no-report",
                                 "--external", "estimator"],
                                cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    outside = None
    try:
        deadline = time.monotonic() + 60
        while not (run_dir / "scenario.json").is_file():
            assert time.monotonic() < deadline and launcher.poll() is None
            time.sleep(0.05)
        elsewhere = tmp_path / "elsewhere"          # no bus.key there: the node signs nothing
        elsewhere.mkdir()
        outside = subprocess.Popen([sys.executable, "-m", "bench.cli", "node", "estimator", "--run-id", run_id,
                                    "--scenario", str(scenario_path), "--connect", loopback_endpoint(port),
                                    "--run-dir", str(elsewhere)], cwd=REPO, stdout=subprocess.DEVNULL,
                                   stderr=subprocess.DEVNULL)
        _, stderr = launcher.communicate(timeout=120)
    finally:
        for process in (launcher, outside):
            if process is not None and process.poll() is None:
                process.kill()
    assert launcher.returncode == 1, stderr
    assert "processes not alive after" in stderr and "estimator: " in stderr, stderr
    assert "presence answer(s) refused, not signed under the run's key" in stderr, stderr
    assert "peers ready" not in (run_dir / "logs" / "plant.log").read_text()


def test_messages_dropped_for_their_tag_are_named_with_their_publisher(tmp_path):
    from bench.launcher import unauthentic_drops

    stats = {"controller": {"unauthentic": {"forged": {"estimate/translation": 40}}}, "plant": {"published": {}}}
    [line] = unauthentic_drops(stats, tmp_path)
    assert line.startswith("estimate/translation from 'estimator' dropped as forged by 'controller': 40")
