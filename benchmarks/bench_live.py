"""The live view's cost to the loop (issue 48): `bench run` without `--live`, with `--live` and no client,
and with `--live` and one Foxglove client subscribed to every channel, interleaved (A B C A B C ...),
so that a host that gets slower or faster during the benchmark moves all three alike.

The loop: a lock-step attitude run (`attitude_quick`: B-dot then rate damping through the
magnetorquer board on the CAN bus over Zenoh, the bus on the wall clock, six processes), which
runs as fast as the machine allows, so any cost the live view puts on the loop's processes shows
as a lower rate. Its figure is the rate from step 0's sample to the last step's (start-up and stop
excluded, as benchmarks/bench_loop.py measures it). Per condition: the mean, the run-to-run spread
(standard deviation, min-max), and the difference of its mean to the run without --live, in
standard errors. With a client: how many messages it received, and what the live view dropped (its
queue full; live.json) — a lock-step run is streamed at its own pace, never throttled.

The client is tests/foxglove_ws_client.py (the `websockets` package, written from the Foxglove
WebSocket protocol's specification).

    PYTHONPATH=$PWD python benchmarks/bench_live.py [--repeats 6] [--steps 1500] [--scenario attitude_quick]
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

CHECKOUT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(CHECKOUT / "tests"))
from foxglove_ws_client import FoxgloveClient  # noqa: E402

from bench.bus.session import free_loopback_port  # noqa: E402

CONDITIONS = ("without --live", "--live, no client", "--live, one client")


class Watcher(threading.Thread):
    """One client: connects as soon as the server is up, subscribes to every channel, counts until the run ends."""

    def __init__(self, port: int):
        super().__init__(daemon=True)
        self.port = port
        self.received = 0
        self.topics = 0
        self.stop = threading.Event()

    def run(self) -> None:
        asyncio.run(self._watch())

    async def _watch(self) -> None:
        deadline = time.monotonic() + 120
        while not self.stop.is_set() and time.monotonic() < deadline:
            try:
                client = await FoxgloveClient(f"ws://127.0.0.1:{self.port}").__aenter__()
            except OSError:
                await asyncio.sleep(0.05)
                continue
            try:
                await client.wait_for(lambda g: len(g.channels) > 10, 10)
                await client.subscribe([c["topic"] for c in client.got.channels.values()])
                self.topics = len(client.got.channels)
                while not self.stop.is_set() and not client._reader.done():
                    await asyncio.sleep(0.05)
                    self.received = sum(len(v) for v in client.got.messages.values())
            finally:
                try:
                    await client.__aexit__(None, None, None)
                except Exception:   # noqa: BLE001 - the server went with the run
                    pass
            return


def one_run(scenario: str, steps: int, runs_dir: Path, run_id: str, condition: int) -> dict:
    cmd = [sys.executable, "-m", "bench.cli", "run", scenario, "--steps", str(steps), "--run-id", run_id,
           "--runs-dir", str(runs_dir), "--no-progress", "--no-report"]
    watcher = None
    if condition > 0:
        port = free_loopback_port()
        cmd += ["--live", str(port)]
        if condition == 2:
            watcher = Watcher(port)
            watcher.start()
    result = subprocess.run(cmd, cwd=CHECKOUT, capture_output=True, text=True)
    if watcher is not None:
        watcher.stop.set()
        watcher.join(timeout=10)
    if result.returncode != 0:
        logs = "".join(f"\n--- {log.name}:\n" + "\n".join(log.read_text(errors="replace").splitlines()[-6:])
                       for log in sorted((runs_dir / run_id / "logs").glob("*.log")))
        raise SystemExit(f"bench run exited with {result.returncode}:\n{result.stderr[-2000:]}{logs}")
    with np.load(runs_dir / run_id / "trajectory.npz") as data:
        sensed = data["stamp_sensed_ns"]
    out = {"rate_hz": (len(sensed) - 1) / ((sensed[-1] - sensed[0]) / 1e9)}
    live = runs_dir / run_id / "live.json"
    if live.is_file():
        summary = json.loads(live.read_text())
        out["dropped"] = sum(summary.get("dropped", {}).values())
        out["forwarded"] = sum(summary.get("forwarded", {}).values())
    if watcher is not None:
        out["received"] = watcher.received
        out["topics"] = watcher.topics
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=6)
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--scenario", default="attitude_quick")
    args = parser.parse_args()
    load_before = os.getloadavg()[0]
    results: list[list[dict]] = [[] for _ in CONDITIONS]
    with tempfile.TemporaryDirectory(prefix="bench-live-") as tmp:
        runs = Path(tmp)
        for repeat in range(args.repeats):
            for condition in range(len(CONDITIONS)):
                r = one_run(args.scenario, args.steps, runs, f"live-{repeat}-{condition}", condition)
                results[condition].append(r)
                extra = "".join(f" {k} {r[k]}" for k in ("received", "forwarded", "dropped") if k in r)
                print(f"repeat {repeat + 1}/{args.repeats} {CONDITIONS[condition]:20s} {r['rate_hz']:7.1f} steps/s{extra}",
                      flush=True)
    print(f"\n{args.scenario}, {args.steps} lock-step steps per run, {args.repeats} runs per condition interleaved; "
          f"{os.cpu_count()} CPUs, load average {load_before:.2f} before, {os.getloadavg()[0]:.2f} after")
    base = [r["rate_hz"] for r in results[0]]
    print(f"{'condition':22s} {'mean':>8s} {'std':>7s} {'min':>8s} {'max':>8s}  vs without --live")
    for name, runs_of in zip(CONDITIONS, results):
        rates = [r["rate_hz"] for r in runs_of]
        mean, std = statistics.mean(rates), statistics.stdev(rates) if len(rates) > 1 else 0.0
        diff = mean - statistics.mean(base)
        se = (std ** 2 / len(rates) + statistics.variance(base) / len(base)) ** 0.5 if len(rates) > 1 else float("nan")
        versus = "" if runs_of is results[0] else f"  {100 * diff / statistics.mean(base):+.1f} % ({diff / se:+.1f} standard errors)"
        print(f"{name:22s} {mean:8.1f} {std:7.1f} {min(rates):8.1f} {max(rates):8.1f}{versus}")
    watched = results[2]
    print(f"one client: {statistics.mean(r.get('received', 0) for r in watched):.0f} messages received per run "
          f"on {watched[0].get('topics', 0)} channels; the live view dropped {sum(r.get('dropped', 0) for r in watched)} "
          f"samples in all (its queue full)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
