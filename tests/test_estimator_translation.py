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
from bench.config.estimator import TranslationSmootherConfig
from bench.estimator.factors import range_bearing
from bench.estimator.motion_model import CwhMotionModel
from bench.estimator import translation
from bench.estimator.translation import TranslationSmoother
from bench.gnc.cwh import RendezvousParams
from bench.report.plots import estimator_error
from estimator_loop import run_closed_loop

PARAMS = RendezvousParams.from_reference()
NOISE_M = 10.0


def _model(config: TranslationSmootherConfig):
    return CwhMotionModel(PARAMS.mass_kg, PARAMS.time_step_s, config.process_noise_psd_m2ps3 or 0.0).discrete(PARAMS.mean_motion)


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
                      fail_at: int | None = None, believed_radius_error: float = 0.0):
    """Per-step NEES of runs of a truth drawn from the smoother's own model (prior and Q).

    fail_at: gtsam's update fails at this step of every run (the smoother restarts).
    """
    m = _model(config)
    nees = np.zeros((runs, steps))
    for run in range(runs):
        rng = np.random.default_rng(1000 + run)
        smoother = TranslationSmoother(config, PARAMS.with_radius_error(believed_radius_error))
        x = PARAMS.initial_state_m_mps("A").copy()
        x[3:] = rng.normal(0.0, config.initial_velocity_std_mps, 3)
        thrust = np.zeros(3)
        for k in range(steps):
            if k == fail_at:
                smoother._smoother = FailingSmoother(smoother._smoother)
            if config.sensor == "relpos":
                fix = x[:3] + rng.normal(0.0, true_noise_m, 3)
                r = smoother.update(k, 600.0 * k, fix, thrust)
            else:
                rb = range_bearing(x[:3]) + rng.normal(0.0, 1.0, 3) * [
                    smoother.range_noise_std_m, smoother.bearing_noise_std_rad, smoother.bearing_noise_std_rad]
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
    ok, inside, mean = _consistent(_nees_monte_carlo(config, NOISE_M, RUNS, STEPS, believed_radius_error=believed_radius_error))
    assert ok, f"{case}: average NEES {mean:.2f}, {inside:.0%} of steps inside the 95 % bounds"


@pytest.mark.parametrize("case, config, believed_radius_error", [
    ("believes 3 m, sensor has 10 m", TranslationSmootherConfig(position_noise_std_m=3.0, lag_steps=10), 0.0),
    ("orbit radius 1 % off, not estimated", TranslationSmootherConfig(lag_steps=10), 0.01),
])
def test_nees_check_catches_an_overconfident_smoother(case, config, believed_radius_error):
    ok, _, mean = _consistent(_nees_monte_carlo(config, NOISE_M, 20, STEPS, believed_radius_error=believed_radius_error))
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


# Every measurement pattern a scenario can configure: a fix every step, every second step, and
# sparser; each sensor; with and without the joint mean motion. QR factorisation keeps gtsam away
# from "indeterminate linear system" on all of them (Cholesky failed on 19 of these 20).
@pytest.mark.parametrize("every", [1, 2, 3, 5, 10])
@pytest.mark.parametrize("sensor", ["relpos", "range_bearing"])
@pytest.mark.parametrize("joint", [False, True], ids=["known orbit", "joint mean motion"])
def test_no_failed_updates_on_any_measurement_pattern(every, sensor, joint):
    config = TranslationSmootherConfig(measurement_every_steps=every, sensor=sensor, estimate_mean_motion=joint)
    smoother = TranslationSmoother(config, PARAMS.with_radius_error(0.01 if joint else 0.0))
    a, _ = PARAMS.discrete_si()
    rng = np.random.default_rng(1)
    x = PARAMS.initial_state_m_mps("A")
    for k in range(60):
        if sensor == "relpos":
            r = smoother.update(k, 600.0 * k, x[:3] + rng.normal(0.0, NOISE_M, 3), np.zeros(3))
        else:
            rb = range_bearing(x[:3]) + rng.normal(0.0, 1.0, 3) * [10.0, 1e-4, 1e-4]
            r = smoother.update(k, 600.0 * k, None, np.zeros(3), range_bearing=rb)
        assert not r.reinitialised
        x = a @ x
    assert smoother.failed_updates == 0


JOINT = TranslationSmootherConfig(lag_steps=10, estimate_mean_motion=True)
JOINT_RADIUS_ERROR = 0.01     # the flight side believes the orbit radius 1 % off (the truth's)


def _believed_params(config: TranslationSmootherConfig):
    return PARAMS.with_radius_error(JOINT_RADIUS_ERROR if config.estimate_mean_motion else 0.0)


@pytest.mark.parametrize("case, config", [("known orbit", TranslationSmootherConfig(lag_steps=10)),
                                          ("joint mean motion", JOINT)])
