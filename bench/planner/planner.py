"""When to replan and what: the planning step of `bench node planner`, without Zenoh or a clock.

`replan_reason` is the one rule for "a plan is due now" (first valid estimate, the schedule, or the
estimate too far off the current plan). The planner process runs it to decide when to plan; in
lock-step the controller runs the same function on the same estimate and the same current plan to
know that a plan is coming for this step and wait for it, which keeps a lock-step run
deterministic (the in-process loop, `bench.sim`, calls `AttitudePlanner` directly).

`AttitudePlanner` plans with MILQR (`bench.planner.plan.plan_from_estimate`) from the estimate to
the scenario's inertial target, over the Gramian horizon, on the flight side's beliefs: the
believed inertia and the same orbit and field model the plant flies ([attitude.orbit],
[attitude.field], tabulated over the run and one horizon beyond it).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from bench.controller.attitude_laws import believed_inertia, dipole_limit_am2
# The replan rule is the flight side's: the controller applies the same one in lock-step.
from bench.controller.plan_tracking import replan_reason
from bench.gnc import quaternion as qt
from bench.gnc.attitude_tracking import AttitudePlan
from bench.gnc.milqr import MilqrOptions
from bench.planner.plan import PlannerConfig, plan_from_estimate
from bench.runtime.time_model import TimeModel
from bench.scenario import Scenario

def inertial_target_wxyz(scenario: Scenario) -> np.ndarray:
    target = scenario.attitude_control.target
    if target.kind != "inertial":
        raise ValueError(f"attitude_control.target.kind: the MILQR planner plans to one attitude at rest "
                         f"(\"inertial\"); got {target.kind!r}")
    return qt.normalize(np.asarray(target.q_wxyz, float))


def planner_config(scenario: Scenario) -> PlannerConfig:
    s = scenario.attitude_control.planner
    wall_s = s.max_planning_wall_s if TimeModel.of(scenario).deadlines_apply else np.inf
    return PlannerConfig(
        inertia_kgm2=believed_inertia(scenario), dipole_limit_am2=dipole_limit_am2(scenario), dt_s=s.plan_step_s,
        gramian_condition_tolerance=s.gramian_condition_tolerance, max_horizon_s=s.max_horizon_s,
        tracking_attitude_deviation_rad=np.deg2rad(s.tracking_attitude_deviation_deg),
        tracking_rate_deviation_radps=s.tracking_rate_deviation_radps, hold_after_arrival_s=s.hold_after_arrival_s,
        milqr=replace(MilqrOptions(), max_iterations=s.max_iterations, max_wall_time_s=wall_s))


@dataclass
class PlanRecord:
    plan_id: int
    seq: int
    time_s: float
    reason: str
    info: dict


class AttitudePlanner:
    def __init__(self, scenario: Scenario):
        from bench.plant.attitude_plant import build_field, build_orbit   # the plant's own models

        self.settings = scenario.attitude_control.planner
        self.config = planner_config(scenario)
        self.target_wxyz = inertial_target_wxyz(scenario)
        self.orbit = build_orbit(scenario.attitude)
        duration_s = (scenario.n_steps * scenario.step_s + self.config.max_horizon_s + self.config.hold_after_arrival_s
                      + 2 * self.config.dt_s)
        self.field = build_field(scenario.attitude, self.orbit, duration_s)
        self.plan: AttitudePlan | None = None
        self.records: list[PlanRecord] = []
        self.failures = 0

    def due(self, time_s: float, valid: bool, q_wxyz) -> str | None:
        return replan_reason(time_s, valid, q_wxyz, self.plan, self.settings)

    def horizon_steps(self, time_s: float, reason: str = "schedule") -> int | None:
        """Steps of a replan: to the current plan's arrival time while it lies ahead, however little
        of it is left; once arrived, 0 (only the hold, `bench.planner.plan.hold_plan`) for a
        scheduled replan and None (a fresh Gramian horizon) for one the tracking error asked for;
        None for the first plan.

        A fresh Gramian horizon from every replan keeps postponing the arrival (measured on
        attitude_slew_milqr with truth feedback: a scheduled replan at 900 s moved it from 1580 s to
        2300 s). Close to the arrival it also throws the manoeuvre away: a fresh plan runs a whole
        Gramian horizon (~1500-2200 s) and the run ends in its middle. Measured on the seed sweep
        (benchmarks/bench_milqr_seed_sweep.py, seed 4, a tracking-error replan 97 s before the
        arrival at 1570 s, the body 12 deg off the target and 9 deg off its plan, saturated and
        spinning up): a fresh horizon (arrival 3693 s) ended 106 deg off at 1800 s; no replan (the
        TVLQR tracker, saturated, kept going) 178 deg; a 300 s minimum horizon 18 deg (a second
        replan); keeping the arrival (5 steps, cond(W) 435) 2.2 deg. MILQR's box-constrained plan
        over the few steps left need not arrive exactly; the hold after it (TVLQR along the hold's
        field) takes it from there. Once arrived, the schedule only renews the hold; a body 10 deg
        off the hold (the tracking-error bound) re-plans the manoeuvre from scratch."""
        if self.plan is None:
            return None
        left_s = self.plan.arrival_time_s - time_s
        if left_s <= 0:
            return 0 if reason == "schedule" and self.config.hold_after_arrival_s > 0 else None
        # To the nearest plan step (plans have a uniform step): the arrival moves by at most half a
        # step per replan, either way; rounding up moved it later at every replan.
        return max(1, int(np.floor(left_s / self.config.dt_s + 0.5)))

    def plan_now(self, seq: int, time_s: float, q_wxyz, omega_radps, reason: str) -> tuple[AttitudePlan, dict]:
        plan, info = plan_from_estimate(time_s, q_wxyz, omega_radps, self.target_wxyz, self.orbit, self.field,
                                        self.config, plan_id=len(self.records), horizon_steps=self.horizon_steps(time_s, reason))
        self.plan = plan
        info = {k: v for k, v in info.items() if k not in ("cost_history", "iteration_times_s")} | {
            "reason": reason, "steps": plan.steps,
            "median_iteration_s": float(np.median(info["iteration_times_s"])) if info["iteration_times_s"] else 0.0}
        self.records.append(PlanRecord(plan.plan_id, seq, time_s, reason, info))
        return plan, info

    def on_estimate(self, seq: int, time_s: float, valid: bool, q_wxyz, omega_radps) -> tuple[AttitudePlan, dict] | None:
        """A new plan if one is due at this estimate, else None."""
        reason = self.due(time_s, valid, q_wxyz)
        if reason is None:
            return None
        return self.plan_now(seq, time_s, q_wxyz, omega_radps, reason)

    def summary(self) -> dict:
        return {"plans": [{"plan_id": r.plan_id, "seq": r.seq, "time_s": r.time_s, "reason": r.reason,
                           **{k: (float(v) if isinstance(v, (np.floating, float)) else v) for k, v in r.info.items()}}
                          for r in self.records],
                "failures": self.failures}
