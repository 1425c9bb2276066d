"""Scenario validation: one clear line naming the field, exit code 2, no process started."""
import socket

import pytest

from bench.scenario import ScenarioError, builtin_names, load_scenario
from conftest import bench_processes, run_bench_cli

BAD_SCENARIOS = {
    "unknown key": ('name = "x"\n[plant]\nthrusters = 4\n', "plant", "thrusters"),
    "wrong type": ('name = "x"\n[run]\nsteps = "many"\n', "run.steps", "int"),
    "negative time step": ('name = "x"\n[plant]\ntime_step_s = -600.0\n', "plant.time_step_s", ">= 0.001"),
    "zero steps": ('name = "x"\n[run]\nsteps = 0\n', "run.steps", ">= 1"),
    "unknown mode": ('name = "x"\n[run]\nmode = "fast"\n', "run.mode", "fast"),
    "unknown initial condition": ('name = "x"\n[plant]\ninitial_condition = "Z"\n', "plant.initial_condition", "Z"),
    "short state": ('name = "x"\n[plant]\ninitial_state_m_mps = [1.0, 2.0]\n', "plant.initial_state_m_mps", "length"),
    "not toml": ('name = "x\n', "not valid TOML", ""),
}


@pytest.mark.parametrize("case", sorted(BAD_SCENARIOS))
def test_bad_scenario_is_named_and_nothing_runs(tmp_path, runs_dir, case):
    text, field, problem = BAD_SCENARIOS[case]
    path = tmp_path / "bad.toml"
    path.write_text(text)
    run_id = f"bad-{case.replace(' ', '-')}"
    result = run_bench_cli("run", str(path), "--run-id", run_id, "--runs-dir", str(runs_dir), "--no-progress")
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert field in lines[0] and problem in lines[0]
    assert not (runs_dir / run_id).exists()
    assert bench_processes(run_id) == []


def test_missing_scenario_file(runs_dir):
    result = run_bench_cli("run", "does/not/exist.toml", "--runs-dir", str(runs_dir))
    assert result.returncode == 2
    assert "does not exist" in result.stderr and "exist.toml" in result.stderr
    assert not runs_dir.exists()


def test_unknown_builtin_lists_the_known_ones():
    with pytest.raises(ScenarioError, match="rendezvous_lqr"):
        load_scenario("no_such_scenario")


def test_port_in_use_is_a_clear_error(runs_dir):
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        result = run_bench_cli("run", "--port", str(port), "--run-id", "port-taken", "--runs-dir", str(runs_dir))
    assert result.returncode == 2
    assert f"port {port}" in result.stderr and "already in use" in result.stderr
    assert bench_processes("port-taken") == []
    assert not (runs_dir / "port-taken").exists()


def test_every_builtin_scenario_loads():
    names = builtin_names()
    assert "rendezvous_lqr" in names
    for name in names:
        assert load_scenario(name).name


def test_scenarios_command_lists_builtins():
    result = run_bench_cli("scenarios")
    assert result.returncode == 0
    assert "rendezvous_lqr" in result.stdout
