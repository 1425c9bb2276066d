"""The planner process (`bench node planner`, issue 12): MILQR attitude plans from the estimate to
the scenario's target, outside the control deadline.

reads:  estimate/attitude (AttitudeEstimate)
writes: plan/attitude     (AttitudePlanMessage: states, dipoles, TVLQR gains and time base of one
                           plan; header.seq and sim_time_s are those of the estimate it starts from)
Summary: planner.json (per plan: why it was made, horizon, MILQR iterations, stop reason, cost,
planning wall time).

When to plan is `bench.planner.planner.replan_reason`: the first valid estimate, then every
replan_period_s, or sooner (not before min_replan_interval_s) when the estimate is more than
replan_error_deg off the plan ([attitude_control.planner]). Lock-step: every estimate is looked at
in order, and the controller waits for a plan it knows is due, so planning time does not change
the run. Real-time: the estimates queued while MILQR ran are stale; only the newest is looked at.
[controller.deadline.stress] with process = "planner" slows every listed plan (cycle i = plan i)
by extra_cycle_time_s before it is published: planning time made longer on purpose.
Planning takes seconds; the controller keeps tracking the previous plan (or its fallback) meanwhile.
"""
from __future__ import annotations

import json
import time

from bench.bus import keys
from bench.bus.schemas import AttitudeEstimate
from bench.bus.plan_message import to_message
from bench.controller.deadline import StressInjector
from bench.controller.newest import NewestEstimate
from bench.planner.planner import AttitudePlanner
from bench.runtime.node import NodeContext


def run(ctx: NodeContext) -> int:
    planner = AttitudePlanner(ctx.scenario)
    estimates = ctx.subscribe_queue(keys.ESTIMATE_ATTITUDE, AttitudeEstimate)
    newest = NewestEstimate(ctx.time_model)
    ctx.declare_ready([keys.PLAN_ATTITUDE])
    stress = StressInjector(ctx.scenario.controller.deadline.stress, "planner")
    for estimate in ctx.until_stopped(estimates):
        estimate = newest.take(estimates, estimate)
        hdr = estimate.header.stamped("planner_received", time.monotonic_ns())
        reason = planner.due(hdr.sim_time_s, estimate.valid, estimate.q_wxyz)
        if reason is None:
            continue
        try:
            plan, info = planner.plan_now(hdr.seq, hdr.sim_time_s, estimate.q_wxyz, estimate.omega_radps, reason)
        except (ValueError, FloatingPointError, ArithmeticError) as exc:
            # Never fatal: the controller keeps its current plan (lock-step: it waits, then goes on).
            planner.failures += 1
            ctx.log.error("planning from step %d failed: %s", hdr.seq, exc)
            continue
        stress.apply(plan.plan_id)
        ctx.publish(keys.PLAN_ATTITUDE, to_message(plan, hdr.stamped("planned", time.monotonic_ns()),
                                                   planner.target_wxyz, info))
        ctx.log.info("plan %d (%s) from t = %.1f s: %d steps of %.0f s (horizon %.0f s, cond %.2f), %s after %d "
                     "iterations in %.2f s", plan.plan_id, reason, plan.start_time_s, plan.steps, plan.dt_s,
                     info["horizon_s"], info["gramian_condition_number"], info["stop_reason"], info["iterations"],
                     info["wall_time_s"])
    summary = planner.summary() | {"stale_estimates_skipped": newest.skipped,
                                   "stress_injected_plans": len(stress.injected_cycles)}
    (ctx.run_dir / "planner.json").write_text(json.dumps(summary, indent=2))
    return 0
