"""NEES and NIS of every translational smoother mode over 50 seeded runs, judged on each run's
time average (consecutive steps are correlated; a per-step fraction rule is fragile):
- NEES: the mean over the runs of each run's time-averaged NEES lies inside the two-sided 95 %
  chi-square bounds of runs x 6 degrees of freedom (a time average varies less than one step's
  NEES, so the bounds are, if anything, generous);
- NIS: the innovations of a consistent filter are white, so each run's time-averaged NIS is
  chi-square with (steps x 3) degrees of freedom over steps: at least 85 % of the runs (95 %
  expected, binomial slack for 50 runs) inside its 95 % bounds, and the mean over all runs inside
  the bounds of all the innovations together.
With the gate on, 5 % of the fixes are 1 km outliers: the gate must reject them and the NIS of
the accepted ones must still be consistent."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from bench.config.estimator import TranslationSmootherConfig
from bench.estimator.factors import range_bearing
from bench.estimator.motion_model import CwhMotionModel
from bench.estimator.translation import TranslationSmoother
from bench.gnc.cwh import RendezvousParams

PARAMS = RendezvousParams.from_reference()
RUNS, STEPS = 50, 25
OUTLIER_M = 1000.0


def monte_carlo(config: TranslationSmootherConfig, outlier_fraction: float = 0.0):
    """Per run: time-averaged NEES (all steps), NIS values of the used measurements, outliers
    rejected, outliers injected, clean fixes rejected."""
    truth_model = CwhMotionModel(PARAMS.mass_kg, PARAMS.time_step_s, config.process_noise_psd_m2ps3 or 0.0).discrete(
        PARAMS.mean_motion)
    runs = []
    for run in range(RUNS):
        rng = np.random.default_rng(7000 + run)
        smoother = TranslationSmoother(config, PARAMS.with_radius_error(0.01 if config.estimate_mean_motion else 0.0))
        x = PARAMS.initial_state_m_mps("A").copy()
        x[3:] = rng.normal(0.0, config.initial_velocity_std_mps, 3)
        thrust, nees, nis = np.zeros(3), [], []
        outliers = caught = false_alarms = 0
        for k in range(STEPS):
            # From step 3: before, the prediction is kilometres uncertain (the 10 m/s velocity prior
            # over 600 s) and a 1 km outlier is not an outlier to any gate.
            outlier = k >= 3 and rng.uniform() < outlier_fraction
            if config.sensor == "relpos":
                fix = x[:3] + rng.normal(0.0, smoother.position_noise_std_m, 3)
                if outlier:
                    fix = fix + OUTLIER_M * rng.choice([-1.0, 1.0], 3)
                r = smoother.update(k, 600.0 * k, fix, thrust)
            else:
                sigmas = np.array([smoother.range_noise_std_m, smoother.bearing_noise_std_rad,
                                   smoother.bearing_noise_std_rad])
                rb = range_bearing(x[:3]) + rng.normal(0.0, 1.0, 3) * sigmas
                if outlier:
                    rb[0] += OUTLIER_M
                r = smoother.update(k, 600.0 * k, None, thrust, range_bearing=rb)
            outliers += outlier
            caught += outlier and r.measurement_rejected
            false_alarms += (not outlier) and r.measurement_rejected
            if r.nis is not None and not r.measurement_rejected:
                nis.append(r.nis)
            err = x - r.state_m_mps
            nees.append(err @ np.linalg.solve(r.covariance, err))
            thrust = rng.uniform(-0.5, 0.5, 3)
            x = truth_model.transition @ x + truth_model.input_matrix @ thrust
        runs.append((np.mean(nees), np.array(nis), caught, outliers, false_alarms))
    return runs


JOINT = dict(estimate_mean_motion=True)    # believing the orbit radius 1 % off (monte_carlo)
MODES = {
    "relative position": TranslationSmootherConfig(lag_steps=10),
    "relative position, fix every 3rd step": TranslationSmootherConfig(lag_steps=10, measurement_every_steps=3),
    "range/bearing": TranslationSmootherConfig(lag_steps=10, sensor="range_bearing"),
    "joint mean motion": TranslationSmootherConfig(lag_steps=10, **JOINT),
    "range/bearing + joint mean motion": TranslationSmootherConfig(lag_steps=10, sensor="range_bearing", **JOINT),
}


def _assert_consistent(runs, case: str):
    time_averaged_nees = np.array([r[0] for r in runs])
    low, high = chi2.ppf([0.025, 0.975], RUNS * 6) / RUNS
    assert low <= time_averaged_nees.mean() <= high, (
        f"{case}: mean of the runs' time-averaged NEES {time_averaged_nees.mean():.2f}, bounds [{low:.2f}, {high:.2f}]")
    inside = []
    for _, nis, *_ in runs:
        n = nis.size
        run_low, run_high = chi2.ppf([0.025, 0.975], 3 * n) / n
        inside.append(run_low <= nis.mean() <= run_high)
    assert np.mean(inside) >= 0.85, f"{case}: {np.mean(inside):.0%} of the runs' time-averaged NIS inside 95 % bounds"
    all_nis = np.concatenate([r[1] for r in runs])
    all_low, all_high = chi2.ppf([0.025, 0.975], 3 * all_nis.size) / all_nis.size
    assert all_low <= all_nis.mean() <= all_high, f"{case}: mean NIS {all_nis.mean():.3f}, bounds [{all_low:.3f}, {all_high:.3f}]"


@pytest.mark.parametrize("case", sorted(MODES))
def test_nees_and_nis_of_every_mode(case):
    _assert_consistent(monte_carlo(MODES[case]), case)


@pytest.mark.parametrize("sensor", ["relpos", "range_bearing"])
def test_gate_keeps_nees_and_nis_consistent_with_outliers(sensor):
    config = TranslationSmootherConfig(lag_steps=10, sensor=sensor, gate_probability=0.9999)
    runs = monte_carlo(config, outlier_fraction=0.05)
    caught, outliers, false_alarms = (sum(r[i] for r in runs) for i in (2, 3, 4))
    assert outliers > 30 and caught == outliers, f"{caught} of {outliers} outliers rejected"
    assert false_alarms <= 2     # 1e-4 per clean fix, ~1200 clean fixes
    _assert_consistent(runs, f"{sensor} with 5 % outliers, gated")
