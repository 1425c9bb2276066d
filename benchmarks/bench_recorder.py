"""The recorder's overhead on the loop: end-to-end latency and loop rate, with and without recording.

    .venv/bin/python benchmarks/bench_recorder.py                 # 4 rounds of 100 real-time steps
    .venv/bin/python benchmarks/bench_recorder.py --rounds 2 --steps 60
    .venv/bin/python benchmarks/bench_recorder.py --mode lock-step --steps 2000

Runs the default scenario (real time: 10 steps per wall second; lock-step: as fast as the loop
goes) through the launcher, once with the recorder node and once without it, alternating ABAB...
in the same invocation so both see the same machine load. End-to-end latency is sensed -> applied
per step, from the plant's own stamps (trajectory.npz), which exist with or without a recorder; the
loop rate is steps per second from the first sample to the last command. Printed: median, p90, p99
per configuration, the ratios recorded/baseline and the median rate. A recorded run that lost a
sample is an error.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import shutil
import tempfile
from pathlib import Path

import msgspec
import numpy as np
from rich.console import Console
from rich.table import Table

from bench import launcher
from bench.report.latency import END_TO_END, hop_samples_s, stamps_from_trajectory
from bench.runtime import node as node_runtime
from bench.scenario import load_scenario


def one_run(with_recorder: bool, mode: str, steps: int, runs_dir: Path, index: int) -> tuple[np.ndarray, float]:
    """End-to-end latencies in s of one run, and its loop rate in steps per second."""
    saved = node_runtime.NODES.pop("recorder") if not with_recorder else None
    try:
        scenario = load_scenario("rendezvous_lqr")
        scenario = msgspec.structs.replace(
            scenario, run=msgspec.structs.replace(scenario.run, mode=mode, steps=steps))
        run_id = f"bench-recorder-{'on' if with_recorder else 'off'}-{index}"
        with contextlib.redirect_stdout(io.StringIO()):    # the launcher's per-run summary table
            code, run_dir = launcher.run_bench(scenario, run_id, runs_dir, port=None, show_progress=False)
        if code != 0:
            raise SystemExit(f"run {run_id} failed with exit code {code}; see {run_dir}/logs")
        with np.load(run_dir / "trajectory.npz") as npz:
            _, latency_s = hop_samples_s(stamps_from_trajectory(dict(npz)), END_TO_END)
            rate_hz = steps / ((npz["stamp_plant_received_ns"][-1] - npz["stamp_sensed_ns"][0]) / 1e9)
        if with_recorder:
            counts = json.loads((run_dir / "recorder_counts.json").read_text())["topics"]
            missing = sum(c["missing"] or 0 for c in counts.values())
            if missing:
                raise SystemExit(f"run {run_id}: the recorder missed {missing} samples")
        return latency_s, rate_hz
    finally:
        if saved is not None:
            node_runtime.NODES["recorder"] = saved


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=4, help="A/B pairs (default 4)")
    parser.add_argument("--steps", type=int, default=100, help="steps per run (default 100)")
    parser.add_argument("--mode", choices=("real-time", "lock-step"), default="real-time")
    args = parser.parse_args()
    runs_dir = Path(tempfile.mkdtemp(prefix="bench-recorder-"))
    samples: dict[str, list[np.ndarray]] = {"without recorder": [], "with recorder": []}
    rates: dict[str, list[float]] = {name: [] for name in samples}
    try:
        for i in range(args.rounds):
            for name in samples:
                latency_s, rate_hz = one_run(name == "with recorder", args.mode, args.steps, runs_dir, i)
                samples[name].append(latency_s)
                rates[name].append(rate_hz)
    finally:
        shutil.rmtree(runs_dir, ignore_errors=True)

    merged_ms = {name: np.concatenate(runs) * 1e3 for name, runs in samples.items()}
    base = merged_ms["without recorder"]
    table = Table(title=f"End-to-end latency (sensed → applied), {args.mode}, {args.rounds} x {args.steps} steps each")
    for column in ("configuration", "n", "median [ms]", "p90 [ms]", "p99 [ms]", "median ratio", "p99 ratio",
                   "rate [steps/s]"):
        table.add_column(column, justify="right")
    for name, ms in merged_ms.items():
        table.add_row(name, str(ms.size), f"{np.median(ms):.3f}", f"{np.percentile(ms, 90):.3f}",
                      f"{np.percentile(ms, 99):.3f}", f"{np.median(ms) / np.median(base):.2f}",
                      f"{np.percentile(ms, 99) / np.percentile(base, 99):.2f}", f"{np.median(rates[name]):.0f}")
    Console().print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
