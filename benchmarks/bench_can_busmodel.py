"""The CAN bus model: what it costs, what it adds, and how a babbling node starves the commands.

    .venv/bin/python benchmarks/bench_can_busmodel.py

1. Model throughput: frames the bus model arbitrates, times and captures per second of CPU, on a
   bus saturated by a babbler (simulated time, one process; no transport involved).
2. Driver-to-board latency through the bus model process on the Zenoh transport (three processes:
   driver here, `bench node canbus`, `bench node mtq`), median and p99 over ROUNDS runs, without
   and with a babbler at 60 % load. One-way latency = the board's applied stamp minus the driver's
   send stamp, both CLOCK_MONOTONIC. Compare with benchmarks/bench_can.py's direct figures (driver
   and board on one channel, no bus model) for what the model process adds.
3. Starvation in bus time (deterministic): command latency on the modelled 1 Mbit/s bus without a
   babbler, with one at 60 % load, and with one back to back (100 %).
"""
from __future__ import annotations

import itertools
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.bus.can import protocol as p
from bench.bus.can.busmodel import FLIGHT, BusModel
from bench.bus.can.faults import FaultSpec
from bench.bus.can.injector import FaultInjector
from bench.runtime.can_bench import CanBench, write_scenario

ROUNDS = 3
DRIVE_S = 3.0
MS = 1_000_000
SLOW_BABBLER = {"name": "flood", "start_s": 0.0, "duration_s": 60.0, "params": {"period_s": 0.0002}}


def model_throughput(simulated_s: float = 5.0) -> dict:
    proto = p.Protocol()
    t0 = 10**12
    bus = BusModel(FaultInjector([FaultSpec("flood", start_s=0.0, duration_s=simulated_s)], proto), proto, t0,
                   capture=lambda msg: None)
    counter = itertools.count()
    start = time.process_time()
    for k in range(round(simulated_s * 50)):
        t = t0 + k * 20 * MS
        bus.submit(FLIGHT, proto.command([0.1, 0.0, 0.0], next(counter)), t)
        bus.run_until(t + 20 * MS)
    cpu_s = time.process_time() - start
    frames = sum(bus.report()["frames"].values())
    return {"frames": frames, "cpu_s": cpu_s, "frames_per_cpu_s": frames / cpu_s}


def through_processes(faults: list[dict], tmp: Path, tag: str) -> tuple[list[float], dict]:
    latencies_us: list[float] = []
    report = {}
    for i in range(ROUNDS):
        scenario = write_scenario(tmp / f"{tag}{i}", {"transport": "zenoh", "faults": faults})
        bench = CanBench(scenario, tmp / f"{tag}{i}-run", f"bench-busmodel-{tag}-{i}")
        try:
            bench.start()
            bench.drive(DRIVE_S)
        except BaseException:
            bench.close()
            raise
        result = bench.stop()
        latencies_us += [ns / 1e3 for ns in result.command_latencies_ns()]
        report = result.report
    return latencies_us, report


def starvation() -> dict:
    proto = p.Protocol()
    out = {}
    for label, faults in (("no babbler", []),
                          ("babbler 60 % (every 200 us)", [FaultSpec("flood", start_s=0.0, duration_s=2.0,
                                                                     params={"period_s": 0.0002})]),
                          ("babbler 100 % (back to back)", [FaultSpec("flood", start_s=0.5, duration_s=0.5)])):
        t0 = 10**12
        bus = BusModel(FaultInjector(faults, proto), proto, t0)
        for k in range(100):
            t = t0 + k * 20 * MS
            bus.submit(FLIGHT, proto.command([0.1, 0.0, 0.0], k), t)
            bus.run_until(t + 20 * MS)
        out[label] = bus.report()
    return out


def percentiles(values: list[float]) -> str:
    if not values:
        return "no samples"
    return f"median {statistics.median(values):8.0f} us   p99 {np.percentile(values, 99):8.0f} us   (n={len(values)})"


def main() -> int:
    print("1. bus model throughput (simulated, saturated bus, candump capture off)")
    t = model_throughput()
    print(f"   {t['frames']} frames in {t['cpu_s']:.2f} s CPU: {t['frames_per_cpu_s']:,.0f} frames per CPU second "
          f"(a saturated 1 Mbit/s bus carries ~7 900 frames/s)")

    print(f"2. driver-to-board latency through the bus model process, zenoh transport, {ROUNDS} x {DRIVE_S:.0f} s at 50 Hz")
    with tempfile.TemporaryDirectory(prefix="bench-busmodel-") as tmp:
        quiet, _ = through_processes([], Path(tmp), "quiet")
        loaded, report = through_processes([SLOW_BABBLER], Path(tmp), "loaded")
    print(f"   no babbler:        {percentiles(quiet)}")
    print(f"   babbler at 60 %:   {percentiles(loaded)}   (bus load {report.get('bus_load_pct', 0):.0f} %)")

    print("3. starvation on the modelled 1 Mbit/s bus (bus time, deterministic)")
    for label, rep in starvation().items():
        lat = rep["command_latency_us"]
        key = "with_flood" if lat["with_flood"]["n"] else "without_flood"
        stats = lat[key]
        starved = rep["dropped"].get("tx_overflow", 0)
        print(f"   {label:30s} load {rep['bus_load_pct']:5.1f} % (peak {rep['peak_load_pct']:5.1f} %)  "
              f"command latency median {stats['median']:9.0f} us, max {stats['max']:9.0f} us, "
              f"{stats['n']} delivered, {starved} dropped (tx queue full)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
