"""The whole loop in one process: the reference the multi-process bench must reproduce.

Same plant, estimator and controller-cycle objects as the processes use, called in the same order,
with the same seeded noise; only the wiring differs.
"""
from __future__ import annotations

import numpy as np

from bench.controller.cycle import ControlCycle
from bench.estimator.frontend import StateEstimator
from bench.plant.model import TranslationPlant
from bench.report.run_metrics import trajectory_metrics
from bench.scenario import Scenario


def simulate_in_process(scenario: Scenario) -> tuple[dict[str, np.ndarray], dict]:
    """Run the scenario without processes; return (trajectory arrays, metrics)."""
    plant = TranslationPlant.from_scenario(scenario)
    estimator = StateEstimator(scenario)
    control = ControlCycle(scenario)
    noise_std_m = scenario.plant.relpos_sensor.noise_std_m
    thrust_n = np.zeros(3)
    estimates = []
    for k in range(scenario.n_steps):
        position_m = plant.measure_position_m()
        estimate = estimator.step(k, plant.sim_time_s, truth_m_mps=plant.state_m_mps, position_m=position_m,
                                  position_noise_std_m=noise_std_m, thrust_commanded_n=thrust_n)
        thrust_n = control.run(estimate.state_m_mps, estimate.mean_motion_radps).thrust_n
        estimates.append(estimate.state_m_mps)
        plant.apply(thrust_n)
    trajectory = plant.trajectory()
    trajectory["estimate_m_mps"] = np.array(estimates)
    return trajectory, trajectory_metrics(trajectory["state_m_mps"], trajectory["thrust_n"], plant.params)
