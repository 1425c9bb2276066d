"""The attitude sensors as separate messages (sense/gyro, sense/mag, sense/star): their schedule from
the scenario's rates and outage windows, deterministic from the seed; their noise against the stated
sigmas; scenario validation naming the field; the estimator's gathering of the three topics into
ticks (waiting, late, refused samples); the smoother through a star-tracker outage."""
from __future__ import annotations

import copy
import threading
import tomllib
from collections import Counter
from importlib import resources

import numpy as np
import pytest
from scipy import stats
from scipy.spatial.transform import Rotation

from bench.bus import keys
from bench.bus.schemas import (
    GyroSample, MagnetometerSample, StarTrackerSample, decode, encode, header,
)
from bench.estimator.attitude_frontend import AttitudeEstimator
from bench.estimator.attitude_sensors import SensorInbox, SensorSchedule
from bench.gnc import quaternion as qt
from bench.plant.attitude_node import sensor_messages
from bench.plant.attitude_plant import AttitudePlant
from bench.scenario import ScenarioError, parse_scenario

KINDS = {keys.SENSE_GYRO: GyroSample, keys.SENSE_MAG: MagnetometerSample, keys.SENSE_STAR: StarTrackerSample}


def scenario_with(sensors: dict | None = None, name: str = "attitude_pointing", **run):
    data = tomllib.loads(resources.files("bench.scenarios").joinpath(f"{name}.toml").read_text())
    data = copy.deepcopy(data)
    data.setdefault("attitude", {}).setdefault("sensors", {}).update(sensors or {})
    data["run"].update(run)
    data.pop("can", None)
    return parse_scenario(data, "test")


def published(scenario, n_steps: int, seed: int):
    """Per tick: the (topic, decoded message) the plant process publishes, open loop (no dipole)."""
    plant = AttitudePlant(scenario.attitude, n_steps, seed)
    ticks = []
    for k in range(n_steps):
        messages = sensor_messages(header("sensors", k, plant.time_s), plant.sense())
        ticks.append([(topic, decode(encode(m), KINDS[topic])) for topic, m in messages])
        plant.apply(np.zeros(3))
    return plant, ticks


# --- schedule ------------------------------------------------------------------------------------
def test_each_sensor_publishes_at_its_own_rate_with_outages_from_the_scenario():
    scenario = scenario_with({"gyro_rate_hz": 10.0, "magnetometer_period_s": 0.5, "star_tracker_period_s": 2.0,
                              "star_tracker_outages_s": [[4.0, 9.0], [14.0, 16.0]]})
    _, ticks = published(scenario, 200, seed=3)
    for k, messages in enumerate(ticks):
        topics = [t for t, _ in messages]
        expected = ([keys.SENSE_MAG] if k % 5 == 0 else []) + ([keys.SENSE_STAR] if k % 20 == 0 else []) + [keys.SENSE_GYRO]
        assert topics == expected, k                          # the gyro last: it closes the tick
        for _, m in messages:
            assert m.header.seq == k and m.header.sim_time_s == pytest.approx(k * 0.1)
    fixes = {m.header.seq: m.q_wxyz is not None for messages in ticks for t, m in messages if t == keys.SENSE_STAR}
    no_fix = sorted(k for k, fix in fixes.items() if not fix)
    assert no_fix == [40, 60, 80, 140]                        # t in [4, 9) and [14, 16): "no fix" reported
    assert len(fixes) == 10


def test_the_sensor_stream_is_deterministic_from_the_seed():
    scenario = scenario_with({"star_tracker_outages_s": [[2.0, 3.0]]})
    _, first = published(scenario, 60, seed=11)
    _, again = published(scenario, 60, seed=11)
    _, other = published(scenario, 60, seed=12)
    as_bytes = lambda ticks: [[(t, encode(m)) for t, m in messages] for messages in ticks]
    assert as_bytes(first) == as_bytes(again)
    assert [[t for t, _ in m] for m in first] == [[t for t, _ in m] for m in other]     # same schedule
    assert as_bytes(first) != as_bytes(other)                                          # other noise


# --- noise against the stated sigmas -------------------------------------------------------------
def _std_interval(samples: np.ndarray, confidence: float = 0.999) -> tuple[float, float]:
    """Chi-square confidence interval of a zero-mean sample's standard deviation."""
    n = len(samples)
    ss = float(np.sum(samples**2))
    return np.sqrt(ss / stats.chi2.ppf(0.5 + confidence / 2, n)), np.sqrt(ss / stats.chi2.ppf(0.5 - confidence / 2, n))


