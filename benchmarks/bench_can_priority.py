"""What the host does to a real-time CAN run with and without SCHED_FIFO for its nodes.

A real-time attitude scenario (`attitude_fault_all` by default: 30 s, five bus faults) run RUNS
times in three variants, alternated: "bus and loop" (the defaults: `[can] realtime_priority` for
the board, the bus model and the controller, `[run] realtime_priority` for the plant, the
estimator and the controller), "bus only" (`[run] realtime_priority = 0`) and "none" (both 0),
while LOAD busy loops
(and whatever else the machine runs) compete for the CPUs. Per variant it prints, for each fault
window (0.5 s either side), how long the host held up the driver, the board or the bus model
(`bench.report.canbus.host_held_per_fault_s`), the median and the largest over the runs; the
commands the board refused as stale (delivered past the freshness window); sense -> board
latency (metrics.json `latency.sense_to_board`, median of the runs' p50 and p99); and the runs
whose criteria failed.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_can_priority.py [--runs 4] [--load 2] [--scenario NAME]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import msgspec
import numpy as np

from bench.report.canbus import host_held_per_fault_s
from bench.report.rundata import load_run
from bench.scenario import load_scenario

REPO = Path(__file__).resolve().parent.parent


def one_run(scenario_file: Path, runs_dir: Path, run_id: str) -> dict:
    result = subprocess.run([sys.executable, "-m", "bench.cli", "run", str(scenario_file), "--run-id", run_id,
                             "--runs-dir", str(runs_dir), "--no-progress", "--no-report"],
                            cwd=REPO, capture_output=True, text=True, timeout=600)
    run_dir = runs_dir / run_id
    metrics = json.loads((run_dir / "metrics.json").read_text())
    board = json.loads((run_dir / "can" / "board.json").read_text())
    latency = metrics["latency"]["sense_to_board"]
    return {"held": host_held_per_fault_s(load_run(run_dir)), "stale": board["rejected"].get("STALE", 0),
            "p50_ms": latency["p50_ms"], "p99_ms": latency["p99_ms"],
            "priority": board.get("realtime_priority", 0),
            "loop_priority": metrics["process_stats"].get("plant", {}).get("realtime_priority", 0),
            "passed": result.returncode == 0 and metrics.get("verdict", {}).get("passed") is True}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=4)
    parser.add_argument("--load", type=int, default=2, help="busy loops beside the runs")
    parser.add_argument("--scenario", default="attitude_fault_all", help="a real-time attitude scenario with a CAN bus")
    args = parser.parse_args()
    hogs = [subprocess.Popen([sys.executable, "-c", "while 1: pass"]) for _ in range(args.load)]
    results: dict[str, list[dict]] = {"bus and loop": [], "bus only": [], "none": []}
    try:
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            base = msgspec.to_builtins(load_scenario(args.scenario))
            files = {}
            for variant, bus, loop in (("bus and loop", base["can"]["realtime_priority"], base["run"]["realtime_priority"]),
                                       ("bus only", base["can"]["realtime_priority"], 0), ("none", 0, 0)):
                data = json.loads(json.dumps(base))
                data["can"]["realtime_priority"] = bus
                data["run"]["realtime_priority"] = loop
                files[variant] = tmp / f"{variant.replace(' ', '_')}.json"
                files[variant].write_text(json.dumps(data))
            for i in range(args.runs):
                for variant in results:
                    results[variant].append(one_run(files[variant], tmp, f"{variant.replace(' ', '_')}{i}"))
                    r = results[variant][-1]
                    print(f"run {i} {variant:12s} priority bus {r['priority']:2d} loop {r['loop_priority']:2d} held " +
                          " ".join(f"{k}={v:.3f}" for k, v in r["held"].items()) +
                          f" stale {r['stale']} sense->board p50 {r['p50_ms']:.2f} p99 {r['p99_ms']:.2f} ms pass {r['passed']}",
                          flush=True)
    finally:
        for hog in hogs:
            hog.kill()
    print(f"\n{args.runs} runs each of {args.scenario}, alternated, {args.load} busy loops beside them")
    windows = list(results["none"][0]["held"])
    print("| variant | " + "".join(f"{w} held s (median / max) | " for w in windows) +
          "STALE refusals (median) | sense -> board p50 / p99 ms (median) | criteria failed |")
    print("| --- " * (len(windows) + 4) + "|")
    for variant, rows in results.items():
        cells = [f"{np.median([r['held'][w] for r in rows]):.3f} / {max(r['held'][w] for r in rows):.3f}" for w in windows]
        print(f"| {variant} | " + "".join(f"{c} | " for c in cells) + f"{np.median([r['stale'] for r in rows]):.0f} | "
              f"{np.median([r['p50_ms'] for r in rows]):.2f} / {np.median([r['p99_ms'] for r in rows]):.2f} | "
              f"{sum(not r['passed'] for r in rows)} of {len(rows)} |")


if __name__ == "__main__":
    main()
