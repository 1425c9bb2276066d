"""The FDIR actuator monitor (bench.gnc.actuator_monitor, issue 45; docs/fdir.md).

- On a rigid body simulated here (Euler's equations, tau = m x B computed in this file, an
  integrating gyro with seeded noise): an open, a reversed and a weakened coil are each detected
  and classified on the right axis; a clean run raises nothing; a coil never commanded is "not
  observable", whatever its fault, and raises nothing.
- The plant's coil hook ([attitude.coils]) gives the torque (gain m) x B, checked against the cross
  product computed here.
- Every fault-free built-in attitude scenario, lock-step processes (short forms), raises 0 FDIR
  alarms and runs the monitor; a coil reversed through the plant's hook is detected at the same
  simulated time, axis and class by the lock-step processes and by the in-process loop, and the
  detection reaches can/driver.json (frame "FDIR"), fdir.json and metrics.json.
- The reaction (accommodate): the reversed coil's command is sign-flipped after the detection and
  the detumble gets its torque back.
"""
from __future__ import annotations

import json
import tomllib
from importlib import resources
from pathlib import Path

import msgspec
import numpy as np
import pytest

from bench.gnc.actuator_monitor import (
    ActuatorMonitor, CoilBelief, MonitorSettings, OnboardActuatorModel, accommodate,
)
from bench.scenario import fault_free_attitude_builtins, load_scenario, parse_scenario
from conftest import run_bench_cli

INERTIA = np.diag([2.2e-3, 2.3e-3, 2.0e-3])     # the 1U body of the built-in scenarios
STEP_S = 1.0
GYRO_NOISE_DENSITY = 1e-4                     # rad/s/sqrt(Hz): the bench's gyro
ONSET_S = 90.0
RUN_TIMEOUT_S = 600


# ---- a rigid body simulated here -----------------------------------------------------------
def cross(a, b):
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def quat_mul(p, q):
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return np.array([pw * qw - px * qx - py * qy - pz * qz, pw * qx + px * qw + py * qz - pz * qy,
                     pw * qy - px * qz + py * qw + pz * qx, pw * qz + px * qy - py * qx + pz * qw])


def body_from_inertial(q, v):
    """v rotated from inertial to body axes, q body to inertial (scalar first)."""
    conj = q * np.array([1.0, -1.0, -1.0, -1.0])
    return quat_mul(quat_mul(conj, np.concatenate([[0.0], v])), q)[1:]


def field_inertial_t(time_s: float) -> np.ndarray:
    """A field of 3e-5 T turning at twice the orbit rate, as a LEO field does."""
    u = 2.2e-3 * time_s
    return 3e-5 * np.array([np.cos(u), 0.6 * np.sin(u), 0.8 * np.cos(0.5 * u)])


def commanded_am2(time_s: float) -> np.ndarray:
    """Each coil swept at its own period (excitation): up to 0.05 A m^2, a quarter of the limit."""
    return 0.05 * np.array([np.sin(2 * np.pi * time_s / 37.0), np.sin(2 * np.pi * time_s / 53.0 + 1.0),
                            np.sin(2 * np.pi * time_s / 71.0 + 2.0)])


