"""Navigation through outlier bursts (issue 27): the default smoother's gate cannot be walked open
by a run of outliers, re-acquires after a real jump, robust losses are relinearised to the batch
optimum, and every built-in smoother scenario flies protected.

The Monte Carlo here is the bounded version of benchmarks/bench_outliers.py (30 runs per regime):
a few seeded runs per regime, the same criteria (tests/outlier_monte_carlo.py)."""
from __future__ import annotations

from pathlib import Path

import gtsam
import msgspec
import numpy as np
import pytest

from bench.estimator import factors
from bench.config.estimator import TranslationSmootherConfig
from bench.estimator.motion_model import CwhMotionModel
from bench.estimator.translation import TranslationSmoother, state_key
from bench.scenario import load_scenario
from outlier_monte_carlo import PARAMS, default_smoother_config, monte_carlo, regime_config

RUNS = 4
PROCESS_NOISE_PSD = 1.0e-6      # 8.5 m of position random walk per 600 s step, against 10 m fixes


@pytest.mark.parametrize("process_noise_psd", [0.0, PROCESS_NOISE_PSD], ids=["no process noise", "process noise"])
@pytest.mark.parametrize("sensor", ["relpos", "range_bearing"])
def test_default_smoother_passes_the_outlier_monte_carlo(sensor, process_noise_psd):
    verdict = monte_carlo(regime_config(default_smoother_config(), sensor, process_noise_psd), RUNS)
    assert verdict.rms_ratio <= 1.5, verdict
    assert verdict.good_rejected_after_burst == 0, verdict
    low, high = verdict.nees_bounds
    assert low <= verdict.nees_after <= high, verdict
    assert verdict.outliers_used <= 1, verdict     # of 8 per run; RMS and NEES above judge what one costs


def test_the_monte_carlo_fails_a_gate_that_a_burst_walks_open():
    # The gate as it was (no burst guard, no re-acquisition): with process noise the prediction
    # widens while the burst is rejected until a burst fix fits; the estimate jumps to it and the
    # good fixes after the burst are rejected.
    walked = regime_config(default_smoother_config(), "relpos", PROCESS_NOISE_PSD,
                           gate_burst_likelihood_ratio=1e15, reacquire_after_rejections=10_000)
    verdict = monte_carlo(walked, RUNS)
    assert verdict.outliers_used > 0 and verdict.good_rejected_after_burst > 0
    assert not verdict.passed


def test_a_real_jump_is_reacquired_from_consistent_fixes():
    # The chaser really moves 300 m off its predicted path at step 15 (an unmodelled manoeuvre
    # the smoother cannot know of): every fix disagrees with the prediction. After
    # reacquire_after_rejections rejected fixes that agree with each other the smoother restarts
    # from their track, counts it, and is consistent with the truth again.
    config = TranslationSmootherConfig()
    smoother, (a, _) = TranslationSmoother(config, PARAMS), PARAMS.discrete_si()
    rng = np.random.default_rng(5)
    x = PARAMS.initial_state_m_mps("A")
    results, truth = [], []
    for k in range(40):
        if k == 15:
            x = x + np.array([300.0, -200.0, 100.0, 0.0, 0.0, 0.0])
        results.append(smoother.update(k, 600.0 * k, x[:3] + rng.normal(0.0, 10.0, 3), np.zeros(3)))
        truth.append(x)
        x = a @ x
    rejected = [r.seq for r in results if r.measurement_rejected]
    reacquired = [r.seq for r in results if r.reacquired]
    assert rejected == list(range(15, 15 + config.reacquire_after_rejections)), rejected
    assert reacquired == [15 + config.reacquire_after_rejections]
    assert results[-1].reacquisitions == 1 and results[-1].rejection_run == 0
    for r, x_true in zip(results[reacquired[0]:], truth[reacquired[0]:]):
        e = r.state_m_mps - x_true
        assert e @ np.linalg.solve(r.covariance, e) < 30.0, r.seq     # chi-square(6) 0.99999 quantile: 33


