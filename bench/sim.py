"""The whole loop in one process: the reference the multi-process bench must reproduce.

Same plant, estimator and controller-cycle objects as the processes use, called in the same order,
with the same seeded noise; only the wiring differs. For the attitude loop the CAN bus is replaced
by what it does to a fault-free command (DBC scaling, the board's quantisation and saturation);
with faults in [can] (bus or hardware: a board losing power, an open, stuck, reversed or weak
coil) the bus is the lock-step one itself, driver, bus model, injector and board with its coils on
simulated time, as the controller and canbus processes run it (bench/bus/can/lockstep_loop.py).
"""
from __future__ import annotations

import numpy as np

from bench.controller.attitude_cycle import AttitudeCycle
from bench.config.controller import PLANNED_LAWS
from bench.controller.cycle import ControlCycle
from bench.controller.fdir import event_arrays as fdir_event_arrays
from bench.estimator.attitude_frontend import AttitudeEstimator
from bench.estimator.frontend import StateEstimate, StateEstimator
from bench.plant.attitude_plant import AttitudePlant
from bench.plant.model import TranslationPlant
from bench.plant.mtq_acceptance import DipoleAcceptance, board_dipole_without_bus
from bench.report.run_metrics import trajectory_metrics
from bench.scenario import Scenario
from bench.studies.campaign_metrics import run_metrics


def simulate_in_process(scenario: Scenario) -> tuple[dict[str, np.ndarray], dict]:
    """Run the scenario without processes; return (trajectory arrays, metrics)."""
    plant = TranslationPlant.from_scenario(scenario)
    estimator = StateEstimator(scenario)
    control = ControlCycle(scenario)
    thrust_n = np.zeros(3)
    estimates, covariances, navigation_truth = [], [], []
    cycles = {"solve_time_s": [], "solver_iterations": [], "ctrl_feasible": []}   # per controller cycle
    for k in range(scenario.n_steps):
        position_m = plant.measure_position_m()
        # Drawn every step as the plant process does, so both keep the same noise sequence.
        range_bearing = plant.measure_range_bearing()
        measured = dict(range_bearing=range_bearing) if estimator.sensor == "range_bearing" else dict(position_m=position_m)
        truth_m_mps = plant.navigation_state_m_mps
        estimate = estimator.step(k, plant.sim_time_s, truth_m_mps=truth_m_mps,
                                  thrust_commanded_n=thrust_n, **measured)
        if estimate is None:    # no fix yet: the controller coasts, as the processes do
            estimate = StateEstimate(np.full(6, np.nan), None, None)
            outcome = control.run(None)
        else:
            outcome = control.run(estimate.state_m_mps, estimate.mean_motion_radps, step=k)
        thrust_n = outcome.thrust_n
        cycles["solve_time_s"].append(float(outcome.info.get("solve_time", np.nan)))
        cycles["solver_iterations"].append(int(outcome.info.get("iterations", 0)))
        cycles["ctrl_feasible"].append(bool(outcome.info.get("ctrl_feas", True)))
        estimates.append(estimate.state_m_mps)
        # The estimate's consistency (NEES) compares it with the truth in the same coordinates.
        covariances.append(np.full((6, 6), np.nan) if estimate.covariance is None else estimate.covariance)
        navigation_truth.append(truth_m_mps)
        plant.apply(thrust_n)
    trajectory = plant.trajectory()
    trajectory["estimate_m_mps"] = np.array(estimates)
    trajectory["estimate_covariance"] = np.array(covariances)
    trajectory["navigation_truth_m_mps"] = np.array(navigation_truth)
    trajectory.update({name: np.array(values) for name, values in cycles.items()})
    return trajectory, trajectory_metrics(trajectory["state_m_mps"], trajectory["thrust_n"], plant.params)


# ---- the attitude loop (issue 11) ---------------------------------------------------------------
def estimate_for(estimator: AttitudeEstimator, plant: AttitudePlant, k: int):
    """What the estimator makes of step k's sensors (or truth)."""
    sample = plant.sense()
    if estimator.needs_truth:
        truth = plant.sim.truth()
        return estimator.truth_step(truth.q_wxyz, truth.omega_body_radps, truth.gyro_bias_radps, plant.sim.field_body_t())
    # The samples the estimator process gets for tick k (sense/gyro, sense/mag, sense/star).
    mag = sample.magnetometer_t
    return estimator.step(k, plant.time_s, sample.gyro_radps, mag, None if mag is None else sample.field_inertial_t,
                          sample.star_tracker_wxyz)


def _through_the_message(plan):
    """The plan as the controller process gets it (encoded, decoded, rebuilt): bit for bit the same."""
    from bench.bus.schemas import decode, encode, header
    from bench.bus.plan_message import AttitudePlanMessage, from_message, to_message

    info = {"stop_reason": "", "iterations": 0, "cost": 0.0, "wall_time_s": 0.0}
    message = to_message(plan, header("in-process", 0, plan.start_time_s), [1.0, 0.0, 0.0, 0.0], info)
    return from_message(decode(encode(message), AttitudePlanMessage))


