"""The pure planning step behind `bench node planner` (seed 004): `plan_from_estimate` takes the
current attitude estimate and the target and returns an `AttitudePlan` (MILQR states and dipoles,
TVLQR gains along them, the time base) with an info dict; no Zenoh, no clock, no process. The
message that carries a plan is `bench.bus.plan_message`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.gnc import quaternion as qt
from bench.gnc.attitude_planning import MagnetorquerAttitudeModel, field_along_orbit_t, gramian_horizon
from bench.gnc.attitude_tracking import AttitudePlan, tvlqr_gains_along
from bench.gnc.milqr import GeodesicAttitudeCost, MilqrOptions, milqr
from bench.gnc.tvlqr import bryson_weights

@dataclass(frozen=True)
class PlannerConfig:
    """What the flight side believes and how it plans (weights of tests/milqr_reference.py's slew)."""
    inertia_kgm2: np.ndarray
    dipole_limit_am2: float = 0.2
    dt_s: float = 20.0
    gramian_condition_tolerance: float = 3.0
    max_horizon_s: float = 5400.0
    attitude_weight: float = 0.1
    rate_weight: float = 10.0
    dipole_weight: float = 1.0
    final_attitude_weight: float = 1000.0
    final_rate_weight: float = 1e7
    tracking_attitude_deviation_rad: float = np.deg2rad(1.0)   # Bryson's rule for the tracker
    tracking_rate_deviation_radps: float = 5e-4
    # After the arrival the plan holds the target at rest for this long, tracked with TVLQR gains
    # designed along the field of those steps (AttitudePlan.hold_steps).
    hold_after_arrival_s: float = 0.0
    milqr: MilqrOptions = MilqrOptions(max_wall_time_s=60.0)


def plan_from_estimate(time_s: float, q_wxyz, omega_radps, target_wxyz, orbit, geomagnetic,
                       config: PlannerConfig, plan_id: int = 0,
                       horizon_steps: int | None = None) -> tuple[AttitudePlan, dict]:
    """MILQR from the estimate at time_s to rest at the target over the Gramian horizon from time_s,
    or over `horizon_steps` steps when given (a replan that keeps the previous plan's arrival);
    `horizon_steps=0`: no manoeuvre, only the hold from time_s (a scheduled replan once arrived:
    fresh hold gains along the field from now on, `hold_plan`)."""
    x0 = np.concatenate([qt.normalize(q_wxyz), np.asarray(omega_radps, dtype=float)])
    if not np.all(np.isfinite(x0)) or not np.isfinite(time_s):
        raise ValueError(f"plan_from_estimate: non-finite estimate (time {time_s}, state {x0})")
    if horizon_steps == 0:
        return hold_plan(time_s, target_wxyz, orbit, geomagnetic, config, plan_id)
    max_steps = int(np.ceil(config.max_horizon_s / config.dt_s))
    hold_steps = _hold_steps(config)
    field = field_along_orbit_t(orbit, geomagnetic, time_s, config.dt_s, max_steps + hold_steps)
    horizon = gramian_horizon(field, config.dt_s, config.gramian_condition_tolerance)
    if horizon_steps is not None:
        if not 1 <= horizon_steps <= max_steps:
            raise ValueError(f"horizon_steps must be 1..{max_steps}, got {horizon_steps}")
        # a tolerance no Gramian meets: the given steps, with cond(W) over them for the record
        horizon = gramian_horizon(field[:horizon_steps], config.dt_s, 1.0 + 1e-12)
    model = MagnetorquerAttitudeModel(config.inertia_kgm2, field[:horizon.steps], config.dt_s)
    cost = GeodesicAttitudeCost(target_wxyz, np.zeros(3), config.attitude_weight, config.rate_weight * np.eye(3),
                                config.dipole_weight * np.eye(3), config.final_attitude_weight,
                                config.final_rate_weight * np.eye(3))
    limit = config.dipole_limit_am2
    result = milqr(model, cost, x0, np.zeros((horizon.steps, 3)), -limit, limit, config.milqr)
    # The hold after the arrival: the target at rest with zero dipole (an equilibrium of the planning
    # model), tracked with gains designed along the field of those steps. Without it the tracker held
    # the final state with the last step's gain, designed for the field at the arrival only: on
    # attitude_slew_milqr (gyro without bias) 1.04 deg at the arrival drifted to 3.8 deg 220 s later.
    q_hold = qt.normalize(np.asarray(target_wxyz, dtype=float))
    q_hold = q_hold if q_hold @ result.states[-1, :4] >= 0 else -q_hold     # same hemisphere: slerp the short way
    states = np.concatenate([result.states, np.tile(np.concatenate([q_hold, np.zeros(3)]), (hold_steps, 1))])
    dipoles = np.concatenate([result.dipoles_am2, np.zeros((hold_steps, 3))])
    plan = AttitudePlan(time_s, config.dt_s, states, dipoles, _tracking_gains(config, field, states, dipoles),
                        plan_id, hold_steps)
    info = dict(result.info, cost=result.cost, horizon_s=horizon.horizon_s,
                horizon_reached=horizon.reached if horizon_steps is None else None, horizon_given=horizon_steps is not None,
                gramian_condition_number=horizon.condition_number)
    return plan, info


def hold_plan(time_s: float, target_wxyz, orbit, geomagnetic, config: PlannerConfig,
              plan_id: int = 0) -> tuple[AttitudePlan, dict]:
    """The target at rest from time_s for hold_after_arrival_s, zero feed-forward, TVLQR gains along
    the field from time_s: what a scheduled replan flies once the manoeuvre has arrived.

    Re-planning the manoeuvre there (MILQR over a fresh Gramian horizon from a state a degree or two
    off the target) starts another slew: on attitude_slew_milqr the schedule's replan at 1830 s
    planned one arriving at 3990 s, and at 2170 s 4 of seeds 0-10 (seed 4 has no such replan) were
    2.05-2.63 deg off, against 0.17-1.63 deg with the hold renewed. A one-step MILQR manoeuvre into
    the hold instead (a saturated step with the final weight's pull) moved the body: the largest
    error in the last 300 s was 1.56-1.66 deg on seeds 6, 17 and 18, against 0.61-0.89 deg here."""
    hold_steps = _hold_steps(config)
    if hold_steps < 1:
        raise ValueError("hold_plan needs hold_after_arrival_s of at least one plan step")
    field = field_along_orbit_t(orbit, geomagnetic, time_s, config.dt_s, hold_steps)
    states = np.tile(np.concatenate([qt.normalize(np.asarray(target_wxyz, dtype=float)), np.zeros(3)]),
                     (hold_steps + 1, 1))
    dipoles = np.zeros((hold_steps, 3))
    plan = AttitudePlan(time_s, config.dt_s, states, dipoles, _tracking_gains(config, field, states, dipoles),
                        plan_id, hold_steps)
    # The keys of a MILQR plan's info (the planner node logs them, the message carries some).
    info = {"stop_reason": "hold", "converged": True, "iterations": 0, "cost": 0.0, "wall_time_s": 0.0,
            "cost_history": [], "iteration_times_s": [], "regularisation": 0.0, "line_search_failures": 0,
            "horizon_s": 0.0, "horizon_reached": None, "horizon_given": True,
            # cond(W) over the hold's field, for the record (no horizon was searched)
            "gramian_condition_number": gramian_horizon(field, config.dt_s, 1.0 + 1e-12).condition_number}
    return plan, info


def _hold_steps(config: PlannerConfig) -> int:
    return int(np.ceil(config.hold_after_arrival_s / config.dt_s - 1e-9))


def _tracking_gains(config: PlannerConfig, field_inertial_t: np.ndarray, states: np.ndarray,
                    dipoles_am2: np.ndarray) -> np.ndarray:
    """TVLQR gains along the plan, Bryson weights from the tracker's deviations (seed 000)."""
    Q, R = bryson_weights([np.tan(config.tracking_attitude_deviation_rad / 2)] * 3
                          + [config.tracking_rate_deviation_radps] * 3, [config.dipole_limit_am2] * 3)
    steps = dipoles_am2.shape[0]
    model = MagnetorquerAttitudeModel(config.inertia_kgm2, field_inertial_t[:steps], config.dt_s)
    return tvlqr_gains_along(model, states, dipoles_am2, Q, R, 10 * Q)
