"""A process run (plant, estimator, controller over Zenoh) with the range/bearing sensor: the plant
publishes it, the estimator uses it, every estimate carries its NIS."""
from __future__ import annotations

import msgspec
import numpy as np
import pytest
from conftest import run_bench_cli

from bench.bus import keys
from bench.bus.schemas import MalformedMessage, RangeBearing, decode, encode, header
from bench.gnc.range_bearing import range_bearing
from bench.plant.model import RangeBearingSensor
from bench.report.rundata import load_run
from bench.scenario import load_scenario, parse_scenario
from bench.sim import simulate_in_process

SCENARIO = '''name = "range_bearing_process"
[run]
steps = 20
[estimator]
mode = "smoother"
translation.sensor = "range_bearing"
translation.gate_probability = 0.9999
'''


def test_a_process_run_flies_on_range_and_bearing(tmp_path, runs_dir):
    path = tmp_path / "rb.toml"
    path.write_text(SCENARIO)
    result = run_bench_cli("run", str(path), "--run-id", "rb-process", "--runs-dir", str(runs_dir), "--no-progress",
                           "--no-report", timeout_s=300)
    assert result.returncode == 0, result.stderr[-2000:]
    run = load_run(runs_dir / "rb-process")
    sensed = run.on(keys.SENSE_RANGE_BEARING)
    estimates = run.on(keys.ESTIMATE_TRANSLATION)
    assert len(sensed) == 20 and len(estimates) == 20
    nis = [m.body["nis"] for m in estimates[1:]]
    assert all(v is not None and np.isfinite(v) for v in nis)
    assert all(m.body["nis_dof"] == 3 for m in estimates[1:])
    truth = {m.seq: np.array(m.body["state_m_mps"]) for m in run.on(keys.TRUTH)}
    errors = [np.linalg.norm(np.array(m.body["state_m_mps"][:3]) - truth[m.seq][:3]) for m in estimates[5:]]
    assert np.median(errors) < 100.0


# --- near the target: no fix -----------------------------------------------------------------
def test_the_sensor_gives_no_fix_at_or_below_its_minimum_range_and_keeps_its_noise_sequence():
    sigmas = np.array([10.0, 1e-4, 1e-4])
    for min_range_m in (0.0, 4.0):
        sensor = RangeBearingSensor(*sigmas[:2], np.random.default_rng(7), min_range_m)
        reference = np.random.default_rng(7)          # the same draws, made here
        outcomes = []
        for k in range(400):
            position_m = np.array([3.0, -2.0, 1.0]) * (1 + k % 5)      # 3.7-18.7 m from the target
            expected = range_bearing(position_m) + sigmas * reference.standard_normal(3)
            fix = sensor.measure(position_m)
            if expected[0] > min_range_m:
                np.testing.assert_array_equal(fix, expected)
            else:
                assert fix is None
            outcomes.append(fix is None)
        assert 0 < sum(outcomes) < 400, min_range_m


def test_a_range_bearing_message_has_all_three_values_or_none():
    hdr = header("r", 3, 1800.0)
    assert decode(encode(RangeBearing(hdr)), RangeBearing).fix is None
    assert decode(encode(RangeBearing(hdr, 5.0, 0.1, -0.2)), RangeBearing).fix == [5.0, 0.1, -0.2]
    for partial in ({"range_m": 5.0}, {"range_m": None, "azimuth_rad": 0.1, "elevation_rad": 0.2},
                    {"range_m": -1.0, "azimuth_rad": 0.1, "elevation_rad": 0.2}):
        payload = msgspec.json.encode({**msgspec.to_builtins(RangeBearing(hdr)), **partial})
        with pytest.raises(MalformedMessage):
            decode(payload, RangeBearing)


