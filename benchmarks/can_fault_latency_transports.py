"""The driver's fault detection latencies over both CAN transports, side by side.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/can_fault_latency_transports.py
    PYTHONPATH=$PWD .venv/bin/python benchmarks/can_fault_latency_transports.py --scenarios attitude_fault_stuck --out /tmp/lat.json
    PYTHONPATH=$PWD .venv/bin/python benchmarks/can_fault_latency_transports.py --whole-lockstep   # + the whole slew and hold in UML

Each built-in attitude fault scenario (bench/scenarios/attitude_fault_*.toml) runs twice, as
`bench run` does: over the portable Zenoh transport on the host, and over the kernel's SocketCAN
(vcan) in user-mode Linux (one boot, tests/uml.py; the scenario moved onto SocketCAN as the guest
tests do: tests/uml_guest_attitude/socketcan_scenarios.py). The runs go one after the other on
each side, so that no run shares the CPU with another run. The scenarios run in real time (time
factor 1): the latencies are wall-clock, the driver's own estimate of each detection (a lost
heartbeat from when the next was due, a rejected command from when it was sent:
bench/bus/can/driver.py), read from each run's can/driver.json. Printed: per scenario and fault
kind, the count, p50 and max latency over each transport, and each run's verdict.

--whole-lockstep also runs the planned slew (2170 lock-step steps) and the pointing hold (11340)
whole over SocketCAN in the same boot, and prints their verdicts (the guest tests run them cut
short: tests/uml_guest_attitude/guest_attitude_scenarios_socketcan.py).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO / "tests" / "uml_guest_attitude"))
from socketcan_scenarios import EXPECTED_KINDS, FAULTS, HOLD, SLEW, detection_latencies_s, fault_names, write_over_socketcan  # noqa: E402

RUN_TIMEOUT_S = 1800
GUEST_MEM = "1536M"          # one run at a time (tests/test_kernel_can_uml.py: ATTITUDE_GUEST_MEM)


def bench_run(scenario: str, run_id: str, runs_dir: Path, *extra: str) -> dict:
    """`bench run` as a user runs it: with the report, which judges the criteria on the driver's
    events (with --no-report those read "not measured")."""
    started = time.monotonic()
    result = subprocess.run([sys.executable, "-m", "bench.cli", "run", scenario, "--run-id", run_id, "--runs-dir",
                             str(runs_dir), "--no-progress", *extra],
                            capture_output=True, text=True, timeout=RUN_TIMEOUT_S, cwd=REPO)
    return {"run_id": run_id, "exit_code": result.returncode, "wall_s": time.monotonic() - started,
            "stderr_tail": result.stderr[-2000:]}


def guest_main(args) -> int:
    """Inside UML: each scenario over SocketCAN on vcan0/vcan1, one after the other."""
    from bench.bus.can import vcan

    vcan.up(("vcan0", "vcan1"))
    runs_dir = Path(args.runs_dir)
    runs_dir.mkdir(parents=True, exist_ok=True)
    records = []
    names = list(args.scenarios) + ([SLEW, HOLD] if args.whole_lockstep else [])
    for name in names:
        path = write_over_socketcan(name, "vcan0", "vcan1", runs_dir)
        records.append(bench_run(str(path), name, runs_dir))
        print(json.dumps(records[-1]), flush=True)
    (runs_dir / "guest_runs.json").write_text(json.dumps(records, indent=1))
    return 0


def run_summary(run_dir: Path) -> dict:
    """Verdict, mode and driver latencies of one finished run."""
    metrics = json.loads((run_dir / "metrics.json").read_text()) if (run_dir / "metrics.json").exists() else {}
    driver_path = run_dir / "can" / "driver.json"
    latencies = detection_latencies_s(json.loads(driver_path.read_text())) if driver_path.exists() else {}
    verdict = metrics.get("verdict", {})
    failed = [c.get("metric") for c in verdict.get("criteria", []) if not c.get("passed")]
    return {"passed": verdict.get("passed"), "failed_criteria": failed, "latencies_s": latencies}


def fmt_latencies(values: list[float] | None) -> str:
    if not values:
        return "- | - | -"
    ms = np.asarray(values) * 1e3
    return f"{len(ms)} | {np.percentile(ms, 50):.1f} | {ms.max():.1f}"


def scenario_kinds(name: str) -> set[str]:
    """The driver events that detect the scenario's faults (as the tests expect them), and the
    driver's own lateness (host_overrun), which says how busy the host was."""
    return set().union(*(EXPECTED_KINDS[f] for f in fault_names(name))) | {"host_overrun"}


