"""Hardware faults of the magnetorquer board (issue 45): board_power_loss, coil_open, coil_stuck,
coil_reversed, coil_gain in [[can.faults]] act on the board's coils and power supply, so the
plant's torque changes, while its current telemetry shows only what is before the sensor.

The torque is checked against m x B computed here; the in-process loop (which runs the lock-step
bus itself when a scenario has faults) against the lock-step processes to 1e-9 with the faults
active; fault times are simulated seconds at any time factor.
"""
import json

import numpy as np
import pytest

from bench.bus.can.coils import CoilHardware
from bench.bus.can.faults import FaultSpec
from bench.bus.can.injector import FaultInjector
from bench.bus.can import protocol as p
from bench.bus.can.sim_window import fault_clock_scale, mission_s
from bench.plant.mtq_acceptance import board_dipole_without_bus
from bench.report.rundata import load_run
from bench.scenario import load_scenario, parse_scenario, scenario_to_toml_dict
from bench.sim import simulate_attitude_in_process
from conftest import run_bench_cli

COIL_FAULTS = [  # x open 10-20 s, y reversed 25-35 s, z at half its gain 40-50 s (attitude_quick, 1 Hz)
    {"name": "coil_open", "start_s": 10.0, "duration_s": 10.0, "params": {"axis": 0}},
    {"name": "coil_reversed", "start_s": 25.0, "duration_s": 10.0, "params": {"axis": 1}},
    {"name": "coil_gain", "start_s": 40.0, "duration_s": 10.0, "params": {"axis": 2, "gain": 0.5}},
]
POWER_LOSS = {"name": "board_power_loss", "start_s": 52.0, "duration_s": 3.0}


def quick_with(faults: list[dict], duration_s: float = 60.0):
    data = scenario_to_toml_dict(load_scenario("attitude_quick"))
    data["name"] = "hardware_faults"
    data["attitude"]["duration_s"] = duration_s
    data["can"]["faults"] = faults
    return data


@pytest.fixture(scope="module")
def coil_run():
    scenario = parse_scenario(quick_with(COIL_FAULTS), "coil faults")
    return scenario, simulate_attitude_in_process(scenario)


def test_torque_with_an_open_reversed_and_weak_coil_is_m_cross_b(coil_run):
    """Each step fully inside a fault's window (the step before one ends holds the next step's first
    frame time of the healthy coil: lock-step holds a step from its command on), the plant's control
    torque is m x B of the board's set-point with that coil open (x), reversed (y), at half (z)."""
    scenario, t = coil_run
    time_s, field = t["att_time_s"], t["att_field_body_t"]
    setpoint = np.array([board_dipole_without_bus(c, scenario.can) for c in t["att_dipole_commanded_am2"]])
    expected = setpoint.copy()
    windows = {0: (10, 19, 0.0), 1: (25, 34, -1.0), 2: (40, 49, 0.5)}
    checked = 0
    for axis, (first, last, gain) in windows.items():
        steps = np.flatnonzero((time_s >= first) & (time_s < last))
        assert len(steps) == last - first
        expected[steps, axis] *= gain
        checked += len(steps)
        # the commands this axis had, so that the check means something
        assert np.abs(setpoint[steps, axis]).max() > 0.005, (axis, setpoint[steps, axis])
    healthy = np.ones(len(time_s), bool)
    for first, last, _ in windows.values():
        healthy &= ~((time_s >= first - 1) & (time_s <= last))
    for k in np.r_[np.flatnonzero(healthy), *[np.flatnonzero((time_s >= a) & (time_s < b)) for a, b, _ in windows.values()]]:
        m, b = expected[k], field[k]
        torque = np.array([m[1] * b[2] - m[2] * b[1], m[2] * b[0] - m[0] * b[2], m[0] * b[1] - m[1] * b[0]])
        np.testing.assert_allclose(t["att_torque_control_nm"][k], torque, rtol=1e-12, atol=1e-18, err_msg=f"step {k}")
        np.testing.assert_array_equal(t["att_dipole_applied_am2"][k], m)
    assert checked == 27 and healthy.sum() > 20
    # The reversed and the weak coil told the driver nothing (telemetry before the wiring and the
    # turns); the open one did (its current sensor in series): mismatches only on x, only then.
    mismatches = [time for time, kind in t["can_driver_events"] if kind == "actuator_mismatch"]
    assert mismatches and all(10.0 < time < 20.5 for time in mismatches)


def test_a_power_loss_leaves_the_coils_off_for_its_whole_window_and_the_driver_starts_the_board_again():
    scenario = parse_scenario(quick_with([POWER_LOSS]), "power loss")
    t = simulate_attitude_in_process(scenario)
    time_s, off = t["att_time_s"], t["att_coils_off_fraction"]
    inside = (time_s >= 52.0) & (time_s < 55.0)
    assert inside.sum() == 3 and np.all(off[inside] == 1.0)
    assert np.all(t["att_dipole_applied_am2"][inside] == 0.0)
    log = [(e["event"], mission_s(round(e["t_s"] * 1e9))) for e in t["can_board_power_log"]]
    assert [e for e, _ in log] == ["power_lost", "booted", "operational"]
    assert log[0][1] == pytest.approx(52.0, abs=1e-9) and log[1][1] == pytest.approx(55.0, abs=1e-9)
    # Booted at 55 s (pre-operational), started by the driver's NMT start at the next step's window,
    # commanded again in it: the coils on for most of the step after.
    assert 55.0 < log[2][1] < 56.0 + 1e-3 and off[time_s == 56.0][0] < 0.01
    kinds = [kind for time, kind in t["can_driver_events"] if 52.0 <= time < 56.0]
    assert {"heartbeat_timeout", "board_rebooted"} <= set(kinds)


