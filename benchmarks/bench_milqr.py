"""MILQR planning time and TVLQR tracking cost for the 90-degree magnetorquer slew (seed 004).

One process, one run, each figure next to a baseline measured in the same run:
- Horizon: the Gramian horizon (cond <= 3) on the 500 km / 51.6 deg orbit and its condition number.
- Planner: MILQR iterations, median time per iteration and time to convergence on the slew, against
  casadi + IPOPT (exact Hessian, single shooting, started from zero dipole) on the same discretised
  problem; both costs printed (they agree to ~1e-9 relative when both converge).
- Tracker: `TvlqrAttitudeTracker.eval` at a 10 Hz control rate over the whole plan (states near the
  plan), against a fixed-gain regulator with the same error computation (no plan look-up, no slerp)
  and against one 0.1 s truth-model RK4 step; percentiles and the share of the 100 ms control period.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_milqr.py [--dt 40] [--dt-fine 20] [--no-ipopt]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from bench.gnc import quaternion as qt
from bench.gnc.attitude_law import AttitudeControlInput as ControlInput
from bench.gnc.attitude_tracking import AttitudePlan, TvlqrAttitudeTracker, tvlqr_gains_along
from bench.gnc.milqr import milqr
from bench.gnc.tvlqr import bryson_weights
from bench.plant.attitude import rk4_attitude_step
from tests.milqr_reference import GOAL, INERTIA, LIMIT_AM2, X0, slew_cost, slew_problem, solve_with_ipopt

CONTROL_RATE_HZ = 10.0


def plan_slew(dt_s):
    horizon, model = slew_problem(dt_s)
    t0 = time.perf_counter()
    result = milqr(model, slew_cost(), X0, np.zeros((model.horizon_steps, 3)), -LIMIT_AM2, LIMIT_AM2)
    wall = time.perf_counter() - t0
    return horizon, model, result, wall


def report_plan(label, horizon, result, wall):
    its = result.info["iteration_times_s"]
    print(f"{label}: horizon {horizon.horizon_s / 60:.1f} min = {horizon.steps} steps (cond {horizon.condition_number:.2f}); "
          f"MILQR {result.info['iterations']} iterations, stop '{result.info['stop_reason']}', "
          f"{wall:.2f} s to convergence, median {1e3 * np.median(its):.0f} ms/iteration "
          f"(p90 {1e3 * np.percentile(its, 90):.0f} ms); cost {result.cost:.9f}; "
          f"final error {np.rad2deg(qt.angle_between_rad(result.states[-1, :4], GOAL)):.3f} deg, "
          f"|omega_N| {np.linalg.norm(result.states[-1, 4:]):.1e} rad/s, "
          f"saturated {np.mean(np.isclose(np.abs(result.dipoles_am2), LIMIT_AM2)):.1%} of dipole samples")


def time_tracker(model, result, dt_s, rng):
    Q, R = bryson_weights([np.tan(np.deg2rad(0.5))] * 3 + [5e-4] * 3, [LIMIT_AM2] * 3)
    t0 = time.perf_counter()
    gains = tvlqr_gains_along(model, result.states, result.dipoles_am2, Q, R, 10 * Q)
    gains_s = time.perf_counter() - t0
    plan = AttitudePlan(0.0, dt_s, result.states, result.dipoles_am2, gains)
    law = TvlqrAttitudeTracker(plan, LIMIT_AM2)
    times = np.arange(0.0, plan.end_time_s, 1.0 / CONTROL_RATE_HZ)
    inputs = []
    for t in times:
        k = min(int(t / dt_s), plan.steps - 1)
        x = result.states[k]
        q = qt.multiply(x[:4], qt.exp(rng.normal(scale=0.01, size=3)))
        inputs.append(ControlInput(t, q, x[4:] + rng.normal(scale=1e-4, size=3), rng.normal(scale=2e-5, size=3)))
    K_fixed = gains[0]

    def fixed_gain(x):   # baseline: same error state and clamp, no plan look-up or slerp
        dx = qt.error_state(x.q_wxyz, x.omega_radps, GOAL, np.zeros(3))
        return np.clip(-K_fixed @ dx, -LIMIT_AM2, LIMIT_AM2)

    def plant_step(x):
        return rk4_attitude_step(x.q_wxyz, x.omega_radps, np.cross(np.ones(3) * 0.1, x.field_body_t), INERTIA, 0.1)

    out = {}
    for name, fn in (("TVLQR tracker eval", law.eval), ("fixed-gain regulator", fixed_gain),
                     ("truth RK4 step 0.1 s", plant_step)):
        samples = np.empty(len(inputs))
        for i, x in enumerate(inputs):
            s = time.perf_counter()
            fn(x)
            samples[i] = time.perf_counter() - s
        out[name] = samples
    return out, gains_s, len(inputs)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dt", type=float, default=40.0, help="planning step for the MILQR vs IPOPT comparison, s")
    ap.add_argument("--dt-fine", type=float, default=20.0, help="planning step of the MILQR-only run and tracker, s")
    ap.add_argument("--no-ipopt", action="store_true")
    args = ap.parse_args()
    rng = np.random.default_rng(0)

    horizon, model, result, wall = plan_slew(args.dt)
    report_plan(f"dt {args.dt:.0f} s", horizon, result, wall)
    if not args.no_ipopt:
        objective, _, _, status, ipopt_wall = solve_with_ipopt(model, slew_cost(), X0, LIMIT_AM2, max_iter=3000,
                                                                max_cpu_time_s=1200.0)
        print(f"  baseline casadi+IPOPT same problem: {ipopt_wall:.2f} s ({status}), cost {objective:.9f} "
              f"(relative difference {(objective - result.cost) / result.cost:+.1e}); "
              f"MILQR is {ipopt_wall / wall:.1f}x faster to convergence")

    horizon_f, model_f, result_f, wall_f = plan_slew(args.dt_fine)
    report_plan(f"dt {args.dt_fine:.0f} s", horizon_f, result_f, wall_f)

    samples, gains_s, n = time_tracker(model_f, result_f, args.dt_fine, rng)
    print(f"TVLQR gains along the {horizon_f.steps}-step plan: {1e3 * gains_s:.1f} ms; {n} evaluations at "
          f"{CONTROL_RATE_HZ:.0f} Hz over the plan:")
    base = np.median(samples["fixed-gain regulator"])
    for name, s in samples.items():
        print(f"  {name:22s} median {1e6 * np.median(s):7.1f} us  p99 {1e6 * np.percentile(s, 99):7.1f} us  "
              f"max {1e6 * s.max():7.1f} us  ({np.median(s) / base:.1f}x fixed-gain; "
              f"{np.percentile(s, 99) * CONTROL_RATE_HZ:.2%} of the 100 ms period at p99)")


if __name__ == "__main__":
    main()
