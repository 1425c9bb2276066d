"""TVLQR plan tracking inside the controller: per-cycle cost through the attitude controller's cycle
and deadline path, against the 100 ms attitude control period (issue 12).

The controller process runs `AttitudeCycle.run` once per estimate: input checks, then
`DeadlineMonitor.run_cycle` times the law's `eval` on the monotonic clock against the deadline
budget. Here that same object runs the "tvlqr_plan" law (`PlanTrackingLaw` holding a MILQR plan
made by the planner's own code from the scenario's start) at 10 Hz over the plan, on inputs near
the plan (attitude 0.5 deg off, rate noise 1e-4 rad/s). Baselines in the same run, same inputs,
same cycle object: the PD and sliding-mode laws of the same scenario. Figures: the monitor's cycle
time (what the deadline sees) and the wall time of the whole `AttitudeCycle.run` call, percentiles,
as a share of the 100 ms period and of the deadline budget, and deadline misses counted.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_tvlqr_cycle.py [--cycles 6000] [--seed 1]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from bench.controller.attitude_cycle import AttitudeCycle
from bench.gnc import quaternion as qt
from bench.planner.planner import AttitudePlanner
from bench.scenario import load_scenario, parse_scenario, scenario_to_toml_dict

CONTROL_RATE_HZ = 10.0


def scenario_at(rate_hz: float, law: str):
    data = scenario_to_toml_dict(load_scenario("attitude_slew_milqr"))
    data["attitude"]["sensors"]["gyro_rate_hz"] = rate_hz
    data["attitude_control"]["law"] = law
    return parse_scenario(data, f"attitude_slew_milqr at {rate_hz} Hz, law {law}")


def inputs_along(plan, cycles: int, rng: np.random.Generator, field_model):
    """(time, q, omega, field_body) at 10 Hz from the plan's start: the plan's state, perturbed."""
    from bench.gnc.attitude_tracking import TvlqrAttitudeTracker

    reference = TvlqrAttitudeTracker(plan, 1.0)
    out = []
    for i in range(cycles):
        t = plan.start_time_s + i / CONTROL_RATE_HZ
        q_ref, omega_ref, *_ = reference.reference(t)
        q = qt.multiply(q_ref, qt.exp(np.deg2rad(0.5) / np.sqrt(3) * rng.standard_normal(3)))
        field_body = qt.rotation_matrix(q).T @ field_model(t)
        out.append((t, q, omega_ref + 1e-4 * rng.standard_normal(3), field_body))
    return out


def time_cycles(cycle: AttitudeCycle, inputs) -> tuple[np.ndarray, np.ndarray]:
    """(monitor cycle time, whole-call wall time) per cycle, seconds."""
    whole = np.empty(len(inputs))
    for i, (t, q, omega, field) in enumerate(inputs):
        start = time.perf_counter()
        cycle.run(t, True, q, omega, field)
        whole[i] = time.perf_counter() - start
    return np.asarray(cycle.monitor.cycle_times_s), whole


def describe(label: str, monitored: np.ndarray, whole: np.ndarray, budget_s: float, misses: int) -> str:
    p = {q: 1e3 * np.percentile(monitored, q) for q in (50, 90, 99)}
    w = {q: 1e3 * np.percentile(whole, q) for q in (50, 99)}
    period_ms = 1e3 / CONTROL_RATE_HZ
    return (f"| {label} | {p[50]:.3f} / {p[90]:.3f} / {p[99]:.3f} / {1e3 * monitored.max():.1f} | "
            f"{w[50]:.3f} / {w[99]:.3f} | {p[99] / period_ms:.2%} | {p[99] / (1e3 * budget_s):.1%} | {misses} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=6000, help="10 Hz cycles (default 6000 = 600 s of the plan)")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()

    tracked = scenario_at(CONTROL_RATE_HZ, "tvlqr_plan")
    planner = AttitudePlanner(tracked)
    q0 = np.asarray(tracked.attitude.initial_q_wxyz, float)
    t0 = time.perf_counter()
    plan, info = planner.plan_now(0, 0.0, qt.normalize(q0), np.zeros(3), "first_plan")
    planning_s = time.perf_counter() - t0
    cycles = min(args.cycles, int(plan.steps * plan.dt_s * CONTROL_RATE_HZ))
    field_model = lambda t: planner.field.field_t(planner.orbit.position_m(t), t)   # noqa: E731
    inputs = inputs_along(plan, cycles, np.random.default_rng(args.seed), field_model)
    print(f"plan: {plan.steps} steps of {plan.dt_s:.0f} s, {info['iterations']} MILQR iterations, "
          f"{planning_s:.1f} s to plan (outside the cycle); {cycles} cycles at {CONTROL_RATE_HZ:.0f} Hz")
    print("| law (AttitudeCycle.run, deadline monitor) | monitor cycle time p50 / p90 / p99 / max [ms] | "
          "whole call p50 / p99 [ms] | p99 / 100 ms period | p99 / deadline budget | misses |")
    print("| --- | --- | --- | --- | --- | --- |")
    for law in ("tvlqr_plan", "pd", "sliding_mode"):
        cycle = AttitudeCycle(tracked if law == "tvlqr_plan" else scenario_at(CONTROL_RATE_HZ, law))
        if law == "tvlqr_plan":
            cycle.law.set_plan(plan)
        monitored, whole = time_cycles(cycle, inputs)
        print(describe(law, monitored, whole, cycle.monitor.budget_s, cycle.monitor.counter.misses), flush=True)
    print(f"deadline budget {cycle.monitor.budget_s * 1e3:.0f} ms ([controller.deadline] budget_s), "
          f"control period {1e3 / CONTROL_RATE_HZ:.0f} ms")


if __name__ == "__main__":
    main()