def test_star_tracker_noise_is_larger_about_the_boresight_by_the_stated_factor():
    sigma, factor = 2e-4, 6.0
    scenario = scenario_with({"star_tracker_period_s": 0.1, "magnetometer_period_s": 10.0, "star_tracker_noise_std_rad": sigma,
                              "star_tracker_boresight_noise_factor": factor,
                              "star_tracker_outages_s": []})
    plant = AttitudePlant(scenario.attitude, 6000, seed=21)
    plant.sim.omega_body_radps = np.deg2rad([0.5, -0.3, 0.8])    # turning: errors are taken in body axes
    errors = []
    for k in range(6000):
        (_, star), *_ = [(t, m) for t, m in sensor_messages(header("s", k, plant.time_s), plant.sense()) if t == keys.SENSE_STAR]
        truth = Rotation.from_quat(plant.sim.q_wxyz, scalar_first=True)
        errors.append((truth.inv() * Rotation.from_quat(star.q_wxyz, scalar_first=True)).as_rotvec())
        plant.apply(np.zeros(3))
    errors = np.array(errors)
    for axis, stated in ((0, sigma), (1, sigma), (2, sigma * factor)):      # boresight: body z
        low, high = _std_interval(errors[:, axis])
        assert low < stated < high, (axis, low, stated, high)
    assert abs(np.corrcoef(errors.T)[0, 2]) < 0.05


def test_gyro_noise_and_bias_random_walk_have_the_stated_sigmas():
    density, walk = 2e-4, 5e-6
    scenario = scenario_with({"gyro_noise_density_radps_per_rthz": density, "gyro_bias_random_walk_radps2_per_rthz": walk})
    plant = AttitudePlant(scenario.attitude, 4000, seed=8)
    dt = plant.dt_s
    q, bias, gyro = [], [], []
    for _ in range(4000):
        # Sample k reads the mean rate over [t_k-1, t_k] plus the bias of tick k-1, which then walks.
        q.append(plant.sim.q_wxyz.copy())
        bias.append(plant.sim.gyro_bias_radps.copy())
        gyro.append(plant.sense().gyro_radps)
        plant.apply(np.zeros(3))
    mean_rate = np.array([qt.log(qt.multiply(qt.conjugate(a), b)) / dt for a, b in zip(q[:-1], q[1:])])
    white = np.array(gyro[1:]) - mean_rate - np.array(bias[:-1])
    steps = np.diff(np.array(bias), axis=0)
    for axis in range(3):
        low, high = _std_interval(white[:, axis])
        assert low < density / np.sqrt(dt) < high, (axis, low, high)
        low, high = _std_interval(steps[:, axis])
        assert low < walk * np.sqrt(dt) < high, (axis, low, high)


# --- scenario validation --------------------------------------------------------------------------
@pytest.mark.parametrize("field, value", [
    ("gyro_rate_hz", 0.0), ("gyro_rate_hz", -10.0), ("gyro_rate_hz", float("nan")),
    ("magnetometer_period_s", 0.0), ("star_tracker_period_s", float("nan")), ("star_tracker_period_s", 0.15),
    ("gyro_noise_density_radps_per_rthz", -1e-4), ("gyro_bias_random_walk_radps2_per_rthz", float("inf")),
    ("magnetometer_noise_std_t", float("nan")), ("star_tracker_noise_std_rad", -1.0),
    ("star_tracker_boresight_noise_factor", float("nan")), ("star_tracker_boresight_noise_factor", 0.5),
])
def test_a_bad_sensor_rate_or_noise_is_a_scenario_error_naming_the_field(field, value):
    with pytest.raises(ScenarioError, match=rf"test: attitude\.sensors\.{field}"):
        scenario_with({field: value})


def test_a_bad_outage_window_is_a_scenario_error_naming_it():
    for window in ([10.0, float("nan")], [10.0, 5.0], [-1.0, 2.0]):
        with pytest.raises(ScenarioError, match=r"test: attitude\.sensors\.star_tracker_outages_s\[0\]"):
            scenario_with({"star_tracker_outages_s": [window]})


# --- the estimator's inbox --------------------------------------------------------------------------
SCHEDULE = SensorSchedule(magnetometer_every=2, star_tracker_every=4)


def inbox(wait_s: float = 0.0, n_steps: int = 100) -> SensorInbox:
    return SensorInbox(SCHEDULE, n_steps, 0.1, wait_s, Counter())


def gyro(k, rate=(0.0, 0.0, 0.0)):
    return GyroSample(header("r", k, 0.1 * k), list(rate))


def mag(k, field=(1e-5, 0.0, 0.0), model=(1e-5, 0.0, 0.0)):
    return MagnetometerSample(header("r", k, 0.1 * k), list(field), list(model))


def star(k, q=(1.0, 0.0, 0.0, 0.0)):
    return StarTrackerSample(header("r", k, 0.1 * k), None if q is None else list(q))


