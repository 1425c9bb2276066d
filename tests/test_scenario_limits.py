"""Validation at the edge: every value the issue found getting through is refused with exit 2 and
one line naming the field, before any process starts or any directory is written."""
from __future__ import annotations

import fcntl
import os

import pytest

from bench.scenario import MAX_SCENARIO_BYTES, ScenarioError, parse_scenario
from conftest import bench_processes, run_bench_cli

BAD = {
    # case: (scenario text, text the one line must contain)
    "infinite time factor": ('name = "x"\n[run]\ntime_factor = inf\n', "run.time_factor: must be a finite number"),
    "nan in the initial state": ('name = "x"\n[plant]\ninitial_state_m_mps = [1.0, nan, 0.0, 0.0, 0.0, 0.0]\n',
                                 "plant.initial_state_m_mps[1]: must be a finite number"),
    "nan weight": ('name = "x"\n[controller]\nq_diag = [1.0, 1.0, 1.0, 1.0, 1.0, -nan]\n', "controller.q_diag[5]"),
    "1e10 steps": ('name = "x"\n[run]\nsteps = 1e10\n', "run.steps"),
    "huge integer steps": ('name = "x"\n[run]\nsteps = 10000000000\n', "run.steps"),
    "mpc horizon 1e5": ('name = "x"\n[controller]\ntype = "mpc"\nhorizon = 100000\n', "controller.horizon"),
    "time factor 1e-6": ('name = "x"\n[run]\ntime_factor = 1e-6\n', "run.time_factor"),
    "real-time step of an hour": ('name = "x"\n[run]\nmode = "real-time"\ntime_factor = 0.1\n', "run.time_factor"),
    "50k nested brackets": ('name = "x"\nz = ' + "[" * 50_000 + "\n", "nested deeper"),
    "empty name": ('name = ""\n', "name"),
    "name that is a path": ('name = "../up"\n', "name"),
    "huge mass": ('name = "x"\n[plant]\nmass_kg = 1e300\n', "plant.mass_kg"),
    "absurd initial state": ('name = "x"\n[plant]\ninitial_state_m_mps = [1e20, 0.0, 0.0, 0.0, 0.0, 0.0]\n',
                             "plant.initial_state_m_mps"),
    "huge weight list": ('name = "x"\n[controller]\nr_diag = [' + ", ".join(["1.0"] * 5000) + "]\n", "controller.r_diag"),
    "real-time priority above SCHED_FIFO's 99": ('name = "x"\n[run]\nrealtime_priority = 100\n', "run.realtime_priority"),
    "negative lease": ('name = "x"\n[run.liveliness]\nlease_s = -1.0\n', "run.liveliness.lease_s"),
    "oversized file": ('name = "x"\n' + "# padding\n" * (MAX_SCENARIO_BYTES // 10 + 1), "at most"),
}


def assert_refused(result, must_contain: str) -> None:
    assert result.returncode == 2, result.stderr + result.stdout
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert must_contain in lines[0], lines[0]


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_scenario_exits_2_with_one_line_and_starts_nothing(tmp_path, runs_dir, case):
    text, must_contain = BAD[case]
    path = tmp_path / "bad.toml"
    path.write_text(text)
    run_id = "limits-" + "".join(c if c.isalnum() else "-" for c in case)
    result = run_bench_cli("run", str(path), "--run-id", run_id, "--runs-dir", str(runs_dir), "--no-progress")
    assert_refused(result, must_contain)
    assert not runs_dir.exists()
    assert bench_processes(run_id) == []


@pytest.mark.parametrize("run_id", ["..", ".", "-x", "a/b", "x" * 65, ""])
def test_unsafe_run_id_exits_2(runs_dir, run_id):
    result = run_bench_cli("run", f"--run-id={run_id}", "--runs-dir", str(runs_dir), "--no-progress")
    assert_refused(result, "run id")
    assert not runs_dir.exists()


@pytest.mark.parametrize("flag, value", [("--steps", "10000000000"), ("--steps", "0")])
def test_bad_override_exits_2(runs_dir, flag, value):
    result = run_bench_cli("run", flag, value, "--run-id", "override", "--runs-dir", str(runs_dir))
    assert_refused(result, "--steps")


def test_a_live_run_id_is_refused(runs_dir):
    # What a running launcher holds: its run directory, flock-ed for the run's lifetime.
    run_dir = runs_dir / "live"
    run_dir.mkdir(parents=True)
    with open(run_dir / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        lock.write(str(os.getpid()))
        lock.flush()
        result = run_bench_cli("run", "--run-id", "live", "--runs-dir", str(runs_dir), "--no-progress")
    assert_refused(result, "in use by a running bench")
    assert sorted(p.name for p in run_dir.iterdir()) == [".lock"]     # nothing written into it
    assert bench_processes("live") == []


def test_a_finished_run_is_not_overwritten(runs_dir):
    run_dir = runs_dir / "done"
    run_dir.mkdir(parents=True)
    (run_dir / "metrics.json").write_text("{}")
    (run_dir / ".lock").write_text("1")    # not held: the run that wrote it is over
    result = run_bench_cli("run", "--run-id", "done", "--runs-dir", str(runs_dir), "--no-progress")
    assert_refused(result, "already holds a run")
    assert (run_dir / "metrics.json").read_text() == "{}"


def test_parse_refuses_non_finite_values_given_as_strings():
    with pytest.raises(ScenarioError, match="run.time_factor"):
        parse_scenario({"name": "x", "run": {"time_factor": "nan"}})