def test_range_bearing_run_without_fixes_near_the_target(tmp_path, runs_dir):
    """rendezvous_smoother on range and bearing, 440 steps: from step 403 the chaser is within
    20 m of the target and the 10 m range noise takes five measured ranges to zero or below. The
    plant sends those steps without a fix, the smoother predicts through them, and the processes
    equal the in-process loop to 1e-9 (before, the plant sent a negative range, every node counted
    it malformed, and the loop stalled at step 403)."""
    steps = 440
    data = msgspec.to_builtins(load_scenario("rendezvous_smoother"))
    data["name"] = "rb_near_target"
    data["estimator"]["translation"]["sensor"] = "range_bearing"
    data["run"]["steps"] = steps
    path = tmp_path / "rb_near_target.json"
    path.write_text(msgspec.json.encode(data).decode())
    result = run_bench_cli("run", str(path), "--run-id", "rb-near", "--runs-dir", str(runs_dir), "--no-progress",
                           "--no-report", timeout_s=300)
    assert result.returncode == 0, result.stderr[-2000:]
    run = load_run(runs_dir / "rb-near")
    without_fix = [m.seq for m in run.on(keys.SENSE_RANGE_BEARING) if m.body["range_m"] is None]
    assert len(without_fix) >= 3 and min(without_fix) > 300, without_fix
    assert len(run.on(keys.ESTIMATE_TRANSLATION)) == steps
    reference, _ = simulate_in_process(parse_scenario(data, "test"))
    scale = np.abs(reference["state_m_mps"]).max(axis=0)
    np.testing.assert_allclose(run.trajectory["state_m_mps"] / scale, reference["state_m_mps"] / scale, rtol=0, atol=1e-9)
    np.testing.assert_allclose(run.trajectory["thrust_n"], reference["thrust_n"], rtol=1e-9, atol=1e-15)
    metrics = msgspec.json.decode((runs_dir / "rb-near" / "metrics.json").read_bytes())
    assert all(not stats.get("malformed") for stats in metrics["process_stats"].values()), metrics["process_stats"]


# --- no fix at the first step ------------------------------------------------------------------
NO_FIRST_FIX = '''name = "rb_no_first_fix"
[run]
steps = 12
[plant]
initial_state_m_mps = [1000.0, 0.0, 0.0, 2.0, 0.0, 0.0]
range_bearing_sensor.min_range_m = 1100.0
[estimator]
mode = "smoother"
translation.sensor = "range_bearing"
'''


def test_a_run_whose_first_steps_have_no_fix_coasts_until_the_first_fix(tmp_path, runs_dir):
    """The chaser starts 1000 m out, inside the sensor's 1100 m minimum range, moving away at
    2 m/s: step 0 has no fix, the later ones do (1.2 km further at 600 s a step). The estimator
    says it has no estimate (valid false), the controller commands zero thrust until it has one,
    and the processes equal the in-process loop (before, the estimator published nothing at step
    0, and the lock-step loop stalled waiting for its first command)."""
    path = tmp_path / "rb_no_first_fix.toml"
    path.write_text(NO_FIRST_FIX)
    result = run_bench_cli("run", str(path), "--run-id", "rb-no-first-fix", "--runs-dir", str(runs_dir),
                           "--no-progress", "--no-report", timeout_s=120)
    assert result.returncode == 0, result.stderr[-2000:]
    run = load_run(runs_dir / "rb-no-first-fix")
    without_fix = [m.seq for m in run.on(keys.SENSE_RANGE_BEARING) if m.body["range_m"] is None]
    assert without_fix == [0]
    estimates = run.on(keys.ESTIMATE_TRANSLATION)
    assert [m.body["valid"] for m in estimates] == [False] + [True] * 11
    commands = run.on(keys.COMMAND_THRUST)
    assert commands[0].body["status"] == "waiting_for_estimate" and commands[0].body["thrust_n"] == [0.0, 0.0, 0.0]
    assert any(np.any(c.body["thrust_n"]) for c in commands[1:])     # the law flies once it has an estimate
    reference, _ = simulate_in_process(parse_scenario(msgspec.toml.decode(NO_FIRST_FIX), "test"))
    np.testing.assert_allclose(run.trajectory["state_m_mps"], reference["state_m_mps"], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(run.trajectory["thrust_n"], reference["thrust_n"], rtol=1e-9, atol=1e-15)
    deadline = msgspec.json.decode((runs_dir / "rb-no-first-fix" / "deadline_controller.json").read_bytes())
    assert deadline["waiting_for_estimate_cycles"] == 1