def test_lock_step_waits_for_a_scheduled_sample_that_comes_after_the_gyro():
    box, stop = inbox(wait_s=30.0), threading.Event()
    box.add(gyro(0))
    box.add(mag(0))
    late_star = threading.Timer(0.2, box.add, [star(0)])
    late_star.start()
    tick = box.next_tick(stop)
    late_star.join()
    assert tick.seq == 0 and tick.magnetometer_t is not None and tick.star_tracker_wxyz == [1.0, 0.0, 0.0, 0.0]
    box.add(gyro(1))
    tick = box.next_tick(stop)                 # nothing else scheduled at tick 1: no wait
    assert tick.seq == 1 and tick.magnetometer_t is None and tick.star_tracker_wxyz is None
    assert not box.missing and not box.late


def test_real_time_takes_what_came_and_counts_a_sample_after_its_tick_late():
    box, stop = inbox(), threading.Event()
    box.add(gyro(0))
    tick = box.next_tick(stop)
    assert tick.magnetometer_t is None and box.missing == {keys.SENSE_MAG: 1, keys.SENSE_STAR: 1}
    box.add(mag(0))                            # after tick 0 was closed
    box.add(star(4, q=None))                   # an outage: the tracker reports no fix
    for k in (1, 2, 3, 4):
        box.add(gyro(k))
        tick = box.next_tick(stop)
    assert tick.seq == 4 and tick.star_tracker_wxyz is None
    assert box.late == {keys.SENSE_MAG: 1}


@pytest.mark.parametrize("message, topic", [
    (gyro(0, rate=(float("nan"), 0.0, 0.0)), keys.SENSE_GYRO),
    (gyro(0, rate=(float("inf"), 0.0, 0.0)), keys.SENSE_GYRO),
    (mag(0, field=(0.0, float("nan"), 0.0)), keys.SENSE_MAG),
    (mag(0, model=(0.0, 0.0, 0.0)), keys.SENSE_MAG),
    (star(0, q=(0.9, 0.0, 0.0, 0.0)), keys.SENSE_STAR),
    (star(0, q=(float("nan"), 0.0, 0.0, 1.0)), keys.SENSE_STAR),
    (gyro(10**6), keys.SENSE_GYRO),            # a tick the run never reaches
])
def test_an_unusable_sensor_message_is_counted_and_dropped(message, topic):
    box, stop = inbox(), threading.Event()
    box.add(message)
    assert box.malformed == {topic: 1}
    for sample in (gyro(0), mag(0), star(0)):
        if type(sample) is not type(message) or message.header.seq != 0:
            box.add(sample)
    tick = box.next_tick(stop)
    assert tick.seq == 0
    assert (tick.gyro_radps is None) == (topic == keys.SENSE_GYRO and message.header.seq == 0)


def test_a_refused_gyro_still_closes_its_tick_and_the_estimator_holds_the_last_one():
    box, stop = inbox(), threading.Event()
    scenario = scenario_with()
    estimator = AttitudeEstimator(scenario)
    box.add(star(0))
    box.add(mag(0))
    box.add(gyro(0, rate=(0.01, 0.0, 0.0)))
    box.add(gyro(1, rate=(float("nan"), 0.0, 0.0)))
    box.add(gyro(2, rate=(0.01, 0.0, 0.0)))
    seen = []
    for _ in range(3):
        tick = box.next_tick(stop)
        estimate = estimator.step(tick.seq, tick.sim_time_s, tick.gyro_radps, tick.magnetometer_t,
                                  tick.field_model_inertial_t, tick.star_tracker_wxyz)
        seen.append(tick.seq)
        assert np.all(np.isfinite(estimate.q_wxyz)) and estimate.valid
    assert seen == [0, 1, 2] and estimator.gyro_samples_held == 1
    # held over tick 1, measured over tick 2: ~0.2 s at 0.01 rad/s about x (less the bias estimate)
    assert 2 * np.arcsin(np.linalg.norm(estimate.q_wxyz[1:])) == pytest.approx(0.002, abs=2e-4)


def test_stop_ends_the_wait_for_a_tick():
    box, stop = inbox(), threading.Event()
    stop.set()
    assert box.next_tick(stop, poll_s=0.01) is None