def simulate(gain_after_onset=(1.0, 1.0, 1.0), seed: int = 4, duration_s: float = 300.0, commands=commanded_am2,
             monitor: ActuatorMonitor | None = None) -> ActuatorMonitor:
    """The body under tau = (g m) x B (held over each 1 s step, RK4 in 20 sub-steps), a gyro that
    reads the mean rate over the step plus white noise, and the monitor fed as the controller feeds
    it: the rate, the field in body axes and the dipole it commanded."""
    rng = np.random.default_rng(seed)
    monitor = monitor or ActuatorMonitor(OnboardActuatorModel(
        INERTIA, STEP_S, GYRO_NOISE_DENSITY / np.sqrt(STEP_S), rate_sample="mean", dipole_resolution_am2=None))
    j_inv = np.linalg.inv(INERTIA)
    q = np.array([1.0, 0.0, 0.0, 0.0])
    omega = np.deg2rad([1.0, -0.8, 0.6])
    gyro = omega + rng.normal(0.0, GYRO_NOISE_DENSITY / np.sqrt(STEP_S), 3)
    for k in range(int(duration_s / STEP_S)):
        t = k * STEP_S
        field_body = body_from_inertial(q, field_inertial_t(t))
        m = commands(t)
        monitor.step(t, q, gyro, np.zeros(3), field_body, m)
        coil = np.asarray(gain_after_onset) * m if t >= ONSET_S else m
        torque = cross(coil, field_body)                       # held over the step, as a board holds it
        h = STEP_S / 20
        turned = np.zeros(3)
        for _ in range(20):
            def rates(w):
                return j_inv @ (torque - cross(w, INERTIA @ w))
            k1 = rates(omega)
            k2 = rates(omega + 0.5 * h * k1)
            k3 = rates(omega + 0.5 * h * k2)
            k4 = rates(omega + h * k3)
            new = omega + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            mid = 0.5 * (omega + new)
            turned += mid * h
            angle = np.linalg.norm(mid) * h
            axis = mid / np.linalg.norm(mid) if angle > 0 else np.zeros(3)
            q = quat_mul(q, np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis]))
            q /= np.linalg.norm(q)
            omega = new
        gyro = turned / STEP_S + rng.normal(0.0, GYRO_NOISE_DENSITY / np.sqrt(STEP_S), 3)
    return monitor


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("gain, fault_class", [(0.0, "open"), (-1.0, "reversed"), (0.5, "gain")])
def test_a_coil_fault_is_detected_on_its_axis_and_classified(axis, gain, fault_class):
    gains = [1.0, 1.0, 1.0]
    gains[axis] = gain
    monitor = simulate(gains)
    assert [(e.axis, e.fault_class) for e in monitor.events] == [(axis, fault_class)], \
        [e.describe() for e in monitor.events]
    event = monitor.events[0]
    assert ONSET_S < event.time_s <= ONSET_S + 90.0
    assert event.alarm_s <= event.time_s
    assert abs(event.onset_s - ONSET_S) <= 3.0            # the onset the isolating fit found
    assert abs(event.gain - gain) < 4 * event.gain_std + 0.05
    assert monitor.beliefs[axis].fault == fault_class


def test_a_reversed_coil_is_found_from_the_dynamics_within_seconds():
    """The physics: a reversed x coil takes 2 |m_x e_x x B| ~ 2.4e-6 N m from the body, a rate
    change of ~1e-3 rad/s a step against 1.4e-4 rad/s of gyro noise on a difference of two samples
    (SNR ~7 a step); the monitor's alarm comes within a few steps, its class once the onset's
    fit holds min_window_s / 2 = 10 s of data."""
    monitor = simulate([-1.0, 1.0, 1.0])
    event = monitor.events[0]
    assert event.alarm_s - ONSET_S <= 10.0
    assert event.time_s - ONSET_S <= 20.0


@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5])
def test_a_clean_body_raises_no_alarm(seed):
    monitor = simulate(seed=seed)
    assert monitor.events == []
    assert min(monitor.judged) > 0.9 * monitor.evaluations        # every coil excited and judged
    assert max(monitor.peak_statistic) < monitor.settings.threshold / 2


def test_a_coil_never_commanded_is_not_observable_and_raises_nothing():
    """The z coil reversed, but never commanded: no torque is missing, nothing to judge."""
    def no_z(t):
        m = commanded_am2(t)
        m[2] = 0.0
        return m

    monitor = simulate([1.0, 1.0, -1.0], commands=no_z)
    assert monitor.events == []
    assert monitor.judged[2] == 0 and monitor.not_observable[2] == monitor.evaluations
    assert monitor.judged[0] > 0.9 * monitor.evaluations


def test_a_coil_along_the_field_is_not_observable():
    """m_j e_j parallel to B: the coil's torque m_j e_j x B is zero whatever its gain."""
    model = OnboardActuatorModel(INERTIA, STEP_S, 1e-4, dipole_resolution_am2=None)
    monitor = ActuatorMonitor(model)
    rng = np.random.default_rng(0)
    for k in range(120):
        m = np.array([0.1 * np.sin(k / 5.0), 0.0, 0.0])
        monitor.step(float(k), [1.0, 0.0, 0.0, 0.0], rng.normal(0, 1e-4, 3), np.zeros(3), [3e-5, 0.0, 0.0], m)
    assert monitor.evaluations > 0 and monitor.judged[0] == 0 and monitor.events == []


