"""Translational smoother: equals the Kalman filter on the linear model, is consistent (NEES),
survives failed updates, rejects bad input, and keeps the seed 003 rendezvous within its terminal
conditions with the smoother in the loop (known and 1 %-wrong orbit radius)."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam_faults import FailingSmoother
from scipy.stats import chi2

from bench.estimator import kalman
from bench.estimator.config import TranslationSmootherConfig
from bench.estimator.factors import range_bearing
from bench.estimator.motion_model import CwhMotionModel
from bench.estimator.translation import TranslationSmoother
from bench.gnc.cwh import RendezvousParams
from bench.report.plots import estimator_error
from estimator_loop import run_closed_loop

PARAMS = RendezvousParams.from_reference()
NOISE_M = 10.0


def _model(config: TranslationSmootherConfig):
    return CwhMotionModel(PARAMS.mass_kg, PARAMS.time_step_s, config.process_noise_psd_m2ps3).discrete(PARAMS.mean_motion)


@pytest.mark.parametrize("lag_steps, every", [(200, 1), (4, 1), (10, 3)])
def test_newest_estimate_equals_kalman_filter(lag_steps, every):
    # Linear Gaussian model: with the whole history in the window (200 > 60 steps) the smoother is
    # the batch least-squares solution, whose newest state is the Kalman filter's; a short window
    # must give the same, because marginalising a linear model is exact. every=3: a fix is used
    # every third step only, the filter predicts through the others.
    config = TranslationSmootherConfig(lag_steps=lag_steps, measurement_every_steps=every)
    smoother, m = TranslationSmoother(config, PARAMS), _model(config)
    rng = np.random.default_rng(11)
    x, thrust, kf = PARAMS.initial_state_m_mps("A"), np.zeros(3), None
    for k in range(60):
        fix = x[:3] + rng.normal(0.0, NOISE_M, 3)
        result = smoother.update(k, 600.0 * k, fix, thrust, NOISE_M)
        if kf is None:
            kf = kalman.initial_belief_from_position(fix, NOISE_M, config.initial_velocity_std_mps)
        else:
            kf = kalman.predict(kf, m.transition, m.input_matrix, thrust, m.process_cov)
            if k % every == 0:
                kf = kalman.correct(kf, fix, kalman.POSITION_MATRIX, np.eye(3) * NOISE_M**2)
        sigma = np.sqrt(np.diag(kf.covariance))
        # Equal to rounding: a micro-sigma, or the last digits of a 400 km position.
        assert np.all(np.abs(result.state_m_mps - kf.mean) <= 1e-6 * sigma + 1e-12 * np.abs(kf.mean))
        np.testing.assert_allclose(result.covariance / np.outer(sigma, sigma),
                                   kf.covariance / np.outer(sigma, sigma), rtol=0, atol=1e-7)
        thrust = rng.normal(0.0, 0.3, 3)
        x = m.transition @ x + m.input_matrix @ thrust


def _nees_monte_carlo(config: TranslationSmootherConfig, true_noise_m: float, runs: int, steps: int,
                      believed_radius_error: float = 0.0):
    """Per-step NEES of runs of a truth drawn from the smoother's own model (prior and Q)."""
    m = _model(config)
    nees = np.zeros((runs, steps))
    for run in range(runs):
        rng = np.random.default_rng(1000 + run)
        smoother = TranslationSmoother(config, PARAMS.with_radius_error(believed_radius_error))
        x = PARAMS.initial_state_m_mps("A").copy()
        x[3:] = rng.normal(0.0, config.initial_velocity_std_mps, 3)
        thrust = np.zeros(3)
        for k in range(steps):
            if config.sensor == "relpos":
                fix = x[:3] + rng.normal(0.0, true_noise_m, 3)
                r = smoother.update(k, 600.0 * k, fix, thrust)
            else:
                rb = range_bearing(x[:3]) + rng.normal(0.0, 1.0, 3) * [
                    config.range_noise_std_m, config.bearing_noise_std_rad, config.bearing_noise_std_rad]
                r = smoother.update(k, 600.0 * k, None, thrust, range_bearing=rb)
            err = x - r.state_m_mps
            nees[run, k] = err @ np.linalg.solve(r.covariance, err)
            thrust = rng.uniform(-0.5, 0.5, 3)
            x = m.transition @ x + m.input_matrix @ thrust + rng.multivariate_normal(np.zeros(6), m.process_cov)
    return nees