@pytest.mark.parametrize("loss", ["huber", "cauchy"])
@pytest.mark.parametrize("sensor", ["relpos", "range_bearing"])
def test_robust_loss_is_relinearised_to_the_batch_optimum(loss, sensor):
    # Independent reference: gtsam's batch Levenberg-Marquardt on the whole graph (the window
    # holds every step), iterated to convergence; the smoother's newest estimate must agree.
    steps, noise = 12, np.array([10.0, 1e-4, 1e-4]) if sensor == "range_bearing" else np.full(3, 10.0)
    # Some process noise: with none the motion factors are 1e8 times stiffer than the fixes and LM
    # stops on its relative tolerance before the robust weights settle.
    config = TranslationSmootherConfig(lag_steps=50, gate_probability=None, robust_loss=loss, sensor=sensor,
                                       process_noise_psd_m2ps3=1e-9)
    smoother = TranslationSmoother(config, PARAMS)
    model = CwhMotionModel(PARAMS.mass_kg, PARAMS.time_step_s, 1e-9).discrete(PARAMS.mean_motion)
    rng = np.random.default_rng(8)
    x = PARAMS.initial_state_m_mps("A")
    graph, guess = gtsam.NonlinearFactorGraph(), gtsam.Values()
    base = gtsam.noiseModel.Diagonal.Sigmas(noise)
    robust = gtsam.noiseModel.Robust.Create(
        (gtsam.noiseModel.mEstimator.Huber if loss == "huber" else gtsam.noiseModel.mEstimator.Cauchy).Create(3.0), base)
    for k in range(steps):
        clean = x[:3] if sensor == "relpos" else factors.range_bearing(x[:3])
        # Fixes 4 to 8 sigma off at steps 6 and 9: where the robust weight matters most.
        z = clean + rng.normal(0.0, 1.0, 3) * noise + (np.array([6.0, -4.0, 3.0]) * noise if k in (6, 9) else 0.0)
        if sensor == "relpos":
            result = smoother.update(k, 600.0 * k, z, np.zeros(3))
            graph.add(factors.position_factor(state_key(k), z, robust))
        else:
            result = smoother.update(k, 600.0 * k, None, np.zeros(3), range_bearing=z)
            graph.add(factors.range_bearing_factor(state_key(k), z, robust))
        if k == 0:
            graph.add(factors.linear_factor([(state_key(0), np.hstack([np.zeros((3, 3)), np.eye(3)]))],
                                            np.zeros(3), np.eye(3) * config.initial_velocity_std_mps**2))
        else:
            graph.add(factors.cwh_motion_factor(state_key(k - 1), state_key(k), np.zeros(3), model))
        guess.insert(state_key(k), x + rng.normal(0.0, 1.0, 6) * [20, 20, 20, 0.05, 0.05, 0.05])
        x = model.transition @ x
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-12)
    params.setMaxIterations(200)
    batch = gtsam.LevenbergMarquardtOptimizer(graph, guess, params).optimize()
    reference = batch.atVector(state_key(steps - 1))
    sigma = np.sqrt(np.diag(result.covariance))
    assert np.max(np.abs(result.state_m_mps - reference) / sigma) < 0.02


def test_every_built_in_smoother_scenario_is_protected():
    scenarios = sorted((Path(__file__).resolve().parents[1] / "bench" / "scenarios").glob("rendezvous_*.toml"))
    smoothers = [s for s in map(load_scenario, scenarios) if s.estimator.mode == "smoother"]
    assert len(smoothers) >= 3
    for scenario in smoothers:
        translation = scenario.estimator.translation
        assert translation.gate_probability is not None and translation.gate_probability >= 0.999, scenario.name
        assert translation.reacquire_after_rejections > 5, scenario.name   # longer than the Monte Carlo's burst
    # And the default: a scenario that says nothing about protection gets it.
    assert msgspec.convert({}, TranslationSmootherConfig).gate_probability == 0.9999
