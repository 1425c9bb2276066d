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
from bench.studies.campaign_metrics import run_metrics


def simulate_in_process(scenario: Scenario) -> tuple[dict[str, np.ndarray], dict]:
    """Run the scenario without processes; return (trajectory arrays, metrics)."""
    plant = TranslationPlant.from_scenario(scenario)
    estimator = StateEstimator(scenario)
    control = ControlCycle(scenario)
    thrust_n = np.zeros(3)
    estimates = []
    cycles = {"solve_time_s": [], "solver_iterations": [], "ctrl_feasible": []}   # per controller cycle
    for k in range(scenario.n_steps):
        position_m = plant.measure_position_m()
        # Drawn every step as the plant process does, so both keep the same noise sequence.
        range_bearing = plant.measure_range_bearing()
        measured = dict(range_bearing=range_bearing) if estimator.sensor == "range_bearing" else dict(position_m=position_m)
        estimate = estimator.step(k, plant.sim_time_s, truth_m_mps=plant.navigation_state_m_mps,
                                  thrust_commanded_n=thrust_n, **measured)
        outcome = control.run(estimate.state_m_mps, estimate.mean_motion_radps)
        thrust_n = outcome.thrust_n
        cycles["solve_time_s"].append(float(outcome.info.get("solve_time", np.nan)))
        cycles["solver_iterations"].append(int(outcome.info.get("iterations", 0)))
        cycles["ctrl_feasible"].append(bool(outcome.info.get("ctrl_feas", True)))
        estimates.append(estimate.state_m_mps)
        plant.apply(thrust_n)
    trajectory = plant.trajectory()
    trajectory["estimate_m_mps"] = np.array(estimates)
    trajectory.update({name: np.array(values) for name, values in cycles.items()})
    return trajectory, trajectory_metrics(trajectory["state_m_mps"], trajectory["thrust_n"], plant.params)


def campaign_case(scenario: Scenario) -> dict:
    """One campaign row's metrics from an in-process run (`bench campaign`, mode "in-process")."""
    trajectory, _ = simulate_in_process(scenario)
    return run_metrics(trajectory["state_m_mps"], trajectory["thrust_n"], scenario.params(),
                       trajectory["solve_time_s"], trajectory["solver_iterations"], trajectory["ctrl_feasible"])
