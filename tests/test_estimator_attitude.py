"""Attitude truth model and sensors, and the attitude/gyro-bias smoother: consistency (NEES over a
seeded Monte Carlo), every key constrained, failed updates survived, bad input named."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam_faults import FailingSmoother
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from bench.estimator.attitude import AttitudeSmoother
from bench.config.estimator import AttitudeSmootherConfig
from bench.plant.attitude import (
    EARTH_RADIUS_M, AttitudeSensorSpec, AttitudeSimulation, TiltedDipole, body_to_inertial, magnetorquer_torque_nm,
    rk4_attitude_step,
)

INERTIA = np.diag([0.03, 0.04, 0.02])    # kg m^2, a 3U-class CubeSat as in seed 004


# ---- plant --------------------------------------------------------------------------------------

def test_torque_free_body_keeps_momentum_energy_and_unit_quaternion():
    q, w = np.array([1.0, 0.0, 0.0, 0.0]), np.array([0.1, -0.05, 0.2])
    h0 = body_to_inertial(q).apply(INERTIA @ w)
    e0 = w @ INERTIA @ w
    for _ in range(2000):
        q, w = rk4_attitude_step(q, w, np.zeros(3), INERTIA, 0.1)
    np.testing.assert_allclose(body_to_inertial(q).apply(INERTIA @ w), h0, rtol=1e-6, atol=1e-9)
    assert w @ INERTIA @ w == pytest.approx(e0, rel=1e-6)
    assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-12)


def test_dipole_field_is_twice_as_strong_over_the_magnetic_pole():
    dipole = TiltedDipole(tilt_rad=0.0)
    over_pole = dipole.field_t(np.array([0.0, 0.0, EARTH_RADIUS_M]), 0.0)
    equator = dipole.field_t(np.array([EARTH_RADIUS_M, 0.0, 0.0]), 0.0)
    assert np.linalg.norm(over_pole) == pytest.approx(2 * np.linalg.norm(equator))
    assert np.linalg.norm(equator) == pytest.approx(dipole.equatorial_field_t)
    assert equator[2] > 0     # field lines point north at the equator


def test_magnetorquer_torque_is_perpendicular_to_the_field_and_changes_momentum():
    sim = AttitudeSimulation(INERTIA, [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0], seed=2)
    field = sim.field_body_t()
    torque = magnetorquer_torque_nm(np.array([0.1, 0.0, 0.0]), field)
    assert abs(torque @ field) < 1e-12 * np.linalg.norm(torque) * np.linalg.norm(field)
    sim.step(torque)
    # A 0.1 A m^2 dipole in a ~3e-5 T field for 0.1 s: angular momentum of order 1e-7 N m s.
    momentum = INERTIA @ sim.omega_body_radps
    assert np.linalg.norm(momentum - torque * sim.dt_s) < 1e-3 * np.linalg.norm(torque * sim.dt_s)


def test_noiseless_gyro_integrates_to_the_true_attitude():
    spec = AttitudeSensorSpec(gyro_noise_density_radps_per_rthz=0.0, gyro_bias_random_walk_radps2_per_rthz=0.0,
                              initial_gyro_bias_std_radps=0.0)
    sim = AttitudeSimulation(INERTIA, [1.0, 0.0, 0.0, 0.0], [0.05, 0.1, -0.2], spec, seed=3)
    attitude = Rotation.identity()
    for _ in range(500):
        sample = sim.step()
        attitude = attitude * Rotation.from_rotvec(sample.gyro_radps * sim.dt_s)
    assert (attitude.inv() * body_to_inertial(sim.q_wxyz)).magnitude() < 1e-10


# ---- smoother -----------------------------------------------------------------------------------

def _run(config: AttitudeSmootherConfig, spec: AttitudeSensorSpec, seed: int, ticks: int, on_keyframe=None):
    """Drive the smoother from the sensors; (rotation NEES, bias NEES) per keyframe with an estimate."""
    rng = np.random.default_rng(seed)
    sim = AttitudeSimulation(INERTIA, Rotation.random(random_state=seed).as_quat(scalar_first=True),
                             rng.normal(0.0, 0.02, 3), spec, seed=seed)
    smoother = AttitudeSmoother(config)
    nees, keyframe = [], 0
    for _ in range(ticks):
        s = sim.step()
        smoother.add_gyro(s.gyro_radps, sim.dt_s)
        if s.magnetometer_t is None and s.star_tracker_wxyz is None:
            continue
        keyframe += 1
        if on_keyframe is not None:
            on_keyframe(smoother, keyframe)
        r = smoother.update(keyframe, s.time_s, s.magnetometer_t, s.field_inertial_t, s.star_tracker_wxyz)
        if r is None:
            continue
        truth = sim.truth()
        e_rot = gtsam.Rot3.Logmap(r.rotation.between(gtsam.Rot3.Quaternion(*truth.q_wxyz)))
        e_bias = truth.gyro_bias_radps - r.gyro_bias_radps
        nees.append((e_rot @ np.linalg.solve(r.attitude_covariance_rad2, e_rot),
                     e_bias @ np.linalg.solve(r.gyro_bias_covariance, e_bias)))
    return np.array(nees), smoother, r


def _within_bounds(nees: np.ndarray, dof: int = 3) -> bool:
    runs = nees.shape[0]
    low, high = chi2.ppf([0.025, 0.975], runs * dof) / runs
    per_step = nees.mean(axis=0)
    return bool(np.mean((per_step >= low) & (per_step <= high)) >= 0.85 and low <= per_step.mean() <= high)


# 50 seeded runs of 25 s (25 keyframes, 3 star-tracker fixes, 250 gyro samples): short so the
# Monte Carlo stays within seconds; the bias is already observable after the second fix.
RUNS, TICKS = 50, 250


def test_attitude_and_bias_nees_within_chi_square_bounds():
    nees = np.stack([_run(AttitudeSmootherConfig(), AttitudeSensorSpec(), seed, TICKS)[0] for seed in range(RUNS)])
    rotation, bias = nees[..., 0], nees[..., 1]
    assert _within_bounds(rotation), f"attitude NEES mean {rotation.mean():.2f} (3 expected)"
    assert _within_bounds(bias), f"gyro-bias NEES mean {bias.mean():.2f} (3 expected)"


def test_nees_check_catches_an_overconfident_star_tracker_model():
    overconfident = AttitudeSmootherConfig(star_tracker_noise_std_rad=2e-5)   # truth is 1e-4 rad
    nees = np.stack([_run(overconfident, AttitudeSensorSpec(), seed, TICKS)[0] for seed in range(15)])
    assert not _within_bounds(nees[..., 0])


def test_every_keyframe_is_constrained_by_the_gyro_alone():
    # Star tracker only at start, no magnetometer: each new key has only the AHRS and bias-walk
    # factors. The solve must stay determinate and the attitude uncertainty must grow.
    spec = AttitudeSensorSpec(star_tracker_period_s=1000.0, magnetometer_period_s=1000.0)
    config = AttitudeSmootherConfig(lag_s=5.0)
    sim = AttitudeSimulation(INERTIA, [1.0, 0.0, 0.0, 0.0], [0.01, 0.0, 0.02], spec, seed=1)
    smoother = AttitudeSmoother(config)
    first = smoother.update(0, 0.0, star_tracker_wxyz=sim.q_wxyz)
    for k in range(1, 30):
        for _ in range(10):
            smoother.add_gyro(sim.step().gyro_radps, sim.dt_s)
        r = smoother.update(k, sim.time_s)
    assert r.failed_updates == 0
    assert np.trace(r.attitude_covariance_rad2) > 2 * np.trace(first.attitude_covariance_rad2)


def test_failed_update_restarts_from_last_good_estimate(caplog):
    def break_once(smoother, keyframe):
        if keyframe == 12:
            smoother._smoother = FailingSmoother(smoother._smoother)

    nees, smoother, last = _run(AttitudeSmootherConfig(), AttitudeSensorSpec(), 7, 400, on_keyframe=break_once)
    assert smoother.failed_updates == 1 and "failed" in caplog.text
    assert np.all(nees < chi2.ppf(0.9999, 3)), "estimate after the restart is not consistent"
    assert last.failed_updates == 1 and not last.reinitialised


def test_bad_attitude_input_is_named():
    smoother = AttitudeSmoother(AttitudeSmootherConfig())
    with pytest.raises(ValueError, match="unit quaternion"):
        smoother.update(0, 0.0, star_tracker_wxyz=[2.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="come together"):
        smoother.update(0, 0.0, magnetometer_t=[1e-5, 0.0, 0.0])
    with pytest.raises(ValueError, match="omega_radps"):
        smoother.add_gyro([0.0, np.inf, 0.0], 0.1)
    assert smoother.update(0, 0.0, magnetometer_t=[1e-5, 0, 0], field_inertial_t=[0, 1e-5, 0]) is None
    smoother.update(1, 1.0, star_tracker_wxyz=[1.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="no gyro samples"):
        smoother.update(2, 2.0, star_tracker_wxyz=[1.0, 0.0, 0.0, 0.0])


def test_restart_keeps_the_joint_covariance_in_the_new_body_frame():
    # The same sensor data into two smoothers; gtsam fails once in the second, on a keyframe with
    # the magnetometer only, while the body turns at ~0.4 rad/s. The restart's prior is the last
    # joint (attitude, bias) covariance carried by the gyro: rotated into the new body frame, the
    # attitude / bias correlation propagated through d(deltaR)/d(bias). The restarted smoother must
    # then go on as the intact one does (gtsam's AHRS factor is the independent reference here).
    spec = AttitudeSensorSpec(star_tracker_period_s=5.0)
    sim = AttitudeSimulation(INERTIA, Rotation.random(random_state=4).as_quat(scalar_first=True),
                             [0.3, -0.2, 0.25], spec, seed=4)
    intact, restarted = AttitudeSmoother(AttitudeSmootherConfig()), AttitudeSmoother(AttitudeSmootherConfig())
    keyframe = 0
    for _ in range(300):
        s = sim.step()
        for smoother in (intact, restarted):
            smoother.add_gyro(s.gyro_radps, sim.dt_s)
        if s.magnetometer_t is None and s.star_tracker_wxyz is None:
            continue
        keyframe += 1
        if keyframe == 17:
            restarted._smoother = FailingSmoother(restarted._smoother)
        r1 = intact.update(keyframe, s.time_s, s.magnetometer_t, s.field_inertial_t, s.star_tracker_wxyz)
        r2 = restarted.update(keyframe, s.time_s, s.magnetometer_t, s.field_inertial_t, s.star_tracker_wxyz)
        if keyframe < 17:
            continue
        cov1 = np.block([[r1.attitude_covariance_rad2, np.zeros((3, 3))], [np.zeros((3, 3)), r1.gyro_bias_covariance]])
        cov2 = np.block([[r2.attitude_covariance_rad2, np.zeros((3, 3))], [np.zeros((3, 3)), r2.gyro_bias_covariance]])
        if r1.joint_covariance is not None:
            cov1, cov2 = r1.joint_covariance, r2.joint_covariance
        sigma = np.sqrt(np.diag(cov1))
        attitude_difference = gtsam.Rot3.Logmap(r1.rotation.between(r2.rotation))
        assert np.all(np.abs(attitude_difference) < 1e-3 * sigma[:3]), keyframe
        assert np.all(np.abs(r1.gyro_bias_radps - r2.gyro_bias_radps) < 1e-3 * sigma[3:]), keyframe
        assert np.max(np.abs(cov1 - cov2) / np.outer(sigma, sigma)) < 1e-3, keyframe
    assert restarted.failed_updates == 1
