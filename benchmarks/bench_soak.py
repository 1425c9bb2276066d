"""Soak: a long real-time attitude run over the CAN bus, every process's memory sampled over it.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_soak.py --minutes 30 > soak.txt 2>&1 &

runs `bench run attitude_pointing_rt --steps N --no-report` (real time at the scenario's time
factor, 1x: plant, estimator, controller with the CAN driver, bus model, magnetorquer board and
recorder, each its own process) for the given wall-clock length, and samples the resident memory
(VmRSS of /proc/<pid>/status) of the launcher and every process it started, every --period-s.

It prints, per process, its memory at the start and the end of the loop and its growth in MiB/h:
the slope of a least-squares line through the samples of the loop's second half (CPython's
allocator keeps freed memory, and the first minutes fill caches and pools: a start-to-end
difference would charge those to the run). Then the sense -> board latency (plant sensed ->
board received, from the run's trajectory.npz stamps, as metrics.json's latency.sense_to_board)
of the first quarter of the steps against the last quarter.

Targets (issue 44): no process grows more than 5 MiB/h over its second half; sense -> board p99
in the last quarter within 1.2x of the first. Exit code 1 if one is missed, 2 if the run failed.
The samples are kept beside the run: <runs-dir>/<run_id>/soak_rss.jsonl, and the figures in
soak.json. docs/performance.md ("Long runs") has the figures of the last soak.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

GROWTH_TARGET_MIB_PER_H = 5.0
LATENCY_RATIO_TARGET = 1.2


def children(pid: int) -> list[int]:
    out: list[int] = []
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/children") as f:
                out += [int(x) for x in f.read().split()]
    except OSError:
        pass
    return out


def descendants(root: int) -> list[int]:
    todo, seen = [root], []
    while todo:
        pid = todo.pop()
        seen.append(pid)
        todo += children(pid)
    return seen


def process_info(pid: int) -> tuple[list[str], int, int] | None:
    """(argv, parent pid, VmRSS in kB), None for a process gone or a zombie."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            argv = f.read().decode(errors="replace").split("\0")
        with open(f"/proc/{pid}/status") as f:
            status = dict(line.split(":", 1) for line in f.read().splitlines() if ":" in line)
    except OSError:
        return None
    if "VmRSS" not in status:
        return None
    return argv, int(status["PPid"]), int(status["VmRSS"].split()[0])


def label(pid: int, root: int, argv: list[str], parent_argv: list[str] | None) -> str:
    if pid == root:
        return "launcher"
    if "node" in argv[:-1]:
        name = argv[argv.index("node") + 1]
        # A node forks a small watchdog (bench/runtime/ownership.py) with the node's own argv.
        return f"{name} (watchdog)" if parent_argv == argv else name
    if "-m" in argv[:-1]:
        return argv[argv.index("-m") + 1].rpartition(".")[2]
    return Path(argv[0]).name


def sample(root: int) -> dict[str, dict]:
    infos = {pid: process_info(pid) for pid in descendants(root)}
    out = {}
    for pid, info in infos.items():
        if info is None:
            continue
        argv, ppid, rss_kb = info
        parent = infos.get(ppid)
        name = label(pid, root, argv, parent[0] if parent else None)
        out[f"{name} [{pid}]"] = {"name": name, "pid": pid, "rss_mib": rss_kb / 1024}
    return out


def growth(series: list[tuple[float, float]], t0: float, t1: float) -> dict:
    """Memory at the loop's start and end and the slope over its second half [MiB/h]."""
    points = np.array([(t, m) for t, m in series if t0 <= t <= t1])
    if len(points) < 3:
        return {"samples": int(len(points))}
    half = points[points[:, 0] >= (t0 + t1) / 2]
    slope = float(np.polyfit(half[:, 0], half[:, 1], 1)[0] * 3600) if len(half) >= 3 else float("nan")
    return {"samples": int(len(points)), "start_mib": float(points[0, 1]), "end_mib": float(points[-1, 1]),
            "peak_mib": float(points[:, 1].max()), "second_half_mib_per_h": slope}


