"""Lock-step loop rate and end-to-end latency of the multi-process bench.

Baseline measured in the same run: the in-process simulation of the same scenario (same plant,
estimator and control law, no Zenoh, no processes). The ratio is what the wiring costs.

    .venv/bin/python benchmarks/bench_loop.py [--repeats 3] [--steps 288]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.scenario import load_scenario
from bench.sim import simulate_in_process


def in_process_rate_hz(steps: int) -> float:
    import msgspec

    scenario = load_scenario("rendezvous_lqr")
    scenario = msgspec.structs.replace(scenario, run=msgspec.structs.replace(scenario.run, steps=steps))
    started = time.perf_counter()
    simulate_in_process(scenario)
    return steps / (time.perf_counter() - started)


def multiprocess_run(steps: int, runs_dir: Path, run_id: str) -> tuple[float, np.ndarray]:
    """(steps per second of the stepping loop, end-to-end latencies in ms)."""
    cmd = [sys.executable, "-m", "bench.cli", "run", "--steps", str(steps), "--run-id", run_id,
           "--runs-dir", str(runs_dir), "--no-progress"]
    subprocess.run(cmd, check=True, capture_output=True)
    with np.load(runs_dir / run_id / "trajectory.npz") as data:
        sensed = data["stamp_sensed_ns"]
        received = data["stamp_plant_received_ns"]
    loop_s = (received[-1] - sensed[0]) / 1e9   # first sample to last command: the loop itself
    return steps / loop_s, (received - sensed) / 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--steps", type=int, default=288)
    args = parser.parse_args()
    baseline = [in_process_rate_hz(args.steps) for _ in range(args.repeats)]
    rates, latencies = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.repeats):
            rate, latency_ms = multiprocess_run(args.steps, Path(tmp), f"bench-loop-{i}")
            rates.append(rate)
            latencies.append(latency_ms)
    latency_ms = np.concatenate(latencies)
    result = {
        "in_process_steps_per_s_median": float(np.median(baseline)),
        "lockstep_cycles_per_s_median": float(np.median(rates)),
        "slowdown_vs_in_process": float(np.median(baseline) / np.median(rates)),
        "end_to_end_latency_ms": {p: float(np.percentile(latency_ms, q)) for p, q in
                                  (("p50", 50), ("p90", 90), ("p99", 99))} | {"max": float(latency_ms.max())},
        "samples": int(latency_ms.size),
    }
    print(f"in-process simulation : {result['in_process_steps_per_s_median']:9.0f} steps/s (baseline)")
    print(f"multi-process lockstep: {result['lockstep_cycles_per_s_median']:9.0f} cycles/s "
          f"({result['slowdown_vs_in_process']:.1f}x slower than in-process)")
    lat = result["end_to_end_latency_ms"]
    print(f"sense-to-actuation latency over {result['samples']} cycles: p50 {lat['p50']:.2f} ms, "
          f"p90 {lat['p90']:.2f} ms, p99 {lat['p99']:.2f} ms, max {lat['max']:.2f} ms")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