def _consistent(nees: np.ndarray, dof: int = 6) -> tuple[bool, float, float]:
    """Average NEES over runs inside the two-sided 95 % chi-square bounds (Bar-Shalom)."""
    runs = nees.shape[0]
    low, high = chi2.ppf([0.025, 0.975], runs * dof) / runs
    per_step = nees.mean(axis=0)
    inside = np.mean((per_step >= low) & (per_step <= high))
    # 95 % of the per-step averages should be inside; allow sampling slack down to 85 %.
    return bool(inside >= 0.85 and low <= per_step.mean() <= high), float(inside), float(per_step.mean())


# Short horizon (25 steps of 600 s) so 50 seeded runs stay within a couple of seconds.
RUNS, STEPS = 50, 25


@pytest.mark.parametrize("case, config, believed_radius_error", [
    ("relative position", TranslationSmootherConfig(lag_steps=10), 0.0),
    ("range/bearing", TranslationSmootherConfig(lag_steps=10, sensor="range_bearing"), 0.0),
    # The truth's orbit radius is 1 % off the believed one; the mean motion is estimated jointly.
    ("joint mean motion", TranslationSmootherConfig(lag_steps=10, estimate_mean_motion=True), 0.01),
])
def test_nees_within_chi_square_bounds(case, config, believed_radius_error):
    ok, inside, mean = _consistent(_nees_monte_carlo(config, NOISE_M, RUNS, STEPS, believed_radius_error))
    assert ok, f"{case}: average NEES {mean:.2f}, {inside:.0%} of steps inside the 95 % bounds"


@pytest.mark.parametrize("case, config, believed_radius_error", [
    ("believes 3 m, sensor has 10 m", TranslationSmootherConfig(position_noise_std_m=3.0, lag_steps=10), 0.0),
    ("orbit radius 1 % off, not estimated", TranslationSmootherConfig(lag_steps=10), 0.01),
])
def test_nees_check_catches_an_overconfident_smoother(case, config, believed_radius_error):
    ok, _, mean = _consistent(_nees_monte_carlo(config, NOISE_M, 20, STEPS, believed_radius_error))
    assert not ok and mean > 6.0, case


def test_failed_update_restarts_from_last_good_estimate(caplog):
    config = TranslationSmootherConfig()
    smoother, m = TranslationSmoother(config, PARAMS), _model(config)
    rng = np.random.default_rng(5)
    x = PARAMS.initial_state_m_mps("A")
    for k in range(40):
        if k == 20:
            smoother._smoother = FailingSmoother(smoother._smoother)
        r = smoother.update(k, 600.0 * k, x[:3] + rng.normal(0.0, NOISE_M, 3), np.zeros(3))
        assert r.reinitialised == (k == 20)
        err = x - r.state_m_mps
        assert err @ np.linalg.solve(r.covariance, err) < chi2.ppf(0.9999, 6)
        x = m.transition @ x
    assert r.failed_updates == 1
    assert "failed" in caplog.text


def test_smoother_keeps_publishing_while_gtsam_keeps_failing(monkeypatch):
    # Update and restart both fail for five steps: the smoother publishes its prediction, counts
    # every failure, and recovers with a working gtsam.
    config = TranslationSmootherConfig()
    smoother, m = TranslationSmoother(config, PARAMS), _model(config)
    real_class = gtsam.IncrementalFixedLagSmoother
    rng = np.random.default_rng(9)
    x = PARAMS.initial_state_m_mps("A")
    for k in range(40):
        if k == 20:
            smoother._smoother = FailingSmoother(smoother._smoother)
            monkeypatch.setattr(gtsam, "IncrementalFixedLagSmoother", lambda *a: FailingSmoother(real_class(*a)))
        if k == 25:
            monkeypatch.setattr(gtsam, "IncrementalFixedLagSmoother", real_class)
        r = smoother.update(k, 600.0 * k, x[:3] + rng.normal(0.0, NOISE_M, 3), np.zeros(3))
        assert r.reinitialised == (20 <= k <= 25)
        err = x - r.state_m_mps
        assert err @ np.linalg.solve(r.covariance, err) < chi2.ppf(0.9999, 6)
        x = m.transition @ x
    assert r.failed_updates == 1 + 5 + 0    # the update at 20, the restarts at 20..24; 25 succeeds
    # Predictions only from 20 to 24: the position uncertainty grew, then the fixes shrank it again.
    assert np.trace(r.covariance[:3, :3]) < 3 * 15.0**2