def test_restart_keeps_the_joint_covariance(case, config):
    # The same data into two smoothers; gtsam fails once in the second. The restart's prior is
    # the last joint estimate (state and delta with their cross-covariance) carried one step, so
    # the restarted smoother must go on as if nothing had happened: exactly for the linear model,
    # to first order in delta (measured: within 0.011 sigma and 0.4 % of the covariance;
    # dropping the cross-covariance gave 4-13 % of sigma and 10-22 % of the covariance).
    intact, restarted = TranslationSmoother(config, _believed_params(config)), TranslationSmoother(config, _believed_params(config))
    a, b = PARAMS.discrete_si()
    rng = np.random.default_rng(3)
    x, thrust = PARAMS.initial_state_m_mps("A"), np.zeros(3)
    for k in range(40):
        if k == 20:
            restarted._smoother = FailingSmoother(restarted._smoother)
        fix = x[:3] + rng.normal(0.0, NOISE_M, 3)
        r1, r2 = intact.update(k, 600.0 * k, fix, thrust), restarted.update(k, 600.0 * k, fix, thrust)
        if k >= 20:
            sigma = np.sqrt(np.diag(r1.covariance))
            assert np.max(np.abs(r1.state_m_mps - r2.state_m_mps) / sigma) < 0.03, (case, k)
            assert np.max(np.abs(r1.covariance - r2.covariance) / np.outer(sigma, sigma)) < 0.02, (case, k)
            if r1.mean_motion_std_radps is not None:
                assert r2.mean_motion_std_radps == pytest.approx(r1.mean_motion_std_radps, rel=0.01)
        thrust = rng.uniform(-0.2, 0.2, 3)
        x = a @ x + b @ thrust
    assert restarted.failed_updates == 1 and intact.failed_updates == 0


def test_nees_after_an_injected_failure_within_the_same_bounds():
    # Every run's update fails at step 5, while the state / mean-motion correlation is strongest.
    nees = _nees_monte_carlo(JOINT, NOISE_M, RUNS, STEPS, fail_at=5, believed_radius_error=JOINT_RADIUS_ERROR)
    ok, inside, mean = _consistent(nees)
    assert ok, f"average NEES {mean:.2f} after a restart, {inside:.0%} of steps inside the 95 % bounds"


def _run_with_outlier(config: TranslationSmootherConfig, outlier_m: float, steps: int = 40, at: int = 20):
    """Estimates of a smoother fed fixes with one outlier of `outlier_m` (along x) at step `at`."""
    smoother, (a, _) = TranslationSmoother(config, PARAMS), PARAMS.discrete_si()
    rng = np.random.default_rng(21)
    x, results, truth = PARAMS.initial_state_m_mps("A"), [], []
    for k in range(steps):
        fix = x[:3] + rng.normal(0.0, NOISE_M, 3) + (np.array([outlier_m, 0.0, 0.0]) if k == at else 0.0)
        results.append(smoother.update(k, 600.0 * k, fix, np.zeros(3)))
        truth.append(x)
        x = a @ x
    return results, np.array(truth)


@pytest.mark.parametrize("options, bound_sigma", [
    (dict(), 1.5),     # the default: gated
    (dict(gate_probability=None, robust_loss="huber"), 3.0), (dict(gate_probability=None, robust_loss="cauchy"), 1.0),
], ids=["gate (default)", "huber", "cauchy"])
def test_a_1_km_outlier_does_not_move_the_estimate(options, bound_sigma):
    # Without protection a single 1 km fix drags the estimate by ~200 m (over 10 sigma). The
    # chi-square gate rejects it (what is left is the lost fix, about 1 sigma); Huber bounds its influence to the threshold
    # (3 sigma of residual, hence a shift of ~2.5 sigma here); Cauchy's weight falls as 1/r^2.
    plain, truth = _run_with_outlier(TranslationSmootherConfig(gate_probability=None), 1000.0)
    clean, _ = _run_with_outlier(TranslationSmootherConfig(**options), 0.0)
    protected, _ = _run_with_outlier(TranslationSmootherConfig(**options), 1000.0)
    sigma = np.sqrt(np.diag(clean[20].covariance))[:3]
    assert np.max(np.abs(plain[20].state_m_mps[:3] - clean[20].state_m_mps[:3]) / sigma) > 10.0
    for k in range(20, 40):
        shift = np.abs(protected[k].state_m_mps[:3] - clean[k].state_m_mps[:3]) / sigma
        assert np.all(shift < bound_sigma), (k, shift)
    assert protected[20].nis > 1000.0 and clean[20].nis < 20.0
    if "gate_probability" not in options:
        assert protected[20].measurement_rejected and protected[-1].rejected_measurements == 1
        assert not any(r.measurement_rejected for r in clean)


