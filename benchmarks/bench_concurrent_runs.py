"""Four concurrent lock-step runs on two busy cores: does hang detection cry wolf?

Each round starts one busy-loop process per core, then RUNS `bench run` processes of the default
scenario at once (lock-step, each with its own hub), and counts how they end: 0 (finished), and
for the others whether the launcher called a process hung ("stopped answering", "is stopped") or
a peer lost. Repeated ROUNDS times for the bench's liveliness defaults and, in the same run as the
baseline, for the settings before issue 10 (600 ms lease, 1 s grace: `lease_s = 0.6`,
`hang_timeout_s = 1.0`).

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_concurrent_runs.py [--rounds 5] [--runs 4]
"""
from __future__ import annotations

import argparse
import multiprocessing
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CONFIGS = {
    "defaults": "",
    "before issue 10 (lease 0.6 s, 1 s grace)": "[run.liveliness]\nlease_s = 0.6\nhang_timeout_s = 1.0\n",
}
HANG_WORDS = ("stopped answering", "is stopped", "lost while waiting", "lost at step")


def busy_loop() -> None:
    while True:
        pass


def one_round(config_text: str, runs: int, steps: int, work: Path, tag: str) -> list[tuple[int, str, float]]:
    scenario = work / f"{tag}.toml"
    scenario.write_text(f'name = "concurrent"\n[run]\nsteps = {steps}\n{config_text}')
    busy = [multiprocessing.Process(target=busy_loop, daemon=True) for _ in range(os.cpu_count() or 2)]
    for p in busy:
        p.start()
    try:
        started = time.monotonic()
        procs = [subprocess.Popen([sys.executable, "-m", "bench.cli", "run", str(scenario), "--run-id", f"{tag}-{i}",
                                   "--runs-dir", str(work / "runs"), "--no-progress", "--no-report"],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
                 for i in range(runs)]
        results = []
        for proc in procs:
            _, stderr = proc.communicate(timeout=1800)
            first = next((line for line in stderr.splitlines() if line.startswith("bench: error")), "")
            results.append((proc.returncode, first, time.monotonic() - started))
        return results
    finally:
        for p in busy:
            p.terminate()
            p.join()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--runs", type=int, default=4)
    parser.add_argument("--steps", type=int, default=288)
    parser.add_argument("--only", choices=["defaults", "baseline"], help="run one configuration only")
    args = parser.parse_args()
    configs = dict(CONFIGS)
    if args.only == "defaults":
        configs = {"defaults": CONFIGS["defaults"]}
    elif args.only == "baseline":
        configs = {k: v for k, v in CONFIGS.items() if k != "defaults"}
    print(f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at start; {args.runs} concurrent lock-step "
          f"runs of {args.steps} steps per round, one busy loop per core", flush=True)
    totals = {name: {"runs": 0, "ok": 0, "false_hang": 0, "other": 0, "wall_s": []} for name in configs}
    with tempfile.TemporaryDirectory(prefix="bench-concurrent-") as tmp:
        work = Path(tmp)
        for r in range(args.rounds):
            for j, (name, text) in enumerate(configs.items()):    # interleaved: same load for both
                results = one_round(text, args.runs, args.steps, work, f"r{r}c{j}")
                t = totals[name]
                for code, line, wall_s in results:
                    t["runs"] += 1
                    t["wall_s"].append(wall_s)
                    if code == 0:
                        t["ok"] += 1
                    elif any(w in line for w in HANG_WORDS):
                        t["false_hang"] += 1
                    else:
                        t["other"] += 1
                codes = [c for c, _, _ in results]
                print(f"round {r + 1} {name}: exit codes {codes}; load {os.getloadavg()[0]:.1f}; "
                      + "; ".join(line[:140] for c, line, _ in results if c != 0), flush=True)
    print("\n| liveliness settings | runs | finished | false hang | other failure | slowest run [s] |")
    print("| --- | --- | --- | --- | --- | --- |")
    for name, t in totals.items():
        print(f"| {name} | {t['runs']} | {t['ok']} | {t['false_hang']} | {t['other']} | {max(t['wall_s']):.0f} |")
    return 0 if totals.get("defaults", {"false_hang": 0})["false_hang"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