def latency_quarters(run_dir: Path) -> dict:
    """sense -> board per step (ms), p50/p99 of the first and the last quarter of the steps."""
    data = np.load(run_dir / "trajectory.npz")
    sensed, board = data["stamp_sensed_ns"], data["stamp_board_received_ns"]
    n = len(sensed)
    quarter = n // 4
    out = {"steps": n}
    for name, part in (("first", slice(0, quarter)), ("last", slice(n - quarter, n))):
        s, b = sensed[part], board[part]
        ok = (s >= 0) & (b >= 0)
        ms = (b[ok] - s[ok]) / 1e6
        out[name] = {"samples": int(ok.sum()), "p50_ms": float(np.percentile(ms, 50)) if ok.any() else None,
                     "p99_ms": float(np.percentile(ms, 99)) if ok.any() else None}
    if out["first"]["p99_ms"] and out["last"]["p99_ms"] is not None:
        out["p99_ratio_last_to_first"] = out["last"]["p99_ms"] / out["first"]["p99_ms"]
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=30.0, help="wall-clock length of the loop (default 30)")
    parser.add_argument("--scenario", default="attitude_pointing_rt")
    parser.add_argument("--period-s", type=float, default=5.0, help="memory sampling period")
    parser.add_argument("--runs-dir", default="runs")
    parser.add_argument("--run-id", default=None)
    args = parser.parse_args(argv)

    from bench.scenario import load_scenario

    scenario = load_scenario(args.scenario)
    if scenario.kind != "attitude" or scenario.run.mode != "real-time" or scenario.can is None:
        parser.error(f"{args.scenario}: a real-time attitude scenario over the CAN bus is needed")
    rate_hz = scenario.attitude.sensors.gyro_rate_hz * scenario.run.time_factor   # steps per wall second
    steps = max(4, round(args.minutes * 60.0 * rate_hz))
    run_id = args.run_id or f"soak_{time.strftime('%Y%m%d_%H%M%S')}"
    run_dir = Path(args.runs_dir) / run_id
    bench = Path(sys.executable).with_name("bench")
    command = [str(bench), "run", args.scenario, "--steps", str(steps), "--no-report", "--no-progress",
               "--runs-dir", args.runs_dir, "--run-id", run_id]
    print(f"soak: {' '.join(command)}  ({steps} steps, {steps / rate_hz / 60:.1f} min at {rate_hz:g} steps/s)",
          flush=True)

    samples: list[dict] = []
    started = time.monotonic()
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    log_lines: list[str] = []
    import threading

    reader = threading.Thread(target=lambda: log_lines.extend(proc.stdout), daemon=True)
    reader.start()
    next_report = started + 300.0
    while proc.poll() is None:
        now = time.monotonic() - started
        samples.append({"t_s": now, "processes": sample(proc.pid)})
        if time.monotonic() >= next_report:
            next_report += 300.0
            rss = {k.split(" [")[0]: round(v["rss_mib"], 1) for k, v in samples[-1]["processes"].items()
                   if "watchdog" not in k}
            print(f"  {now / 60:5.1f} min  RSS MiB {rss}", flush=True)
        time.sleep(args.period_s)
    reader.join(timeout=5.0)
    code = proc.returncode
    print(f"bench run exited with {code} after {(time.monotonic() - started) / 60:.1f} min", flush=True)
    if code != 0:
        print("".join(log_lines[-30:]))

    run_dir.mkdir(parents=True, exist_ok=True)
    with open(run_dir / "soak_rss.jsonl", "w") as f:
        for s in samples:
            f.write(json.dumps(s) + "\n")

    # The loop: from the first sample with the plant up to the last one with it.
    with_plant = [s["t_s"] for s in samples if any(p["name"] == "plant" for p in s["processes"].values())]
    if len(with_plant) < 3:
        print("the plant was never seen running")
        return 2
    t0, t1 = with_plant[0], with_plant[-1]
    series: dict[str, list[tuple[float, float]]] = {}
    for s in samples:
        for key, p in s["processes"].items():
            series.setdefault(key, []).append((s["t_s"], p["rss_mib"]))
    results = {key: growth(points, t0, t1) for key, points in sorted(series.items())}
    print(f"\nresident memory over the loop ({(t1 - t0) / 60:.1f} min, sampled every {args.period_s:g} s); "
          f"growth = slope over the second half")
    print(f"  {'process':34s} {'start':>9s} {'end':>9s} {'growth':>12s}")
    worst = 0.0
    for key, g in results.items():
        if "second_half_mib_per_h" not in g:
            continue
        slope = g["second_half_mib_per_h"]
        worst = max(worst, slope)
        flag = "" if slope <= GROWTH_TARGET_MIB_PER_H else "  over target"
        print(f"  {key:34s} {g['start_mib']:7.1f} M {g['end_mib']:7.1f} M {slope:+8.2f} M/h{flag}")

    latency = latency_quarters(run_dir) if (run_dir / "trajectory.npz").exists() else {}
    ratio = latency.get("p99_ratio_last_to_first")
    if latency:
        f, last = latency["first"], latency["last"]
        print(f"\nsense -> board ({latency['steps']} steps): first quarter p50 {f['p50_ms']:.2f} ms, p99 {f['p99_ms']:.2f} ms; "
              f"last quarter p50 {last['p50_ms']:.2f} ms, p99 {last['p99_ms']:.2f} ms; p99 last/first {ratio:.2f}")
    metrics_path = run_dir / "metrics.json"
    verdict = (json.loads(metrics_path.read_text()).get("verdict") or {}).get("passed") if metrics_path.exists() else None
    growth_ok = worst <= GROWTH_TARGET_MIB_PER_H
    latency_ok = ratio is not None and ratio <= LATENCY_RATIO_TARGET
    print(f"\ntargets: growth <= {GROWTH_TARGET_MIB_PER_H:g} MiB/h: {'met' if growth_ok else 'MISSED'} "
          f"(worst {worst:+.2f}); sense -> board p99 last/first <= {LATENCY_RATIO_TARGET:g}: "
          f"{'met' if latency_ok else 'MISSED'}; run verdict passed: {verdict}")
    (run_dir / "soak.json").write_text(json.dumps({
        "command": command, "steps": steps, "loop_s": t1 - t0, "period_s": args.period_s, "exit_code": code,
        "memory": results, "latency_sense_to_board": latency, "verdict": verdict,
        "targets_met": {"growth": growth_ok, "latency": latency_ok}}, indent=1))
    if code != 0:
        return 2
    return 0 if growth_ok and latency_ok else 1


if __name__ == "__main__":
    sys.exit(main())
