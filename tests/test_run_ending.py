"""A run always ends clean: the launcher's children die with it, a second Ctrl-C is prompt,
divergence stops the run with its own exit code, and every ending that leaves data leaves
metrics.json (valid JSON, marked partial with the reason) and the report."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from bench.plant.divergence import EXIT_DIVERGED, check_state
from bench.plant.node import STATE_NAMES
from bench.report.jsonout import dumps_finite
from bench.scenario import load_scenario
from bench.sim import simulate_in_process
from conftest import REPO, bench_processes, node_pids, parent_pid, process_cmdline, run_bench_cli

ORPHAN_LIMIT_S = 2.0


def strict_json(path):
    """Parse as a strict JSON reader would: NaN / Infinity literals are an error."""
    def refuse(literal):
        raise AssertionError(f"{path.name} holds the non-JSON literal {literal}")
    return json.loads(path.read_text(), parse_constant=refuse)


def start_run(runs_dir, run_id, *extra, node_start="zygote"):
    """node_start: how the launcher starts its nodes (BENCH_NODE_START): forked from its
    pre-imported zygote (the default) or each by exec."""
    cmd = [sys.executable, "-m", "bench.cli", "run", "--mode", "real-time", "--steps", "2000", "--run-id", run_id,
           "--runs-dir", str(runs_dir), "--no-progress", *extra]
    env = {**os.environ, "BENCH_NODE_START": node_start}
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:   # until the plant is stepping
        log = runs_dir / run_id / "logs" / "plant.log"
        if log.exists() and "peers ready" in log.read_text():
            time.sleep(0.5)              # a few steps of data
            return proc
        time.sleep(0.1)
    proc.kill()
    raise AssertionError("run did not start within 60 s")


def children_of(proc) -> list[int]:
    """Every process below the launcher: its nodes, their watchdogs and, on the zygote path, the
    zygote the nodes were forked from."""
    parent_of = {p: parent_pid(p) for p in bench_processes_all()}
    pids, frontier = [], {proc.pid}
    while frontier:
        frontier = {p for p, parent in parent_of.items() if parent in frontier}
        pids += sorted(frontier)
    assert len(node_pids(pids)) >= 4, pids        # recorder, plant, estimator, controller
    return pids


def bench_processes_all() -> list[int]:
    return [int(e) for e in os.listdir("/proc") if e.isdigit()]


def alive_by_ps(pids: list[int]) -> list[str]:
    """`ps` rows of the pids that still exist and are not zombies."""
    out = subprocess.run(["ps", "-o", "pid=,stat=,args=", "-p", ",".join(map(str, pids))], capture_output=True, text=True)
    return [row for row in out.stdout.splitlines() if row.split()[1][0] != "Z"]


@pytest.mark.parametrize("sig,node_start", [(signal.SIGKILL, "zygote"), (signal.SIGKILL, "exec"),
                                            (signal.SIGTERM, "zygote")],
                         ids=["SIGKILL-zygote", "SIGKILL-exec", "SIGTERM-zygote"])
def test_children_die_with_the_launcher(runs_dir, sig, node_start):
    run_id = f"owner-{sig.name.lower()}-{node_start}"
    proc = start_run(runs_dir, run_id, node_start=node_start)
    pids = children_of(proc)
    parents = {parent_pid(p) for p in node_pids(pids)}
    if node_start == "zygote":       # the path under test was taken: every node forked by the zygote
        assert len(parents) == 1 and b"bench.runtime.zygote" in process_cmdline(parents.pop())
    else:
        assert parents == {proc.pid}
    proc.send_signal(sig)
    _, stderr = proc.communicate(timeout=60)
    time.sleep(ORPHAN_LIMIT_S)
    assert alive_by_ps(pids) == [], stderr
    assert bench_processes(str(runs_dir / run_id)) == []     # nor anything they started
    if sig == signal.SIGTERM:
        assert proc.returncode == 143
        metrics = strict_json(runs_dir / run_id / "metrics.json")
        assert metrics["partial"] is True and metrics["end_reason"] == "interrupted by SIGTERM"
        assert metrics["steps"] > 0
        assert (runs_dir / run_id / "report.html").is_file()


def test_second_ctrl_c_exits_promptly(runs_dir):
    run_id = "double-sigint"
    proc = start_run(runs_dir, run_id)
    pids = children_of(proc)
    proc.send_signal(signal.SIGINT)
    time.sleep(0.3)
    proc.send_signal(signal.SIGINT)
    proc.communicate(timeout=3.0)          # the bound; the launcher arms a 2.5 s hard exit
    assert proc.returncode == 130
    time.sleep(ORPHAN_LIMIT_S)
    assert alive_by_ps(pids) == []


def test_ctrl_c_leaves_partial_metrics_and_report(runs_dir):
    run_id = "one-sigint"
    proc = start_run(runs_dir, run_id)
    proc.send_signal(signal.SIGINT)
    proc.communicate(timeout=60)
    assert proc.returncode == 130
    run_dir = runs_dir / run_id
    metrics = strict_json(run_dir / "metrics.json")
    assert metrics["partial"] is True and metrics["end_reason"] == "interrupted by SIGINT"
    assert 0 < metrics["steps"] < 2000
    assert "partial" in strict_json(run_dir / "metrics.json") and (run_dir / "report.md").is_file()
    assert "Partial run" in (run_dir / "report.md").read_text()


def test_a_killed_child_leaves_partial_metrics_and_report(runs_dir):
    run_id = "killed-estimator"
    proc = start_run(runs_dir, run_id)
    victim = next(p for p in node_pids(children_of(proc)) if b"estimator" in process_cmdline(p))
    os.kill(victim, signal.SIGKILL)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 1 and "process 'estimator'" in stderr
    metrics = strict_json(runs_dir / run_id / "metrics.json")
    assert metrics["partial"] is True and "estimator" in metrics["end_reason"]
    assert (runs_dir / run_id / "report.html").is_file()


# --- divergence ---------------------------------------------------------------------------------
def test_divergence_ends_the_run_naming_step_and_quantity(tmp_path, runs_dir):
    # From A the tuned LQR's speed peaks at 112 m/s at step 4 (in-process reference): a 100 m/s
    # limit must stop the run exactly there, as a state blown up by a bad command would.
    limit_mps = 100.0
    path = tmp_path / "diverge.toml"
    path.write_text(f'name = "diverge"\n[run]\nsteps = 20\n[plant.divergence]\nmax_abs_velocity_mps = {limit_mps}\n')
    scenario = load_scenario(str(path))
    reference, _ = simulate_in_process(scenario)
    expected_step = next(k for k, x in enumerate(reference["state_m_mps"]) if np.abs(x[3:]).max() > limit_mps)
    expected = check_state(expected_step, reference["state_m_mps"][expected_step], STATE_NAMES,
                           [1e8] * 3 + [limit_mps] * 3)
    result = run_bench_cli("run", str(path), "--run-id", "diverge", "--runs-dir", str(runs_dir), "--no-progress")
    assert result.returncode == EXIT_DIVERGED, result.stderr
    line = next(l for l in result.stderr.splitlines() if "diverged" in l)
    assert f"step {expected_step}:" in line and expected.quantity in line, line
    metrics = strict_json(runs_dir / "diverge" / "metrics.json")
    assert metrics["partial"] is True and "diverged" in metrics["end_reason"]
    assert metrics["exit_code"] == EXIT_DIVERGED


def test_non_finite_state_is_divergence_and_metrics_stay_valid_json(tmp_path):
    divergence = check_state(7, [1.0, float("nan"), 0.0, 0.0, 0.0, 0.0], STATE_NAMES, [1e8] * 3 + [1e4] * 3)
    assert divergence.step == 7 and divergence.quantity == "y_m" and divergence.value is None
    text = dumps_finite({"a": float("nan"), "b": [1.0, float("inf")], "c": np.float64("-inf"), "d": np.arange(2)})
    assert json.loads(text, parse_constant=lambda c: pytest.fail(c)) == {"a": None, "b": [1.0, None], "c": None, "d": [0, 1]}


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")   # the dropped exception, on purpose
def test_a_signal_whose_exception_python_dropped_still_ends_the_run():
    """The handler runs wherever the main thread is, here inside a weakref callback (an import's
    module lock, as in CI105). It raises nothing there (an exception there was dropped, or left
    the module lock half taken); the launcher's waits ask the guard at every look, and it raises
    then, once."""
    import gc
    import weakref

    from bench.launcher import RunInterrupted, SignalGuard

    class Freed:
        pass

    guard = SignalGuard(group=None)
    guard.check()                                   # no signal: nothing to raise
    freed = Freed()
    ref = weakref.ref(freed, lambda _: guard._handle(signal.SIGINT, None))
    del freed                                       # the handler runs in the callback, and raises nothing there
    gc.collect()
    assert ref() is None and guard.first == signal.SIGINT
    with pytest.raises(RunInterrupted) as raised:
        guard.check()
    assert raised.value.signum == signal.SIGINT
    guard.check()                                   # delivered: not raised a second time during the cleanup