def simulate_attitude_in_process(scenario: Scenario, coil_fault=None, with_bus: bool | None = None) -> dict[str, np.ndarray]:
    """Run an attitude scenario without processes; the arrays the plant process writes, and the
    controller's cycle time per step (NaN when no law ran) and the planner's wall time per plan,
    and the FDIR actuator monitor's detections (fdir_event_time_s, _axis, _class; simulated time).
    coil_fault(time_s, applied_am2) -> applied_am2: what a bus fault does to the coils (a study's
    fault model, bench.studies.attitude_comparison; the scenario's own faults are then not run);
    None: the scenario's [can] faults through the lock-step bus, or a fault-free bus without them.
    with_bus: the lock-step bus even without faults (a clean run's false alarms); None: with faults.
    With the bus also: `can_driver_events` (the driver's events as (mission s, kind)), the part of
    each step the coils were off (`att_coils_off_fraction`) and the board's `can_board_power_log`."""
    n_steps = scenario.n_steps
    plant = AttitudePlant(scenario.attitude, n_steps, scenario.run.seed)
    estimator = AttitudeEstimator(scenario)
    cycle = AttitudeCycle(scenario)
    acceptance = DipoleAcceptance(scenario.can)
    planner = None
    if scenario.attitude_control.law in PLANNED_LAWS:   # issue 12: the planner process, in line
        from bench.planner.planner import AttitudePlanner

        planner = AttitudePlanner(scenario)
    commanded, estimated_q, valid, cycle_time_s, planning_wall_s, plan_records = [], [], [], [], [], []
    # The board model goes through the DBC encoder (~0.3 ms); a saturating or zero command repeats.
    board_dipoles: dict[bytes, np.ndarray] = {}
    bus = None
    if coil_fault is None and scenario.can is not None and (scenario.can.faults if with_bus is None else with_bus):
        from bench.bus.can.lockstep_loop import LockStepLoopBus

        bus = LockStepLoopBus(scenario.can, scenario.step_s, scenario.run.seed)
    coils_off = []
    for k in range(n_steps):
        estimate = estimate_for(estimator, plant, k)
        if planner is not None:
            planned = planner.on_estimate(k, plant.time_s, estimate.valid, estimate.q_wxyz, estimate.omega_radps)
            if planned is not None:
                cycle.law.set_plan(_through_the_message(planned[0]))
                planning_wall_s.append(planned[1]["wall_time_s"])
                plan_records.append((plant.time_s, planned[1]["reason"], planned[0].arrival_time_s))
        outcome = cycle.run(plant.time_s, estimate.valid, estimate.q_wxyz, estimate.omega_radps, estimate.field_body_t,
                            gyro_bias_radps=estimate.gyro_bias_radps)
        # The driver's word on the board as of the step just flown (the processes' order too).
        board_ok = (bus.board_ok() if bus is not None
                    else coil_fault.board_ok() if hasattr(coil_fault, "board_ok") else True)
        cycle.monitor_actuators(board_ok)
        if bus is not None:     # the canbus process's report of the step, as the plant accepts it
            coils = bus.step(k, outcome.dipole_am2)
            dipole, _ = acceptance.accept(np.array(coils.dipole_am2.tolist()), None)
            coils_off.append(coils.off_fraction)
        else:
            key = np.asarray(outcome.dipole_am2, float).tobytes()
            if key not in board_dipoles:
                board_dipoles[key] = board_dipole_without_bus(outcome.dipole_am2, scenario.can)
            dipole, _ = acceptance.accept(board_dipoles[key].copy(), None)
        if coil_fault is not None:
            dipole = coil_fault(plant.time_s, dipole)
        cycle_time_s.append(np.nan if outcome.monitored is None else outcome.monitored.cycle_time_s)
        commanded.append(outcome.dipole_am2)
        estimated_q.append(estimate.q_wxyz)
        valid.append(estimate.valid)
        plant.apply(dipole)
    with_bus = {} if bus is None else {
        "can_driver_events": [(t, e.kind) for t, e in bus.events],
        "att_coils_off_fraction": np.array(coils_off, float),
        "can_board_power_log": [dict(e) for e in bus.bus.board.power_log],
    }
    return plant.trajectory() | with_bus | {
        "att_dipole_commanded_am2": np.array(commanded).reshape(-1, 3),
        "att_estimate_q_wxyz": np.array(estimated_q).reshape(-1, 4),
        "att_estimate_valid": np.array(valid, dtype=bool),
        "att_control_cycle_time_s": np.array(cycle_time_s),
        "planner_wall_time_s": np.array(planning_wall_s),
        # per plan: when it was made, why (bench.controller.plan_tracking.replan_reason), its arrival
        "planner_plan_time_s": np.array([r[0] for r in plan_records], dtype=float),
        "planner_plan_reason": np.array([r[1] for r in plan_records], dtype=str),
        "planner_arrival_time_s": np.array([r[2] for r in plan_records], dtype=float),
    } | fdir_event_arrays(cycle.fdir_events())


def campaign_case(scenario: Scenario) -> dict:
    """One campaign row's metrics from an in-process run (`bench campaign`, mode "in-process")."""
    trajectory, _ = simulate_in_process(scenario)
    return run_metrics(trajectory["state_m_mps"], trajectory["thrust_n"], scenario.params(),
                       trajectory["solve_time_s"], trajectory["solver_iterations"], trajectory["ctrl_feasible"],
                       estimate_m_mps=trajectory["estimate_m_mps"], estimate_covariance=trajectory["estimate_covariance"],
                       navigation_truth_m_mps=trajectory["navigation_truth_m_mps"])
