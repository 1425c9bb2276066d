"""Per-step cost of the in-process attitude loop (`bench.sim.simulate_attitude_in_process`), this
tree against another (e.g. main) in the same run, on the same scenario files, interleaved so both
see the same machine load. Prints ms/step (best of the repeats) and the ratio.

    PYTHONPATH=$PWD python benchmarks/bench_attitude_step.py --other /work/main --steps 1000 \\
        --scenario /tmp/slew10hz.toml --repeats 3

The scenario files are given by path so both trees run the very same definition.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys

CHILD = """
import sys, time, msgspec
from bench.scenario import load_scenario
from bench.sim import simulate_attitude_in_process
s = load_scenario(sys.argv[1])
s = msgspec.structs.replace(s, run=msgspec.structs.replace(s.run, steps=int(sys.argv[2])))
simulate_attitude_in_process(msgspec.structs.replace(s, run=msgspec.structs.replace(s.run, steps=20)))  # imports, tables
t = time.process_time(); simulate_attitude_in_process(s); print((time.process_time() - t) / int(sys.argv[2]) * 1e3)
"""


def step_ms(tree: str, scenario: str, steps: int) -> float:
    env = dict(os.environ, PYTHONPATH=tree)
    out = subprocess.run([sys.executable, "-c", CHILD, scenario, str(steps)], env=env, cwd=tree,
                         capture_output=True, text=True, check=True, timeout=1800)
    return float(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--other", required=True, help="the tree to compare with (e.g. /work/main)")
    parser.add_argument("--scenario", action="append", required=True, help="scenario TOML path (repeatable)")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    here = os.getcwd()
    for scenario in args.scenario:
        best = {here: float("inf"), args.other: float("inf")}
        for _ in range(args.repeats):
            for tree in (args.other, here):
                best[tree] = min(best[tree], step_ms(tree, scenario, args.steps))
        print(f"{os.path.basename(scenario)}: {args.other} {best[args.other]:.3f} ms/step (CPU), "
              f"this tree {best[here]:.3f} ms/step, ratio {best[args.other] / best[here]:.2f}x")


if __name__ == "__main__":
    main()
