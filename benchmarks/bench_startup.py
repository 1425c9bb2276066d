"""Start-up of `bench run`: nodes forked from the launcher's pre-imported zygote against each node
started by exec (BENCH_NODE_START=exec), alternated in the same run so both see the same load.

For each scenario and path, RUNS times: `bench run SCENARIO --steps N --no-report` in a scratch
runs directory, timed from just before the command starts to the plant's "peers ready" log line
(the loop's first step: every node is up and connected) and to the command's exit. Prints the
median and p90 of both, the 1-minute load average before and after, and fails (exit 1) if any run
did not finish. `--against DIR` adds a third path: the zygote path of another checkout of the
bench (its code on PYTHONPATH, run from it), to measure a change against the code before it.
`--whole` times the command as a user runs it instead: `bench run attitude_quick` with all its
steps and its report (zygote path only; with `--against`, this checkout against the other).

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_startup.py [--runs 5] [--against DIR] [--whole]
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
CASES = [("attitude_quick", 20), ("rendezvous_lqr", 5)]
WHOLE_CASES = [("attitude_quick", None)]     # --whole: every step, and the report
FIRST_STEP_MARK = "peers ready"     # the plant's log line when its loop starts


def one_run(scenario: str, steps: int | None, path: str, runs_dir: Path, run_id: str,
            repo: Path = REPO) -> tuple[float, float]:
    """(seconds to the first step, seconds to the command's end) of one `bench run` of the bench
    in `repo`, its nodes started by `path` ("zygote" or "exec"); steps None: the scenario's own,
    and the report."""
    env = {**os.environ, "BENCH_NODE_START": path, "PYTHONPATH": str(repo)}
    limits = ["--steps", str(steps), "--no-report"] if steps is not None else []
    cmd = [sys.executable, "-m", "bench.cli", "run", scenario, *limits, "--no-progress",
           "--run-id", run_id, "--runs-dir", str(runs_dir)]
    started_wall = time.time()
    started = time.monotonic()
    result = subprocess.run(cmd, cwd=repo, env=env, capture_output=True, text=True, timeout=600)
    end_s = time.monotonic() - started
    if result.returncode != 0:
        raise SystemExit(f"{scenario} ({path}) exited with {result.returncode}:\n{result.stderr[-2000:]}")
    return first_step_wall_s(runs_dir / run_id) - started_wall, end_s


def first_step_wall_s(run_dir: Path) -> float:
    """Wall-clock time (time.time) of the plant's first step: its "peers ready" log line."""
    for line in (run_dir / "logs" / "plant.log").read_text().splitlines():
        if FIRST_STEP_MARK in line:
            return datetime.strptime(line[:23], "%Y-%m-%d %H:%M:%S,%f").timestamp()
    raise SystemExit(f"{run_dir}: no '{FIRST_STEP_MARK}' in the plant's log")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5, help="runs per scenario and path (default 5)")
    parser.add_argument("--against", type=Path, help="another checkout of the bench: its zygote path as a third row")
    parser.add_argument("--whole", action="store_true", help="the whole command: every step and the report")
    args = parser.parse_args()
    if args.runs < 1:
        parser.error(f"--runs must be at least 1, got {args.runs}")
    if args.against is not None and not (args.against / "bench" / "cli.py").is_file():
        parser.error(f"--against: {args.against} is not a checkout of the bench (no bench/cli.py)")
    # (label, how nodes start, checkout)
    paths = [("zygote (fork)", "zygote", REPO)] + ([] if args.whole else [("exec", "exec", REPO)])
    cases = WHOLE_CASES if args.whole else CASES
    if args.against is not None:
        paths.append((f"zygote, {args.against}", "zygote", args.against.resolve()))
    load_before = os.getloadavg()[0]
    times: dict[tuple[str, str], list[tuple[float, float]]] = {}
    with tempfile.TemporaryDirectory(prefix="bench-startup-") as scratch:
        for i in range(args.runs):
            for scenario, steps in cases:
                order = paths if i % 2 == 0 else paths[::-1]     # no path always goes first
                for k, (label, path, repo) in enumerate(order):
                    run = one_run(scenario, steps, path, Path(scratch), f"startup-{scenario}-{path}-{i}-{k}", repo)
                    times.setdefault((scenario, label), []).append(run)
                    print(f"  {scenario:16s} {label:18s} run {i + 1}: first step {run[0]:5.2f} s, end {run[1]:5.2f} s",
                          file=sys.stderr)
    load_after = os.getloadavg()[0]
    print(f"bench run start-up, {args.runs} runs per row, {os.cpu_count()} CPUs, "
          f"load average (1 min) {load_before:.2f} before, {load_after:.2f} after")
    print(f"{'scenario':26s} {'nodes started by':18s} {'first step p50':>15s} {'p90':>7s} {'end p50':>9s} {'p90':>7s}")
    for scenario, steps in cases:
        for label, _, _ in paths:
            first, end = np.array(times[(scenario, label)]).T
            print(f"{scenario + (f' --steps {steps}' if steps else ''):26s} {label:18s} {np.median(first):13.2f} s {np.percentile(first, 90):5.2f} s "
                  f"{np.median(end):7.2f} s {np.percentile(end, 90):5.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
