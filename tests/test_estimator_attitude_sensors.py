"""Attitude sensor models of the smoother: the star tracker's error larger about its boresight,
the magnetometer's bias and scale factor (believed or estimated). Each model is checked against
an independent reference (the plant's own draws, finite differences, gtsam's MagFactor1)."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2
from test_estimator_attitude import INERTIA, _run, _within_bounds

from bench.estimator import factors
from bench.estimator.attitude import AttitudeSmoother, star_tracker_covariance
from bench.config.estimator import AttitudeSmootherConfig
from bench.plant.attitude import AttitudeSensorSpec, AttitudeSimulation, body_to_inertial

RUNS, TICKS = 50, 250
BIASED = AttitudeSensorSpec(magnetometer_bias_t=(2e-6, -1e-6, 1.5e-6), magnetometer_scale=1.02)


def test_star_tracker_covariance_is_what_the_plant_draws():
    # Independent reference: the sample covariance of the plant's star-tracker errors (its own
    # draw, written as sigma z + (sigma_b - sigma)(a . z) a), with a tilted boresight.
    spec = AttitudeSensorSpec(star_tracker_period_s=0.1, magnetometer_period_s=1000.0,
                              star_tracker_boresight_body=(0.0, 0.6, 0.8))
    sim = AttitudeSimulation(INERTIA, [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0], spec, seed=5)
    errors = []
    for _ in range(20000):
        s = sim.step()
        truth = body_to_inertial(sim.q_wxyz)
        errors.append((truth.inv() * Rotation.from_quat(s.star_tracker_wxyz, scalar_first=True)).as_rotvec())
    sample = np.cov(np.array(errors).T)
    model = star_tracker_covariance(spec.star_tracker_noise_std_rad, spec.star_tracker_boresight_noise_std_rad,
                                    spec.star_tracker_boresight_body)
    scale = np.sqrt(np.outer(np.diag(model), np.diag(model)))
    np.testing.assert_allclose(sample / scale, model / scale, atol=0.03)
    axis = np.array([0.0, 0.6, 0.8])
    assert np.sqrt(axis @ model @ axis) == pytest.approx(8e-4)


def test_nees_catches_a_star_tracker_believed_isotropic():
    # The plant's star tracker errs 8 times more about its boresight; a smoother that believes
    # it isotropic is overconfident about the roll (measured: average attitude NEES ~19).
    overconfident = AttitudeSmootherConfig(star_tracker_boresight_noise_std_rad=1e-4)
    nees = np.stack([_run(overconfident, AttitudeSensorSpec(), seed, TICKS)[0] for seed in range(15)])
    assert not _within_bounds(nees[..., 0])


def test_calibrated_magnetometer_factor_jacobians_match_finite_differences():
    rotation = gtsam.Rot3.Quaternion(*Rotation.random(random_state=8).as_quat(scalar_first=True))
    field = np.array([1.2e-5, -2.5e-5, 0.8e-5])
    calibration = np.array([1.5, -0.7, 2.0, 0.015])
    factor = factors.magnetometer_calibrated_factor(1, 2, np.array([1e-5, 2e-5, -1e-5]), field,
                                                    gtsam.noiseModel.Isotropic.Sigma(3, 1e-7))
    values = gtsam.Values()
    values.insert(1, rotation)
    values.insert(2, calibration)
    linear = factor.linearize(values)
    a_rotation, a_calibration = linear.jacobian()[0][:, :3], linear.jacobian()[0][:, 3:]

    def whitened(r, c):
        v = gtsam.Values()
        v.insert(1, r)
        v.insert(2, c)
        return factor.whitenedError(v)

    h = 1e-7
    numeric_r = np.column_stack([(whitened(rotation.retract(h * e), calibration)
                                  - whitened(rotation.retract(-h * e), calibration)) / (2 * h) for e in np.eye(3)])
    numeric_c = np.column_stack([(whitened(rotation, calibration + h * e)
                                  - whitened(rotation, calibration - h * e)) / (2 * h) for e in np.eye(4)])
    # The linearised factor is whitened and its sign convention is A dx = -error: compare magnitudes
    # through the same whitening.
    np.testing.assert_allclose(np.abs(a_rotation), np.abs(numeric_r), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.abs(a_calibration), np.abs(numeric_c), rtol=1e-5, atol=1e-6)


def test_calibrated_magnetometer_factor_equals_gtsams_magfactor1_at_known_calibration():
    rotation = gtsam.Rot3.Quaternion(*Rotation.random(random_state=9).as_quat(scalar_first=True))
    field, measured = np.array([1.2e-5, -2.5e-5, 0.8e-5]), np.array([1e-5, 2e-5, -1e-5])
    bias_t, scale = np.array([1.5e-6, -0.7e-6, 2.0e-6]), 1.015
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 1e-7)
    ours = factors.magnetometer_calibrated_factor(1, 2, measured, field, noise)
    values = gtsam.Values()
    values.insert(1, rotation)
    values.insert(2, np.concatenate([bias_t / factors.MAGNETOMETER_BIAS_UNIT_T, [scale - 1.0]]))
    reference = gtsam.MagFactor1(1, measured, scale * np.linalg.norm(field), gtsam.Unit3(field), bias_t, noise)
    ref_values = gtsam.Values()
    ref_values.insert(1, rotation)
    np.testing.assert_allclose(ours.whitenedError(values), reference.whitenedError(ref_values), rtol=1e-9, atol=1e-9)


def _drawn_calibration(config: AttitudeSmootherConfig, seed: int) -> AttitudeSensorSpec:
    """A plant magnetometer whose bias and scale are drawn from the smoother's prior (one per run:
    with one fixed calibration for all runs their errors would not average out over the runs)."""
    rng = np.random.default_rng(500 + seed)
    return AttitudeSensorSpec(magnetometer_bias_t=tuple(rng.normal(0.0, config.magnetometer_bias_prior_std_t, 3)),
                              magnetometer_scale=1.0 + rng.normal(0.0, config.magnetometer_scale_prior_std))


def test_a_biased_magnetometer_is_caught_and_estimated():
    # The plant's magnetometer has a 2.7 uT bias (27 noise sigmas) and a 2 % scale error.
    believed_perfect = np.stack([_run(AttitudeSmootherConfig(), BIASED, seed, TICKS)[0] for seed in range(5)])
    assert believed_perfect[..., 0].mean() > 100.0     # hopelessly overconfident (measured ~900)
    config = AttitudeSmootherConfig(estimate_magnetometer_calibration=True)
    nees = np.stack([_run(config, _drawn_calibration(config, seed), seed, TICKS)[0] for seed in range(RUNS)])
    assert _within_bounds(nees[..., 0]), f"attitude NEES {nees[..., 0].mean():.2f}"
    assert _within_bounds(nees[..., 1]), f"gyro-bias NEES {nees[..., 1].mean():.2f}"
    _, smoother, last = _run(config, BIASED, 3, 1200)
    error = np.concatenate([last.magnetometer_bias_t - BIASED.magnetometer_bias_t,
                            [last.magnetometer_scale - BIASED.magnetometer_scale]])
    unit = np.array([factors.MAGNETOMETER_BIAS_UNIT_T] * 3 + [1.0])
    covariance = smoother._last.covariance[6:, 6:] * np.outer(unit, unit)
    assert error @ np.linalg.solve(covariance, error) < chi2.ppf(0.999, 4)
    assert np.linalg.norm(error[:3]) < 0.2e-6


def _nees_and_nis(config: AttitudeSmootherConfig, spec_of_seed, runs: int = RUNS):
    """Per run: time-averaged attitude NEES and the NIS values (with their dof) of its keyframes."""
    out = []
    for seed in range(runs):
        rng = np.random.default_rng(seed)
        sim = AttitudeSimulation(INERTIA, Rotation.random(random_state=seed).as_quat(scalar_first=True),
                                 rng.normal(0.0, 0.02, 3), spec_of_seed(seed), seed=seed)
        smoother = AttitudeSmoother(config)
        nees, nis, dof, keyframe = [], [], [], 0
        for _ in range(TICKS):
            s = sim.step()
            smoother.add_gyro(s.gyro_radps, sim.dt_s)
            if s.magnetometer_t is None and s.star_tracker_wxyz is None:
                continue
            keyframe += 1
            r = smoother.update(keyframe, s.time_s, s.magnetometer_t, s.field_inertial_t, s.star_tracker_wxyz)
            if r is None:
                continue
            e = gtsam.Rot3.Logmap(r.rotation.between(gtsam.Rot3.Quaternion(*sim.truth().q_wxyz)))
            nees.append(e @ np.linalg.solve(r.attitude_covariance_rad2, e))
            if r.nis is not None:
                nis.append(r.nis)
                dof.append(r.nis_dof)
        out.append((np.mean(nees), np.array(nis), np.array(dof)))
    return out


@pytest.mark.parametrize("case", ["believed calibration", "estimated calibration"])
def test_attitude_nees_and_nis_time_averages_within_bounds(case):
    # As tests/test_estimator_consistency.py for translation: the mean of the runs' time-averaged
    # NEES inside the 95 % bounds of runs x 3 dof; each run's time-averaged NIS (white
    # innovations) inside the 95 % bounds of its total dof in at least 85 % of the runs.
    if case == "believed calibration":
        config, spec_of_seed = AttitudeSmootherConfig(), lambda seed: AttitudeSensorSpec()
    else:
        config = AttitudeSmootherConfig(estimate_magnetometer_calibration=True)
        spec_of_seed = lambda seed: _drawn_calibration(config, seed)  # noqa: E731
    runs = _nees_and_nis(config, spec_of_seed)
    nees = np.array([r[0] for r in runs])
    low, high = chi2.ppf([0.025, 0.975], RUNS * 3) / RUNS
    assert low <= nees.mean() <= high, f"{case}: time-averaged NEES {nees.mean():.2f}, bounds [{low:.2f}, {high:.2f}]"
    inside = []
    for _, nis, dof in runs:
        run_low, run_high = chi2.ppf([0.025, 0.975], dof.sum())
        inside.append(run_low <= nis.sum() <= run_high)
    assert np.mean(inside) >= 0.85, f"{case}: {np.mean(inside):.0%} of the runs' NIS inside the 95 % bounds"
    total = np.concatenate([r[1] for r in runs]).sum()
    total_dof = np.concatenate([r[2] for r in runs]).sum()
    assert chi2.ppf(0.025, total_dof) <= total <= chi2.ppf(0.975, total_dof), f"{case}: mean NIS per dof {total / total_dof:.3f}"


def test_the_gate_rejects_a_wild_star_tracker_fix():
    # One star-tracker fix 5 degrees off (a misidentified star pattern): used, it drags the
    # attitude by degrees; gated, the keyframe's measurements are rejected and the gyro carries on.
    def corrupt(sample):
        if sample.star_tracker_wxyz is not None and sample.time_s == 20.0:
            wrong = Rotation.from_quat(sample.star_tracker_wxyz, scalar_first=True) * Rotation.from_rotvec([0.087, 0, 0])
            sample.star_tracker_wxyz = wrong.as_quat(scalar_first=True)
        return sample

    results = {}
    for gate in (None, 0.9999):
        sim = AttitudeSimulation(INERTIA, Rotation.random(random_state=6).as_quat(scalar_first=True),
                                 [0.01, -0.02, 0.015], AttitudeSensorSpec(), seed=6)
        smoother = AttitudeSmoother(AttitudeSmootherConfig(gate_probability=gate))
        keyframe, worst, rejected = 0, 0.0, []
        for _ in range(300):
            s = corrupt(sim.step())
            smoother.add_gyro(s.gyro_radps, sim.dt_s)
            if s.magnetometer_t is None and s.star_tracker_wxyz is None:
                continue
            keyframe += 1
            r = smoother.update(keyframe, s.time_s, s.magnetometer_t, s.field_inertial_t, s.star_tracker_wxyz)
            if r is None:
                continue
            rejected.append(r.measurement_rejected)
            if s.time_s >= 20.0:
                e = gtsam.Rot3.Logmap(r.rotation.between(gtsam.Rot3.Quaternion(*sim.truth().q_wxyz)))
                worst = max(worst, float(e @ np.linalg.solve(r.attitude_covariance_rad2, e)))
        results[gate] = (worst, sum(rejected), smoother.failed_updates)
    assert results[None][0] > 1000.0 and results[None][1] == 0
    assert results[0.9999][0] < chi2.ppf(0.9999, 3) and results[0.9999][1] == 1 and results[0.9999][2] == 0