def table(results: dict, all_kinds: bool = False) -> str:
    lines = ["| scenario | driver event | zenoh n | zenoh p50 [ms] | zenoh max [ms] | socketcan n | socketcan p50 [ms] "
             "| socketcan max [ms] |", "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for name, sides in results.items():
        kinds = sorted(set(sides["zenoh"]["latencies_s"]) | set(sides["socketcan"]["latencies_s"]))
        if not all_kinds:
            kinds = [k for k in kinds if k in scenario_kinds(name)]
        for kind in kinds:
            lines.append(f"| {name} | {kind} | {fmt_latencies(sides['zenoh']['latencies_s'].get(kind))} | "
                         f"{fmt_latencies(sides['socketcan']['latencies_s'].get(kind))} |")
    lines.append("")
    lines.append("| scenario | zenoh verdict (host) | socketcan verdict (UML) |")
    lines.append("| --- | --- | --- |")
    for name, sides in results.items():
        verdicts = []
        for side in ("zenoh", "socketcan"):
            s = sides[side]
            verdicts.append("PASS" if s["passed"] else f"FAIL {', '.join(s['failed_criteria'])}" if s["passed"] is False
                            else "no verdict")
        lines.append(f"| {name} | {verdicts[0]} | {verdicts[1]} |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenarios", nargs="+", default=list(FAULTS), help="built-in fault scenarios")
    parser.add_argument("--runs-dir", default=None, help="where both sides' run directories go (default: a new temp dir)")
    parser.add_argument("--out", default=None, help="JSON file for the results")
    parser.add_argument("--all-kinds", action="store_true", help="every driver event kind, not only the faults' own")
    parser.add_argument("--whole-lockstep", action="store_true", help="also the whole slew and hold over SocketCAN")
    parser.add_argument("--guest", action="store_true", help=argparse.SUPPRESS)    # the half that runs in UML
    args = parser.parse_args()
    if args.guest:
        return guest_main(args)

    import tempfile

    import uml

    root = Path(args.runs_dir or tempfile.mkdtemp(prefix="can-fault-latency-"))
    zenoh_dir, socketcan_dir = root / "zenoh", root / "socketcan"
    zenoh_dir.mkdir(parents=True, exist_ok=True)
    for name in args.scenarios:
        record = bench_run(name, name, zenoh_dir)
        print(f"zenoh (host): {name}: exit {record['exit_code']}, {record['wall_s']:.0f} s", flush=True)
    command = [sys.executable, str(Path(__file__).resolve()), "--guest", "--runs-dir", str(socketcan_dir),
               "--scenarios", *args.scenarios] + (["--whole-lockstep"] if args.whole_lockstep else [])
    per_run_s = 300 + (7200 if args.whole_lockstep else 0)
    started = time.monotonic()
    result = uml.run(command, root / "uml-job", timeout_s=per_run_s * len(args.scenarios) + 120, mem=GUEST_MEM)
    print(f"socketcan (UML): exit {result.returncode}, {time.monotonic() - started:.0f} s", flush=True)
    if result.returncode != 0:
        print(result.output[-4000:], file=sys.stderr)
    results = {name: {"zenoh": run_summary(zenoh_dir / name), "socketcan": run_summary(socketcan_dir / name)}
               for name in args.scenarios}
    print(f"\nreal time (time factor 1), wall-clock latencies; runs in {root}\n")
    print(table(results, args.all_kinds))
    if args.whole_lockstep:
        for name in (SLEW, HOLD):
            print(f"{name} whole over socketcan (UML, lock-step): {run_summary(socketcan_dir / name)}")
    if args.out:
        Path(args.out).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