def test_accommodation_flips_a_reversed_coil_and_spreads_an_open_one_over_the_others():
    field_t = np.array([1e-5, -2e-5, 2.5e-5])
    wanted = np.array([0.05, -0.02, 0.03])
    reversed_x = [CoilBelief(-1.0, 0.0, "reversed"), CoilBelief(), CoilBelief()]
    np.testing.assert_allclose(accommodate(wanted, field_t, reversed_x, 0.2), [-0.05, -0.02, 0.03])
    open_y = [CoilBelief(), CoilBelief(0.0, 0.0, "open"), CoilBelief()]
    m = accommodate(wanted, field_t, open_y, 0.2)
    assert m[1] == 0.0
    # the torque the law asked for, from x and z alone (B has a y component: reachable)
    np.testing.assert_allclose(cross(m, field_t), cross(wanted, field_t), rtol=1e-9, atol=1e-15)
    assert np.max(np.abs(accommodate(wanted * 10, field_t, open_y, 0.2))) <= 0.2 + 1e-12


# ---- the plant's coil hook --------------------------------------------------------------------
@pytest.mark.parametrize("gain", [[0.0, 1.0, 1.0], [1.0, -1.0, 1.0], [1.0, 1.0, 0.5]])
def test_the_plant_turns_a_faulty_coil_into_the_torque_of_its_dipole(gain):
    """Open, reversed and weakened coils: torque = (gain m) x B, against m x B computed here."""
    from bench.plant.attitude_plant import AttitudePlant

    data = msgspec.to_builtins(load_scenario("attitude_quick"))
    data["attitude"]["coils"] = {"gain": gain, "from_s": 2.0}
    scenario = parse_scenario(data, "coils")
    plant = AttitudePlant(scenario.attitude, 5, seed=1)
    dipole = np.array([0.1, -0.05, 0.15])
    for _ in range(5):
        plant.apply(dipole)
    trajectory = plant.trajectory()
    for k, t in enumerate(trajectory["att_time_s"]):
        coil = np.asarray(gain) * dipole if t >= 2.0 else dipole
        expected = cross(coil, trajectory["att_field_body_t"][k])
        np.testing.assert_allclose(trajectory["att_torque_control_nm"][k], expected, rtol=1e-12, atol=1e-18)
    np.testing.assert_array_equal(trajectory["att_dipole_applied_am2"], np.tile(dipole, (5, 1)))   # the board's


# ---- the loop: in process and as lock-step processes ---------------------------------------------
LOCKSTEP_STEPS = 300


def lock_step_form(name: str, tmp_path: Path) -> Path | None:
    """The scenario in lock-step, LOCKSTEP_STEPS steps, on the portable transport; None where the
    scenario cannot run lock-step (the board's magnetometer windows are wall-clock)."""
    data = msgspec.to_builtins(load_scenario(name))
    if (data.get("can") or {}).get("board", {}).get("mag_window_period_s"):
        return None
    data["run"]["mode"] = "lock-step"
    data["run"]["steps"] = LOCKSTEP_STEPS
    if data.get("can"):
        data["can"]["transport"] = "zenoh"
    for key in ("flight_channel", "board_channel"):
        (data.get("can") or {}).pop(key, None)
    parse_scenario(data, name)
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps(data))
    return path


def test_every_fault_free_built_in_attitude_scenario_raises_no_fdir_alarm(tmp_path):
    """Lock-step processes, short forms: 0 FDIR alarms in can/driver.json, fdir.json and
    metrics.json, and the monitor ran (evaluated, and judged the coils where they were commanded
    hard enough). A scenario that cannot be lock-step runs its in-process twin."""
    from bench.sim import simulate_attitude_in_process

    names = fault_free_attitude_builtins()
    assert {"attitude_quick", "attitude_detumble", "attitude_slew_milqr", "attitude_pointing"} <= set(names)
    judged_somewhere = False
    for name in names:
        path = lock_step_form(name, tmp_path)
        if path is None:
            data = msgspec.to_builtins(load_scenario(name))
            data["run"]["steps"] = LOCKSTEP_STEPS
            trajectory = simulate_attitude_in_process(parse_scenario(data, name))
            assert trajectory["fdir_event_time_s"].size == 0, name
            continue
        run_id = f"clean_{name}"
        result = run_bench_cli("run", str(path), "--run-id", run_id, "--runs-dir", str(tmp_path / "runs"),
                               "--no-progress", "--no-report", timeout_s=RUN_TIMEOUT_S)
        assert result.returncode == 0, name + result.stderr[-3000:]
        run_dir = tmp_path / "runs" / run_id
        fdir = json.loads((run_dir / "fdir.json").read_text())
        assert fdir["events"] == [], (name, fdir["events"])
        assert fdir["evaluations"] > 0, name
        judged_somewhere |= any(c["judged"] > 0 for c in fdir["coils"].values())
        driver = json.loads((run_dir / "can" / "driver.json").read_text())
        assert [e for e in driver["events"] if e["frame"] == "FDIR"] == [], name
        assert not any(e["kind"].startswith("fdir_") for e in driver["events"]), name
    assert judged_somewhere