def test_no_estimate_before_the_first_fix_then_gaps_are_bridged():
    smoother = TranslationSmoother(TranslationSmootherConfig(), PARAMS)
    assert smoother.update(0, 0.0, None, np.zeros(3)) is None
    x = PARAMS.initial_state_m_mps("A")
    a, _ = PARAMS.discrete_si()
    first = smoother.update(1, 600.0, (a @ x)[:3], np.zeros(3))
    later = smoother.update(4, 2400.0, (np.linalg.matrix_power(a, 4) @ x)[:3], np.zeros(3))
    assert first is not None and later.seq == 4
    # Three missing steps widen the covariance beyond what a single step would.
    assert np.trace(later.covariance[3:, 3:]) < np.trace(first.covariance[3:, 3:])


@pytest.mark.parametrize("kwargs, message", [
    (dict(position_m=[1.0, np.nan, 2.0]), "position_m has non-finite"),
    (dict(position_m=[1.0, 2.0]), "position_m must have 3"),
    (dict(thrust_applied_n=[0.0, 0.0]), "thrust_applied_n must have 3"),
    (dict(position_noise_std_m=0.0), "position_noise_std_m must be positive"),
    (dict(range_bearing=[1.0, 0.0, 0.0]), "sensor is 'relpos'"),
])
def test_bad_input_is_named(kwargs, message):
    smoother = TranslationSmoother(TranslationSmootherConfig(), PARAMS)
    args = dict(seq=0, sim_time_s=0.0, position_m=[1.0, 2.0, 3.0], thrust_applied_n=[0.0, 0.0, 0.0])
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        smoother.update(**args)


def test_seq_must_increase():
    smoother = TranslationSmoother(TranslationSmootherConfig(), PARAMS)
    smoother.update(3, 0.0, [1.0, 2.0, 3.0], np.zeros(3))
    with pytest.raises(ValueError, match="seq must increase"):
        smoother.update(3, 0.0, [1.0, 2.0, 3.0], np.zeros(3))


def _meets_terminal_conditions(result) -> bool:
    position_m, velocity_mps = result.terminal_errors()
    return position_m <= PARAMS.max_final_position_m and velocity_mps <= PARAMS.max_final_velocity_mps


def test_default_rendezvous_meets_terminal_conditions_with_smoother_in_the_loop(tmp_path):
    result = run_closed_loop(PARAMS, TranslationSmootherConfig(), NOISE_M, seed=1)
    assert _meets_terminal_conditions(result), result.terminal_errors()
    assert result.failed_updates == 0
    # The estimate it flew on was consistent with its covariance (3 sigma per axis).
    err = result.truth_m_mps[:-1] - result.estimate_m_mps
    sigma = np.sqrt(np.diagonal(result.covariance, axis1=1, axis2=2))
    assert np.mean(np.abs(err) <= 3 * sigma) > 0.97
    # The report's figure of that run (bench.report draws it from recordings; here from the loop).
    time_s = PARAMS.time_step_s * np.arange(len(result.estimate_m_mps))
    figure = estimator_error(time_s, -err, 3 * sigma, tmp_path / "estimator_error.png")
    assert figure.stat().st_size > 10_000


def test_one_percent_radius_error_breaks_the_rendezvous_unless_mean_motion_is_estimated():
    wrong = TranslationSmootherConfig()
    assert not _meets_terminal_conditions(run_closed_loop(PARAMS, wrong, NOISE_M, seed=1, believed_radius_error=0.01))

    joint = TranslationSmootherConfig(estimate_mean_motion=True)
    smoother_params = TranslationSmoother(joint, PARAMS.with_radius_error(0.01))
    result = run_closed_loop(PARAMS, joint, NOISE_M, seed=1, believed_radius_error=0.01)
    assert _meets_terminal_conditions(result), result.terminal_errors()
    assert result.failed_updates == 0
    believed_error = abs(smoother_params.believed_mean_motion_radps / PARAMS.mean_motion - 1.0)
    final_error = abs(result.mean_motion_radps[-1] / PARAMS.mean_motion - 1.0)
    assert believed_error > 0.014 and final_error < 1e-3
