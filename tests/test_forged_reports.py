"""A rogue peer on a plain run's bus forges the launcher's inputs: process statistics, the plant's
step reports (the last one, "finished", included) and altered copies of the genuine signed ones.
The run's metrics.json and trajectory are those of the same run without the rogue; the launcher
counts what it dropped. Loopback only."""
from __future__ import annotations

import json
import subprocess
import sys
import threading

import msgspec
import numpy as np

from bench.bus import keys
from bench.bus.schemas import ProcessStats, StepDone, decode, encode, header
from bench.bus.session import SessionOptions, free_loopback_port, loopback_endpoint, open_session
from conftest import REPO
from test_security import _wait_port

STEPS = 20
FORGE_PERIOD_S = 0.005
PROCESSES = ("recorder", "plant", "estimator", "controller")


class RogueReporter:
    """Every FORGE_PERIOD_S: stats for each process of the run (one command published, one
    unsigned, one with a made-up signature) and a 'finished' step report. Every genuine report it
    sees is sent again with other contents under the genuine signature."""

    def __init__(self, session, run_id: str):
        self.session, self.run_id = session, run_id
        self.sent = 0
        self.stop = threading.Event()
        self.subscribers = [session.declare_subscriber(keys.key(run_id, keys.STATUS_STEP), self._alter_step),
                            session.declare_subscriber(keys.key(run_id, f"{keys.STATUS_STATS}/*"), self._alter_stats)]
        self.thread = threading.Thread(target=self._forge, daemon=True)
        self.thread.start()

    def _put(self, topic: str, message) -> None:
        self.session.put(keys.key(self.run_id, topic), encode(message))
        self.sent += 1

    def _forge(self) -> None:
        fake_mac = "0" * 64
        while not self.stop.wait(FORGE_PERIOD_S):
            for name in PROCESSES:
                for mac in ("", fake_mac):
                    stats = ProcessStats(header(self.run_id, 0, 0.0), name, {keys.COMMAND_THRUST: 1}, {keys.TRUTH: 5},
                                         mac=mac)
                    self._put(f"{keys.STATUS_STATS}/{name}", stats)
            self._put(keys.STATUS_STEP, StepDone(header(self.run_id, STEPS - 1, 0.0), STEPS, True, mac=fake_mac))

    def _alter_step(self, sample) -> None:
        message = decode(sample.payload.to_bytes(), StepDone)
        if message.mac and not message.finished:
            altered = msgspec.structs.replace(message, header=header(self.run_id, STEPS - 1, 0.0), finished=True)
            self._put(keys.STATUS_STEP, altered)

    def _alter_stats(self, sample) -> None:
        message = decode(sample.payload.to_bytes(), ProcessStats)
        if message.mac and message.published.get(keys.COMMAND_THRUST, 0) > 1:
            self._put(f"{keys.STATUS_STATS}/{message.process}",
                      msgspec.structs.replace(message, published={keys.COMMAND_THRUST: 1}))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=5)
        for subscriber in self.subscribers:
            subscriber.undeclare()


def _start(runs_dir, run_id: str, steps: int) -> tuple[subprocess.Popen, int]:
    port = free_loopback_port()
    cmd = [sys.executable, "-m", "bench.cli", "run", "rendezvous_lqr", "--run-id", run_id, "--runs-dir", str(runs_dir),
           "--steps", str(steps), "--port", str(port), "--no-progress", "--no-report"]
    return subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True), port


def _finish(runs_dir, run_id: str, run: subprocess.Popen) -> tuple[dict, dict]:
    try:
        out, err = run.communicate(timeout=120)
    finally:
        if run.poll() is None:
            run.kill()
    assert run.returncode == 0, err + out
    metrics = json.loads((runs_dir / run_id / "metrics.json").read_text())
    with np.load(runs_dir / run_id / "trajectory.npz") as data:
        trajectory = {k: data[k] for k in ("state_m_mps", "thrust_n")}
    return metrics, trajectory


def comparable(metrics: dict) -> dict:
    """metrics.json without what differs between any two runs (times, pids) and the drop counts
    (the launcher's `forged` and `replayed`, the nodes' `unauthentic`: their data-topic MAC)."""
    varying = {"wall_time_s", "end_to_end_latency", "sense_to_plant_latency", "processes"}
    kept = {k: v for k, v in metrics.items() if k not in varying}
    kept["process_stats"] = {name: {k: v for k, v in entry.items() if k not in ("forged", "replayed", "unauthentic")}
                             for name, entry in metrics["process_stats"].items()}
    kept["exit_codes"] = {name: p["exit_code"] for name, p in metrics["processes"].items()}
    return kept


def attacked_beside_clean(runs_dir, prefix: str, steps: int, make_rogue):
    """A clean run and an attacked one side by side (bounded time: a lock-step run's numbers do not
    depend on the machine's load); `make_rogue(session, run_id)` joins the attacked run's hub.
    Returns (rogue, (attacked metrics, trajectory), (clean metrics, trajectory))."""
    clean_run, _ = _start(runs_dir, f"{prefix}-clean", steps)
    attacked_run, port = _start(runs_dir, f"{prefix}-rogue", steps)
    session = rogue = None
    try:
        _wait_port(port, 60.0)
        session = open_session(SessionOptions(connect=(loopback_endpoint(port),)))
        rogue = make_rogue(session, f"{prefix}-rogue")
        attacked = _finish(runs_dir, f"{prefix}-rogue", attacked_run)
        clean = _finish(runs_dir, f"{prefix}-clean", clean_run)
    finally:
        for run in (clean_run, attacked_run):
            if run.poll() is None:
                run.kill()
        if rogue is not None:
            rogue.close()
        if session is not None:
            session.close()
    return rogue, attacked, clean


def test_forged_reports_change_nothing_in_a_plain_run(runs_dir):
    rogue, (attacked, attacked_trajectory), (clean, clean_trajectory) = attacked_beside_clean(
        runs_dir, "reports", STEPS, RogueReporter)
    sent = rogue.sent
    assert sent > 0
    assert attacked["process_stats"]["controller"]["published"][keys.COMMAND_THRUST] == STEPS
    assert comparable(attacked) == comparable(clean)
    for key, values in clean_trajectory.items():
        np.testing.assert_array_equal(attacked_trajectory[key], values)
    # The rogue reached the launcher: it dropped forgeries naming each process, and counted them.
    forged = {name: entry.get("forged", 0) for name, entry in attacked["process_stats"].items()}
    assert all(forged.get(name, 0) > 0 for name in PROCESSES), forged
    assert all("forged" not in entry for entry in clean["process_stats"].values())
    # The recorder took only the processes' own stats (the forged ones fail the data-topic MAC).
    counts = json.loads((runs_dir / "reports-rogue" / "recorder_counts.json").read_text())
    assert counts["publishers"]["controller"][keys.COMMAND_THRUST] == STEPS
    assert attacked["process_stats"]["recorder"]["unauthentic"]["forged"][f"{keys.STATUS_STATS}/controller"] > 0