def test_fault_times_are_simulated_seconds_at_any_time_factor():
    """A fault's window on the bus's clock is start_s and duration_s of simulated time: divided by
    the time factor on a real-time run's wall clock (rendezvous_mtq_bus: 6000), as they are on a
    bus on simulated time."""
    rendezvous = load_scenario("rendezvous_mtq_bus")
    assert rendezvous.run.mode == "real-time" and fault_clock_scale(rendezvous) == 1 / 6000
    power = next(f for f in rendezvous.can.faults if f.name == "board_power_loss")
    injector = FaultInjector([power], p.Protocol(), wall_s_per_sim_s=fault_clock_scale(rendezvous))
    injector.arm(10**12)
    (summary,) = injector.summary()
    assert (summary["start_ns"] - 10**12, summary["end_ns"] - summary["start_ns"]) == (3_000_000_000, 1_000_000_000)
    hardware = injector.hardware
    assert hardware.powered(10**3 + 2.999) and not hardware.powered(10**3 + 3.0) and hardware.powered(10**3 + 4.0)
    attitude_rt = load_scenario("attitude_fault_board_death")
    assert fault_clock_scale(attitude_rt) == 1.0                          # real time at 1x
    lock_step = parse_scenario({**quick_with([POWER_LOSS]), "run": {"mode": "lock-step"}}, "x")
    assert fault_clock_scale(lock_step) == 1.0                            # the bus on simulated time


def test_retired_fault_names_are_refused_naming_their_replacement():
    with pytest.raises(ValueError, match="use 'board_power_loss'"):
        FaultSpec(name="board_death", duration_s=1.0)
    with pytest.raises(ValueError, match="use 'telemetry_freeze'.*'coil_stuck'"):
        FaultSpec(name="stuck_actuator", duration_s=1.0)
    with pytest.raises(ValueError, match="not on frames"):
        FaultSpec(name="coil_open", frames=["MTQ_CMD"], params={"axis": 1})


def test_the_current_sensor_sees_what_is_before_it():
    hardware = CoilHardware([FaultSpec(name=name, params=params) for name, params in (
        ("coil_open", {"axis": 0}), ("coil_reversed", {"axis": 1}), ("coil_gain", {"axis": 2, "gain": 0.25}))],
        max_dipole_am2=0.2)
    hardware.arm(0.0)
    setpoint = np.array([0.1, -0.2, 0.2])
    np.testing.assert_array_equal(hardware.physical_am2(setpoint, 1.0), [0.0, 0.2, 0.05])
    np.testing.assert_array_equal(hardware.sensed_am2(setpoint, 1.0), [0.0, -0.2, 0.2])
    stuck = CoilHardware([FaultSpec(name="coil_stuck", params={"axis": 1, "value_am2": 0.5})], max_dipole_am2=0.2)
    stuck.arm(0.0)
    np.testing.assert_array_equal(stuck.physical_am2(np.zeros(3), 1.0), [0.0, 0.2, 0.0])   # clipped, in safe state too


# --- the processes ----------------------------------------------------------------------------------
RUN_TIMEOUT_S = 600


def test_lock_step_processes_equal_the_in_process_loop_with_hardware_faults(tmp_path):
    """Coils open, reversed and weak, then the board's power lost and back: `bench run` in lock-step
    (the bus on simulated time, faults in the scenario) gives the trajectory of the in-process loop
    to 1e-9, and its driver detected what the in-process one did at the same simulated times."""
    path = tmp_path / "hardware_faults.json"
    path.write_text(json.dumps(quick_with(COIL_FAULTS + [POWER_LOSS])))
    result = run_bench_cli("run", str(path), "--run-id", "hw", "--runs-dir", str(tmp_path / "runs"), "--no-progress",
                           "--no-report", timeout_s=RUN_TIMEOUT_S)
    assert result.returncode == 0, result.stderr + result.stdout
    run = load_run(tmp_path / "runs" / "hw")
    reference = simulate_attitude_in_process(run.scenario)     # the run's scenario.json: its SecOC key too
    for name in ("att_q_wxyz", "att_omega_radps", "att_dipole_applied_am2", "att_dipole_commanded_am2",
                 "att_torque_control_nm"):
        np.testing.assert_allclose(run.trajectory[name], reference[name], rtol=0, atol=1e-9, err_msg=name)
    driver = json.loads((run.run_dir / "can" / "driver.json").read_text())
    seen = [(round(mission_s(e["detected_ns"]), 6), e["kind"]) for e in driver["events"] if e["frame"] != "FDIR"]
    assert seen == [(round(t, 6), kind) for t, kind in reference["can_driver_events"]]
    board = json.loads((run.run_dir / "can" / "board.json").read_text())
    assert [e["event"] for e in board["power_log"]] == ["power_lost", "booted", "operational"]
    metrics = json.loads((run.run_dir / "metrics.json").read_text())
    assert metrics["can_bus"]["board_power"]["recovered"] == 1
    windows = {f["name"]: (f["start_sim_s"], f["end_sim_s"]) for f in metrics["can_bus"]["faults"]}
    assert windows["board_power_loss"] == pytest.approx((52.0, 55.0), abs=1e-6)
    assert windows["coil_reversed"] == pytest.approx((25.0, 35.0), abs=1e-6)