def test_a_late_measurement_is_applied_at_its_sensing_time():
    # The fix of step 10 arrives after step 13: applied to x_10 inside the window, the newest
    # estimate is the one of a smoother that had it on time (the model is linear: exactly).
    config = TranslationSmootherConfig(lag_steps=10)
    on_time, late = TranslationSmoother(config, PARAMS), TranslationSmoother(config, PARAMS)
    a, b = PARAMS.discrete_si()
    rng = np.random.default_rng(4)
    x, thrust = PARAMS.initial_state_m_mps("A"), np.zeros(3)
    fixes = {}
    for k in range(20):
        fixes[k] = x[:3] + rng.normal(0.0, NOISE_M, 3)
        expected = on_time.update(k, 600.0 * k, fixes[k], thrust)
        got = late.update(k, 600.0 * k, None if k == 10 else fixes[k], thrust)
        if k == 13:
            got = late.add_late_measurement(10, fixes[10])
            assert got.seq == 13 and got.nis is not None
        if k >= 13:
            sigma = np.sqrt(np.diag(expected.covariance))
            assert np.max(np.abs(got.state_m_mps - expected.state_m_mps) / sigma) < 1e-6, k
            np.testing.assert_allclose(got.covariance / np.outer(sigma, sigma),
                                       expected.covariance / np.outer(sigma, sigma), atol=1e-7)
        thrust = rng.uniform(-0.2, 0.2, 3)
        x = a @ x + b @ thrust
    assert late.late_measurements_applied == 1
    # Older than the window (lag 10 steps): dropped and counted, the estimate untouched.
    assert late.add_late_measurement(2, fixes[2]) is None and late.late_measurements_dropped == 1
    with pytest.raises(ValueError, match="not late"):
        late.add_late_measurement(25, fixes[2])


def test_joint_marginal_full_matrix_is_in_query_order():
    # The smoothers read gtsam's JointMarginal.fullMatrix() as [first key; second key]: check it
    # against the blocks at(), in both orders.
    smoother = TranslationSmoother(JOINT, _believed_params(JOINT))
    x = PARAMS.initial_state_m_mps("A")
    for k in range(5):
        smoother.update(k, 600.0 * k, x[:3], np.zeros(3))
        x = PARAMS.discrete_si()[0] @ x
    isam = smoother._smoother.getISAM2()
    for keys in ([gtsam.symbol("x", 4), gtsam.symbol("n", 0)], [gtsam.symbol("n", 0), gtsam.symbol("x", 4)]):
        joint = isam.jointMarginalCovariance(keys)
        np.testing.assert_array_equal(joint.fullMatrix(), np.block([[joint.at(a, b) for b in keys] for a in keys]))


def _rb_run(config: TranslationSmootherConfig, steps: int = 80):
    smoother, (a, b) = TranslationSmoother(config, _believed_params(config)), PARAMS.discrete_si()
    rng = np.random.default_rng(17)
    x, thrust, out = PARAMS.initial_state_m_mps("A"), np.zeros(3), []
    for k in range(steps):
        rb = range_bearing(x[:3]) + rng.normal(0.0, 1.0, 3) * [10.0, 1e-4, 1e-4]
        out.append(smoother.update(k, 600.0 * k, None, thrust, range_bearing=rb))
        thrust = rng.uniform(-0.2, 0.2, 3)
        x = a @ x + b @ thrust
    return out


@pytest.mark.parametrize("joint", [False, True], ids=["known orbit", "joint mean motion"])
def test_fast_factors_leave_the_estimates_unchanged(joint, monkeypatch):
    # Speed (benchmarks/bench_estimator.py): range/bearing linearised once about its (iterated)
    # prediction instead of gtsam's nonlinear factor relinearised every update, and states
    # relinearised only beyond 10 m / 10 mm/s when every measurement is linear in them. Reference:
    # gtsam's nonlinear factors with the 0.1 m / 0.1 mm/s thresholds. Stated tolerance: 0.03 sigma
    # of the state, 0.01 sigma of the mean motion (measured: 0.0004 and 0.017 / 0.004).
    options = dict(sensor="range_bearing", estimate_mean_motion=joint)
    fast = _rb_run(TranslationSmootherConfig(**options))
    monkeypatch.setattr(translation, "_STATE_RELINEARISE_LINEAR_MEASUREMENTS", translation._STATE_RELINEARISE)
    reference = _rb_run(TranslationSmootherConfig(range_bearing_linearisation="every_update", **options))
    for f, r in zip(fast, reference):
        sigma = np.sqrt(np.diag(r.covariance))
        assert np.max(np.abs(f.state_m_mps - r.state_m_mps) / sigma) < 0.03, f.seq
        assert np.max(np.abs(f.covariance - r.covariance) / np.outer(sigma, sigma)) < 0.03, f.seq
        if joint:
            assert abs(f.mean_motion_radps - r.mean_motion_radps) < 0.01 * r.mean_motion_std_radps, f.seq