# --- the smoother through a star-tracker outage ----------------------------------------------------
def test_the_smoother_propagates_on_the_gyro_through_an_outage_and_reconverges():
    scenario = scenario_with({"star_tracker_period_s": 1.0, "magnetometer_period_s": 1.0,
                              "star_tracker_outages_s": [[30.0, 90.0]]})
    assert scenario.estimator.mode == "smoother"
    n = 1200                                              # 120 s at 10 Hz, open loop
    plant = AttitudePlant(scenario.attitude, n, scenario.run.seed)
    plant.sim.omega_body_radps = np.deg2rad([0.3, -0.2, 0.4])
    estimator = AttitudeEstimator(scenario)
    error_deg = np.zeros(n)
    for k in range(n):
        s = plant.sense()
        e = estimator.step(k, plant.time_s, s.gyro_radps, s.magnetometer_t,
                           None if s.magnetometer_t is None else s.field_inertial_t, s.star_tracker_wxyz)
        assert e.valid
        error_deg[k] = np.degrees(qt.angle_between_rad(e.q_wxyz, plant.sim.q_wxyz))
        plant.apply(np.zeros(3))
    t = np.arange(n) * plant.dt_s
    before, during, after = error_deg[(t > 10) & (t < 30)], error_deg[(t >= 30) & (t < 90)], error_deg[t > 100]
    # Measured (seed 7): at most 0.064 deg before; the gyro (bias estimated) and the magnetometer
    # carry it through 60 s without a fix at 0.092 deg; 10 s after the outage, 0.045 deg.
    assert before.max() < 0.15
    assert during.max() < 0.5
    assert after.max() < 0.15


def test_an_estimate_between_keyframes_carries_the_gyros_uncertainty_too():
    """Between star-tracker fixes (0.5 s apart) the estimate is the last keyframe's carried by the
    gyro, and its covariance must be carried with it. Over 40 seeded open-loop runs of 5 s the
    average NEES of every tick (chi-square with 3 x 40 dof over 40) is inside its band, and no tick
    before a fix is out in the tail. With the keyframe's covariance held unchanged (the estimator
    before this test) the average NEES grew to 38 by the tick before the second fix, and to 4.5
    over 20 s of attitude_pointing_rt's sensors."""
    from bench.report.attitude_estimation import rotation_vector

    n_runs, n_ticks = 40, 50
    scenario = scenario_with({"star_tracker_period_s": 0.5, "magnetometer_period_s": 1.0,
                              "star_tracker_outages_s": []}, steps=n_ticks)
    nees = np.full((n_runs, n_ticks), np.nan)
    for run in range(n_runs):
        plant = AttitudePlant(scenario.attitude, n_ticks, 100 + run)
        estimator = AttitudeEstimator(scenario)
        for k in range(n_ticks):
            s = plant.sense()
            e = estimator.step(k, plant.time_s, s.gyro_radps, s.magnetometer_t,
                               None if s.magnetometer_t is None else s.field_inertial_t, s.star_tracker_wxyz)
            error = rotation_vector(np.array([plant.sim.q_wxyz]), np.array([e.q_wxyz]))[0]
            nees[run, k] = error @ np.linalg.solve(e.attitude_covariance_rad2, error)
            plant.apply(np.zeros(3))
    average = nees.mean(axis=0)
    low, high = stats.chi2.ppf([0.025, 0.975], 3 * n_runs) / n_runs
    tail = stats.chi2.ppf(0.999, 3 * n_runs) / n_runs
    assert low <= average.mean() <= high, np.round(average, 2)
    before_fix = average[4::5]                          # the ticks just before each fix
    assert before_fix.max() <= tail, np.round(before_fix, 2)


# --- the magnetometer in the board's coil-blanking windows ----------------------------------------
def rt_blanking(**board):
    data = tomllib.loads(resources.files("bench.scenarios").joinpath("attitude_detumble_rt.toml").read_text())
    data["attitude"]["sensors"]["magnetometer_sampling"] = "coil_blanking"
    data["can"]["board"] = board
    return parse_scenario(data, "test")


def test_coil_blanking_sampling_needs_the_boards_windows_each_at_least_a_tick_long():
    with pytest.raises(ScenarioError, match=r"test: attitude\.sensors\.magnetometer_sampling"):
        rt_blanking()
    with pytest.raises(ScenarioError, match=r"test: can\.board\.mag_window_s"):
        rt_blanking(mag_window_period_s=1.0, mag_window_s=0.05)         # a 0.1 s tick can step over it
    scenario = rt_blanking(mag_window_period_s=1.0, mag_window_s=0.15)
    assert SensorSchedule.from_sensors(scenario.attitude.sensors).has_magnetometer(0) is False   # not on a schedule


def test_the_magnetometer_samples_once_per_coil_blanking_window():
    from bench.plant.attitude_node import CoilBlankingGate

    blanked = [False, True, True, False, False, False, True, False, True, True, True, False]
    ticks = iter(blanked)
    gate = CoilBlankingGate(lambda: next(ticks))
    scenario = scenario_with()
    plant = AttitudePlant(scenario.attitude, len(blanked), seed=2, magnetometer_due=gate)   # tick 0 asks too
    sampled = []
    for k in range(len(blanked)):
        sampled.append(plant.sense().magnetometer_t is not None)
        if k < len(blanked) - 1:
            plant.apply(np.zeros(3))
    assert sampled == [False, True, False, False, False, False, True, False, True, False, False, False]
    assert gate.windows_sampled == 3