def reversed_coil_scenario(tmp_path: Path, accommodate_: bool = False, steps: int = 200) -> Path:
    """attitude_quick with its x coil wired backwards from 100 s (the plant's coil hook)."""
    data = tomllib.loads((resources.files("bench.scenarios") / "attitude_quick.toml").read_text())
    data["name"] = "fdir_reversed_x"
    data["run"]["steps"] = steps
    data["attitude"]["coils"] = {"gain": [-1.0, 1.0, 1.0], "from_s": 100.0}
    data["attitude_control"]["fdir"] = {"accommodate": accommodate_}
    parse_scenario(data, "fdir_reversed_x")
    path = tmp_path / f"reversed_x_{accommodate_}.json"
    path.write_text(json.dumps(data))
    return path


def test_in_process_and_lock_step_processes_detect_at_the_same_simulated_time(tmp_path):
    from bench.report.rundata import load_run
    from bench.sim import simulate_attitude_in_process

    path = reversed_coil_scenario(tmp_path)
    result = run_bench_cli("run", str(path), "--run-id", "reversed", "--runs-dir", str(tmp_path / "runs"),
                           "--no-progress", timeout_s=RUN_TIMEOUT_S)
    assert result.returncode == 0, result.stderr[-3000:]
    run_dir = tmp_path / "runs" / "reversed"
    run = load_run(run_dir)
    reference = simulate_attitude_in_process(run.scenario)
    in_process = list(zip(reference["fdir_event_time_s"].tolist(), reference["fdir_event_axis"].tolist(),
                          reference["fdir_event_class"].tolist()))
    assert in_process and in_process[0][1:] == ("x", "reversed") and in_process[0][0] > 100.0
    events = json.loads((run_dir / "fdir.json").read_text())["events"]
    assert [(e["time_s"], e["axis"], e["class"]) for e in events] == in_process
    driver = json.loads((run_dir / "can" / "driver.json").read_text())
    fdir_events = [e for e in driver["events"] if e["frame"] == "FDIR"]
    assert [e["kind"] for e in fdir_events] == ["fdir_reversed"]
    assert "coil x: reversed at" in fdir_events[0]["detail"]
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["can_bus"]["driver"]["events"]["fdir_reversed"] == 1


def test_accommodating_a_reversed_coil_gives_the_detumble_its_torque_back(tmp_path):
    """In process: after the detection the x command is sign-flipped, so the coil gives the torque
    the law asks for again; without it the reversed coil keeps pumping the rate up on x."""
    from bench.sim import simulate_attitude_in_process

    runs = {}
    for accommodate_ in (False, True):
        data = json.loads(reversed_coil_scenario(tmp_path, accommodate_, steps=500).read_text())
        runs[accommodate_] = simulate_attitude_in_process(parse_scenario(data, "reversed"))
    detected_s = runs[True]["fdir_event_time_s"][0]
    assert runs[False]["fdir_event_time_s"][0] == detected_s      # the reaction changes nothing before it
    before = runs[True]["att_time_s"] <= detected_s
    for name in ("att_omega_radps", "att_dipole_commanded_am2"):
        np.testing.assert_array_equal(runs[True][name][before], runs[False][name][before])
    # Afterwards the x command is flipped: the reversed coil gives the law's torque, and the body
    # slows as the clean detumble does, where without the reaction it does not.
    rate = {k: np.rad2deg(np.linalg.norm(v["att_omega_radps"][-1])) for k, v in runs.items()}
    assert rate[True] < 0.5 * rate[False], rate
