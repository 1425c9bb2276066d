"""Time to build a run's report (`bench report RUN_DIR`: metrics, report.html and .md, the plots,
the Parquet tables), alternated with another checkout's in the same run so both see the same load.

One short run per scenario is made first (`bench run SCENARIO --steps N --no-report`); then, RUNS
times, each checkout builds the report of that same run directory in a fresh process (copies of
it, so neither reads the other's output). Prints the median and p90 of the wall time and of the
CPU time (the process and its children) per checkout, and the ratio of the medians. Without
`--against` it times this checkout alone.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_report.py [--runs 5] [--against DIR]
"""
from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
CASES = [("attitude_slew", 25), ("rendezvous_lqr", 40)]


def children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def build_report(repo: Path, run_dir: Path) -> tuple[float, float]:
    """(wall s, CPU s) of `bench report run_dir` with the code of `repo`."""
    env = {**os.environ, "PYTHONPATH": str(repo)}
    cpu0, wall0 = children_cpu_s(), time.monotonic()
    result = subprocess.run([sys.executable, "-m", "bench.cli", "report", str(run_dir)], cwd=repo, env=env,
                            capture_output=True, text=True, timeout=600)
    wall, cpu = time.monotonic() - wall0, children_cpu_s() - cpu0
    if result.returncode != 0:
        raise SystemExit(f"bench report {run_dir} ({repo}) exited with {result.returncode}:\n{result.stderr[-2000:]}")
    return wall, cpu


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5, help="reports per scenario and checkout (default 5)")
    parser.add_argument("--against", type=Path, help="another checkout of the bench, timed alternately with this one")
    args = parser.parse_args()
    if args.runs < 1:
        parser.error(f"--runs must be at least 1, got {args.runs}")
    checkouts = {"this checkout": REPO}
    if args.against is not None:
        if not (args.against / "bench" / "cli.py").is_file():
            parser.error(f"--against {args.against}: not a checkout of the bench (no bench/cli.py)")
        checkouts[f"against {args.against}"] = args.against.resolve()
    print(f"1-min load average before: {os.getloadavg()[0]:.2f}")
    with tempfile.TemporaryDirectory(prefix="bench-report-") as scratch:
        scratch = Path(scratch)
        for scenario, steps in CASES:
            made = subprocess.run([sys.executable, "-m", "bench.cli", "run", scenario, "--steps", str(steps), "--no-report",
                                   "--no-progress", "--run-id", scenario, "--runs-dir", str(scratch)],
                                  cwd=REPO, capture_output=True, text=True, timeout=600)
            if made.returncode != 0:
                raise SystemExit(f"bench run {scenario} exited with {made.returncode}:\n{made.stderr[-2000:]}")
            times: dict[str, list[tuple[float, float]]] = {name: [] for name in checkouts}
            for i in range(args.runs):
                for k, (name, repo) in enumerate(checkouts.items()):
                    copy = scratch / f"{scenario}-{i}-{k}"
                    shutil.copytree(scratch / scenario, copy)
                    times[name].append(build_report(repo, copy))
                    shutil.rmtree(copy)
            print(f"\n{scenario} --steps {steps}: `bench report`, {args.runs} times per checkout")
            print(f"{'checkout':48s} {'wall p50':>9s} {'p90':>7s} {'CPU p50':>9s} {'p90':>7s}")
            medians = {}
            for name, rows in times.items():
                wall, cpu = np.array(rows).T
                medians[name] = np.median(wall)
                print(f"{name:48s} {np.median(wall):8.2f}s {np.percentile(wall, 90):6.2f}s "
                      f"{np.median(cpu):8.2f}s {np.percentile(cpu, 90):6.2f}s")
            if len(medians) == 2:
                this, other = medians.values()
                print(f"wall p50 ratio (this / against): {this / other:.2f}")
    print(f"\n1-min load average after: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
