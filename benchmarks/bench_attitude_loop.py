"""Attitude loop: how fast it runs in lock-step, and how late its torque is in real time.

1. Lock-step loop rate: `bench run attitude_detumble --steps N` (six processes, the CAN bus on the
   portable Zenoh transport) against the in-process loop of the same scenario in the same run; the
   figure that travels between machines is the ratio.
2. Sense-to-torque latency through CAN in real-time mode (`--rt-scenario`, default
   `attitude_detumble_rt`; `attitude_pointing_rt` is the pointing hold): from the plant's
   `sensed` stamp of step k to the board's `applied` stamp (coil drivers set) of the first command
   frame that carried step k's dipole (DipoleCommand.alive_counter joined with MtqApplied in the
   recording), percentiles, and the share of the cycle it uses; the per-hop split.

    PYTHONPATH=$PWD python benchmarks/bench_attitude_loop.py [--steps 600] [--rt-steps 300]
        [--rt-scenario attitude_detumble_rt] [--no-lock-step]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))   # bench_loop, beside this file
from bench_loop import attitude_multiprocess_rate_hz, bench_run, in_process_rate_hz  # noqa: E402

from bench.sim import simulate_attitude_in_process  # noqa: E402
from bench.report.rundata import load_run  # noqa: E402
from bench.scenario import load_scenario  # noqa: E402


def lockstep_rate(runs: Path, steps: int) -> dict:
    # The two rates as benchmarks/bench_loop.py defines them (one definition of each figure).
    multi = attitude_multiprocess_rate_hz("attitude_detumble", steps, runs, "lockstep")
    single = in_process_rate_hz("attitude_detumble", simulate_attitude_in_process, steps)
    step_s = load_scenario("attitude_detumble").step_s
    return {"steps": steps, "multi_process_steps_per_s": multi, "in_process_steps_per_s": single,
            "ratio": multi / single, "real_time_margin_x": multi * step_s}


def sense_to_torque(run_dir: Path) -> dict:
    run = load_run(run_dir)
    applied_by_counter: dict[int, list[tuple[int, int]]] = {}
    for message in run.on("actuator/mtq"):
        stamps = message.body["header"]["stamps_ns"]
        if "applied" in stamps and "board_received" in stamps:
            applied_by_counter.setdefault(message.body["alive_counter"], []).append(
                (stamps["board_received"], stamps["applied"]))
    hops = {"sense -> commanded": [], "commanded -> can_sent": [], "can_sent -> board applied": [],
            "sense -> board applied (torque)": []}
    for message in run.on("command/dipole"):
        stamps, counter = message.body["header"]["stamps_ns"], message.body["alive_counter"]
        if counter < 0 or "can_sent" not in stamps:
            continue
        later = [a for r, a in applied_by_counter.get(counter, []) if r >= stamps["can_sent"]]
        if not later:
            continue
        applied = min(later)
        hops["sense -> commanded"].append(stamps["commanded"] - stamps["sensed"])
        hops["commanded -> can_sent"].append(stamps["can_sent"] - stamps["commanded"])
        hops["can_sent -> board applied"].append(applied - stamps["can_sent"])
        hops["sense -> board applied (torque)"].append(applied - stamps["sensed"])
    cycle_ms = run.scenario.step_s * 1e3 / run.scenario.run.time_factor
    out = {}
    for hop, values in hops.items():
        ms = np.array(values) / 1e6
        out[hop] = {"n": len(ms), **{f"p{p}_ms": float(np.percentile(ms, p)) for p in (50, 90, 99)},
                    "max_ms": float(ms.max()), "p50_share_of_cycle": float(np.percentile(ms, 50) / cycle_ms),
                    "p99_share_of_cycle": float(np.percentile(ms, 99) / cycle_ms)}
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=600, help="lock-step steps (default 600)")
    parser.add_argument("--rt-steps", type=int, default=300, help="real-time steps (default 300)")
    parser.add_argument("--rt-scenario", default="attitude_detumble_rt",
                        help="the real-time scenario (default attitude_detumble_rt)")
    parser.add_argument("--no-lock-step", action="store_true", help="only the real-time latency")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        runs = Path(tmp)
        if not args.no_lock_step:
            rate = lockstep_rate(runs, args.steps)
            print(f"lock-step, {rate['steps']} steps: {rate['multi_process_steps_per_s']:.1f} steps/s as processes "
                  f"over CAN, {rate['in_process_steps_per_s']:.1f} steps/s in process (ratio {rate['ratio']:.2f}); "
                  f"{rate['real_time_margin_x']:.1f}x faster than real time")
        scenario = load_scenario(args.rt_scenario)
        cycle_ms = scenario.step_s * 1e3 / scenario.run.time_factor
        latency = sense_to_torque(bench_run(args.rt_scenario, args.rt_steps, runs, "realtime"))
        print(f"real time, {args.rt_scenario} ({cycle_ms:.0f} ms cycle, {scenario.can.driver.transmission} "
              f"transmission), sense-to-torque through CAN:")
        print(f"  {'hop':34s} {'n':>5s} {'p50 ms':>8s} {'p90 ms':>8s} {'p99 ms':>8s} {'max ms':>8s} {'p50 share':>10s} {'p99 share':>10s}")
        for hop, s in latency.items():
            print(f"  {hop:34s} {s['n']:5d} {s['p50_ms']:8.2f} {s['p90_ms']:8.2f} {s['p99_ms']:8.2f} {s['max_ms']:8.2f} "
                  f"{s['p50_share_of_cycle']:10.1%} {s['p99_share_of_cycle']:10.1%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
