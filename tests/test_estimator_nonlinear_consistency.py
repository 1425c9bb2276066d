"""The smoother's NEES on the nonlinear plant (seed 001's nonlinear noisy-sensor cells, short):
with the two-body curvilinear motion model it is consistent; with the linear CWH model (what the
smoother used there before), it is not, whatever small process noise it believes.

Truth: the plant's integration of two-body relative motion (bench/plant/dynamics.py) from seed
001's start A dispersed (500 m per axis; velocity drawn from the smoother's own prior), a random
held thrust, seen in curvilinear coordinates through 10 m Cartesian fixes, as the plant gives
them. Judged as tests/test_estimator_consistency.py does: the mean over the runs of each run's
time-averaged NEES inside the two-sided 95 % chi-square bounds of runs x 6 degrees of freedom."""
from __future__ import annotations

import functools

import numpy as np
import pytest

from bench.config.estimator import TranslationSmootherConfig
from bench.estimator.translation import TranslationSmoother
from bench.gnc.cwh import RendezvousParams
from bench.plant.curvilinear import (cartesian_to_curvilinear, curvilinear_to_cartesian, position_to_curvilinear_m,
                                     thrust_to_lvlh)
from bench.plant.dynamics import propagate
from bench.studies.campaign_report import nees_bounds

PARAMS = RendezvousParams.from_reference()
RUNS, STEPS = 12, 20
NOISE_M = 10.0
VELOCITY_PRIOR_MPS = 1.0


@functools.lru_cache(maxsize=1)
def truth_runs():
    """Per run: curvilinear truth (STEPS + 1, 6), thrusts (STEPS, 3) and fixes (STEPS + 1, 3)."""
    radius = PARAMS.target_radius_m
    runs = []
    for run in range(RUNS):
        rng = np.random.default_rng(2400 + run)
        start = cartesian_to_curvilinear(np.array(PARAMS.initial_state_m_mps("A")), radius)
        start[:3] += rng.normal(0.0, 500.0, 3)
        start[3:] = rng.normal(0.0, VELOCITY_PRIOR_MPS, 3)
        cartesian = curvilinear_to_cartesian(start, radius)
        thrusts = rng.uniform(-0.2, 0.2, (STEPS, 3))
        states, fixes = [start], [position_to_curvilinear_m(cartesian[:3] + rng.normal(0, NOISE_M, 3), radius)]
        for thrust in thrusts:
            cartesian = propagate(cartesian, thrust_to_lvlh(thrust, cartesian[:3], radius), PARAMS.time_step_s,
                                  PARAMS, "nonlinear")
            states.append(cartesian_to_curvilinear(cartesian, radius))
            fixes.append(position_to_curvilinear_m(cartesian[:3] + rng.normal(0, NOISE_M, 3), radius))
        runs.append((np.array(states), thrusts, np.array(fixes)))
    return runs


def mean_nees(config: TranslationSmootherConfig) -> float:
    averages = []
    for states, thrusts, fixes in truth_runs():
        smoother = TranslationSmoother(config, PARAMS)
        nees, thrust = [], np.zeros(3)
        for k in range(STEPS + 1):
            result = smoother.update(k, k * PARAMS.time_step_s, fixes[k], thrust)
            error = states[k] - result.state_m_mps
            nees.append(float(error @ np.linalg.solve(result.covariance, error)))
            if k < STEPS:
                thrust = thrusts[k]
        averages.append(np.mean(nees))
    return float(np.mean(averages))


def config(motion_model: str, psd: float = 0.0) -> TranslationSmootherConfig:
    return TranslationSmootherConfig(motion_model=motion_model, process_noise_psd_m2ps3=psd,
                                     position_noise_std_m=NOISE_M, initial_velocity_std_mps=VELOCITY_PRIOR_MPS,
                                     gate_probability=None)


def test_two_body_model_is_consistent_on_the_nonlinear_plant():
    low, high = nees_bounds(RUNS)
    nees = mean_nees(config("two_body_curvilinear"))
    assert low <= nees <= high, f"mean NEES {nees:.2f} outside [{low:.2f}, {high:.2f}]"


@pytest.mark.parametrize("psd", [0.0, 1e-8])
def test_linear_model_is_not(psd):
    """The check above can fail: the CWH model (seed 001's smoother before, with its 1e-8 belief)."""
    _, high = nees_bounds(RUNS)
    assert mean_nees(config("cwh", psd)) > high
