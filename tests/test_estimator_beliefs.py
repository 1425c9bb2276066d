"""The flight side's beliefs are its own: a mistuned belief changes the run, the default belief is
the plant's truth (no process noise on the linear CWH), and the in-loop NEES then sits at 6."""
from __future__ import annotations

import numpy as np
import pytest
from estimator_loop import run_closed_loop
from scipy.stats import chi2

from bench.estimator.beliefs import OnboardBeliefs
from bench.config.estimator import TranslationSmootherConfig
from bench.gnc.cwh import RendezvousParams
from bench.plant.model import TranslationPlant
from bench.scenario import parse_scenario
from bench.sim import simulate_in_process

PARAMS = RendezvousParams.from_reference()


def _scenario(translation: dict, plant: dict | None = None, onboard: dict | None = None):
    return parse_scenario({"name": "t", "run": {"steps": 40}, "plant": plant or {}, "onboard": onboard or {},
                           "estimator": {"mode": "smoother", "translation": translation}})


def test_default_beliefs_are_the_plants_truth():
    beliefs = OnboardBeliefs.from_scenario(_scenario({}, {"relpos_sensor": {"noise_std_m": 4.0}}))
    assert beliefs.relpos_noise_std_m == 4.0 and beliefs.process_noise_psd_m2ps3 == 0.0
    assert beliefs.target_radius_m == PARAMS.target_radius_m


def test_onboard_beliefs_and_the_estimators_own_override():
    onboard = {"relpos_noise_std_m": 3.0, "process_noise_psd_m2ps3": 1e-12, "believed_radius_error": 0.01}
    beliefs = OnboardBeliefs.from_scenario(_scenario({}, onboard=onboard))
    assert (beliefs.relpos_noise_std_m, beliefs.process_noise_psd_m2ps3) == (3.0, 1e-12)
    assert beliefs.target_radius_m == pytest.approx(1.01 * PARAMS.target_radius_m)
    assert OnboardBeliefs.from_scenario(_scenario({"position_noise_std_m": 5.0}, onboard=onboard)).relpos_noise_std_m == 5.0


@pytest.mark.parametrize("belief, min_change_m", [
    # The plant's sensor has 10 m. Believing 3 m changes the fixes' weight against the velocity
    # prior only (no process noise: the fixes are all equally weighted among themselves), a
    # small change to the estimate; the covariance it reports is ~11 times too small.
    ({"position_noise_std_m": 3.0}, 1e-3),
    ({"onboard": {"relpos_noise_std_m": 3.0}}, 1e-3),
    # Believing in process noise the CWH plant does not have discounts old fixes: a large change.
    ({"process_noise_psd_m2ps3": 1e-9}, 1.0),
])
def test_a_mistuned_belief_changes_the_run(belief, min_change_m):
    # Before, the noise level in the measurement message overrode the belief: bit-identical runs.
    tuned, _ = simulate_in_process(_scenario({}))
    onboard = belief.pop("onboard", None)
    mistuned, _ = simulate_in_process(_scenario(belief, onboard=onboard))
    np.testing.assert_array_equal(tuned["state_m_mps"][0], mistuned["state_m_mps"][0])
    assert np.max(np.abs(tuned["estimate_m_mps"] - mistuned["estimate_m_mps"])) > min_change_m
    assert not np.array_equal(tuned["thrust_n"], mistuned["thrust_n"])


def test_in_loop_nees_is_six_without_invented_process_noise():
    # 50 seeded closed loops (LQR on the estimate) of 100 steps. Consecutive NEES samples are
    # correlated, so each run is judged by its time average; the average of the 50 independent
    # time averages must lie in the two-sided 95 % chi-square bounds of 50 x 6 dof. The old
    # default (an assumed 1e-9 m^2/s^3 the CWH plant does not have) gave ~3.2: outside.
    runs = 50
    per_run = []
    for seed in range(runs):
        r = run_closed_loop(PARAMS, TranslationSmootherConfig(), 10.0, seed=seed, steps=100)
        err = r.truth_m_mps[:-1] - r.estimate_m_mps
        per_run.append(np.mean([e @ np.linalg.solve(c, e) for e, c in zip(err, r.covariance)]))
    low, high = chi2.ppf([0.025, 0.975], runs * 6) / runs
    assert low <= np.mean(per_run) <= high, f"average in-loop NEES {np.mean(per_run):.2f}, bounds [{low:.2f}, {high:.2f}]"


def test_the_plant_senses_range_and_bearing_for_a_range_bearing_scenario():
    # The plant draws range/bearing noise from its own generator: the relative-position fixes of
    # a run are the same whichever sensor the estimator uses.
    scenario = _scenario({"sensor": "range_bearing"}, {"range_bearing_sensor": {"range_noise_std_m": 5.0}})
    assert OnboardBeliefs.from_scenario(scenario).range_noise_std_m == 5.0
    trajectory, metrics = simulate_in_process(scenario)
    truth, estimate = trajectory["state_m_mps"][:-1], trajectory["estimate_m_mps"]
    # Range 5 m and 0.1 mrad at ~1e5 m: the position is known to tens of metres after a few steps.
    assert np.median(np.linalg.norm(truth[10:, :3] - estimate[10:, :3], axis=1)) < 100.0
    with_rb, without = TranslationPlant.from_scenario(scenario), TranslationPlant.from_scenario(_scenario({}))
    for _ in range(3):
        with_rb.measure_range_bearing()
        np.testing.assert_array_equal(with_rb.measure_position_m(), without.measure_position_m())
