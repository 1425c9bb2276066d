"""The SocketCAN fault suite in user-mode Linux, N times in a row with the host's cores busy.

    .venv/bin/python benchmarks/can_uml_load.py                 # 10 runs, 2 busy processes
    .venv/bin/python benchmarks/can_uml_load.py --runs 3 --busy 0 --selection tests/uml_guest_can/guest_can_faults.py::test_socketcan_clean_bus

Each run boots UML once and runs the guest suite (tests/uml_guest_can, as test_kernel_can_uml.py
does) with BENCH_CAN_REPORT_DIR set, so that every fault run inside the guest appends what the
driver, the board and the bus model said about their own lateness to host_overruns.jsonl:
- host_overruns: command periods the driver's command loop started more than half a period late;
- board_host_overruns: periodic frames the board sent more than half a period late;
- bus_model_host_overruns: deliveries or wake-ups of the bus model more than 5 ms late;
- host_caused: what those explain (tests/test_can_faults.py::host_caused): board command
  timeouts, missed frame deadlines and actuator mismatches next to measured lateness, and the
  error reset after them: the host's doing, not the bus's;
- bus_events_before_silence: everything else the driver reported while commanding.
A test that fails where its run had host overruns is reported as "failed with host overruns", not
as a bus fault. `--busy N` starts N processes spinning on the host (N = 2: both cores here) for
the whole benchmark and stops them (by pid) at the end. The result table goes to stdout and, with
--out, to a JSON file.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
import uml  # noqa: E402

SELECTION = "tests/uml_guest_can"
PER_TEST_TIMEOUT_S = uml.CAN_BENCH_TEST_TIMEOUT_S     # as tests/test_kernel_can_uml.py
# what each fault run records of the nodes' own lateness (tests/test_can_faults.py)
HOST_OVERRUN_KEYS = ("host_overruns", "board_host_overruns", "bus_model_host_overruns")


def busy_processes(n: int) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def one_run(index: int, job_dir: Path, selection: str, timeout_s: float) -> dict:
    job_dir.mkdir(parents=True, exist_ok=True)
    junit = job_dir / "junit.xml"
    command = ["env", f"BENCH_CAN_REPORT_DIR={job_dir}", sys.executable, "-m", "pytest", "-q", "-n", "0", "-p", "no:cacheprovider",
               "-o", "python_files=guest_*.py", f"--junitxml={junit}", f"--basetemp={job_dir / 'tmp'}",
               f"--timeout={PER_TEST_TIMEOUT_S:g}", selection]
    started = time.monotonic()
    result = uml.run(command, job_dir, timeout_s=timeout_s)
    outcomes = {}
    if junit.exists():
        for case in ET.parse(junit).getroot().iter("testcase"):
            failed = any(child.tag in ("failure", "error") for child in case)
            outcomes[case.get("name")] = "failed" if failed else "passed"
    records = []
    report = job_dir / "host_overruns.jsonl"
    if report.exists():
        records = [json.loads(line) for line in report.read_text().splitlines() if line]
    # pytest's tmp_path names are the test's name cut to 30 characters plus a number.
    by_prefix = {r["test"].rstrip("0123456789"): r for r in records}
    tests = {}
    for name, outcome in outcomes.items():
        record = next((r for prefix, r in by_prefix.items() if name.startswith(prefix)), {})
        host = sum(record.get(k, 0) for k in HOST_OVERRUN_KEYS)
        if outcome == "failed" and host:
            outcome = "failed with host overruns"
        tests[name] = {"outcome": outcome, "driver_host_overruns": record.get("host_overruns"),
                       "board_host_overruns": record.get("board_host_overruns"),
                       "bus_model_host_overruns": record.get("bus_model_host_overruns"),
                       "host_caused": record.get("host_caused", []),
                       "bus_events": record.get("bus_events_before_silence", [])}
    return {"run": index, "uml_exit": result.returncode, "wall_s": round(time.monotonic() - started, 1),
            "tests": tests}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--busy", type=int, default=2, help="host processes spinning meanwhile (2: both cores)")
    parser.add_argument("--selection", default=SELECTION)
    parser.add_argument("--timeout-s", type=float, default=1200, help="bound of one boot (both cores busy: slower than the test's 840 s)")
    parser.add_argument("--jobs", type=Path, default=Path("/tmp/can-uml-load"))
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    uml.ensure_uml()
    busy = busy_processes(args.busy)
    runs = []
    try:
        for i in range(args.runs):
            run = one_run(i, args.jobs / f"run{i}", args.selection, args.timeout_s)
            runs.append(run)
            passed = sum(t["outcome"] == "passed" for t in run["tests"].values())
            host = sum((t[f"{k}_host_overruns"] or 0) for t in run["tests"].values() for k in ("driver", "board", "bus_model"))
            print(f"run {i}: {passed}/{len(run['tests'])} passed in {run['wall_s']} s (UML exit {run['uml_exit']}), "
                  f"host overruns {host}", flush=True)
            for name, t in run["tests"].items():
                if t["outcome"] != "passed":
                    print(f"    {name}: {t['outcome']}; host-caused {t['host_caused'][:3]}; bus events {t['bus_events'][:6]}")
    finally:
        for proc in busy:
            proc.kill()
            proc.wait()
    all_passed = sum(all(t["outcome"] == "passed" for t in r["tests"].values()) and r["tests"] != {} for r in runs)
    print(f"{all_passed}/{len(runs)} runs passed every test with {args.busy} busy host processes")
    if args.out:
        args.out.write_text(json.dumps({"busy": args.busy, "selection": args.selection, "runs": runs}, indent=1))
    return 0 if all_passed == len(runs) else 1


if __name__ == "__main__":
    sys.exit(main())
