"""The whole loop in one process: the reference the multi-process bench must reproduce.

Same plant, estimator and control-law objects as the processes use, called in the same order,
with the same seeded noise; only the wiring differs.
"""
from __future__ import annotations

import numpy as np

from bench.controller.thrust import ThrustLaw
from bench.estimator.truth import TruthEstimator
from bench.metrics import trajectory_metrics
from bench.plant.model import TranslationPlant
from bench.scenario import Scenario


def simulate_in_process(scenario: Scenario) -> tuple[dict[str, np.ndarray], dict]:
    """Run the scenario without processes; return (trajectory arrays, metrics)."""
    plant = TranslationPlant.from_scenario(scenario)
    estimator = TruthEstimator()
    law = ThrustLaw(scenario)
    for _ in range(scenario.n_steps):
        plant.measure_position_m()   # the sensor draws noise every step, as in the plant process
        state_m_mps, _, _ = estimator.estimate(plant.state_m_mps)
        thrust_n, _ = law.command(state_m_mps)
        plant.apply(thrust_n)
    trajectory = plant.trajectory()
    return trajectory, trajectory_metrics(trajectory["state_m_mps"], trajectory["thrust_n"], plant.params)
