"""What the CAN bus on simulated time costs per simulated second (lock-step, docs/can-bus.md).

Runs the two halves of a simulated-bus lock-step step in one process, as the controller and the
canbus processes run them (bench/bus/can/windowed_driver.py, lockstep_bus.py; no Zenoh), for
`attitude_quick`'s bus (10 ms command period, mixed transmission, secoc), interleaved per repeat
with the in-process attitude loop of the same scenario (bench.sim, no bus) as the baseline.
Prints wall time per simulated second of bus, per frame, and per plant step of each.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_can_lockstep.py [--seconds 20] [--repeats 3]
"""
from __future__ import annotations

import argparse
import statistics
import time

import msgspec
import numpy as np

from bench.bus.can.lockstep_bus import LockStepBus
from bench.bus.can.run_key import can_with_key
from bench.bus.can.sim_window import sim_ns
from bench.bus.can.windowed_driver import BOOT_WINDOWS, WindowedDriver
from bench.scenario import load_scenario
from bench.sim import simulate_attitude_in_process


def simulated_bus_s_per_sim_s(config, seconds: int, step_s: float) -> tuple[float, int]:
    """(wall s per simulated s, frames on the bus) for `seconds` of mixed-mode commanding."""
    driver, bus = WindowedDriver(config), LockStepBus(config, seed=1)
    for _, start_ns, end_ns in BOOT_WINDOWS:
        driver.heard(bus.advance(start_ns, end_ns, driver.window(start_ns, end_ns)[0])[0])
    rng = np.random.default_rng(1)
    n_steps = round(seconds / step_s)
    t0 = time.perf_counter()
    for k in range(n_steps):
        frames, _, _ = driver.window(sim_ns(k * step_s), sim_ns((k + 1) * step_s), rng.uniform(-0.2, 0.2, 3))
        heard, _ = bus.advance(sim_ns(k * step_s), sim_ns((k + 1) * step_s), frames)
        driver.heard(heard)
    return (time.perf_counter() - t0) / seconds, sum(bus.report()["frames"].values())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=int, default=20, help="simulated seconds of bus per repeat")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    scenario = load_scenario("attitude_quick")
    config = can_with_key(scenario.can, "2b7e151628aed2a6abf7158809cf4f3c")
    in_process = msgspec.structs.replace(scenario, run=msgspec.structs.replace(scenario.run, steps=200))
    bus_s, loop_s, frames = [], [], 0
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        simulate_attitude_in_process(in_process)
        loop_s.append((time.perf_counter() - t0) / (200 * scenario.step_s))
        per_s, frames = simulated_bus_s_per_sim_s(config, args.seconds, scenario.step_s)
        bus_s.append(per_s)
    bus, loop = statistics.median(bus_s), statistics.median(loop_s)
    frames_per_s = frames / (args.seconds + 0.05)
    print(f"attitude_quick, {scenario.step_s:g} s steps, {config.driver.command_period_s * 1e3:g} ms command period, "
          f"{config.security.profile}: {frames_per_s:.0f} frames per simulated second")
    print(f"in-process loop (no bus):      {loop * 1e3:8.3f} ms per simulated s ({1 / (loop * scenario.step_s):,.0f} steps/s)")
    print(f"bus on simulated time:         {bus * 1e3:8.3f} ms per simulated s ({bus / frames_per_s * 1e6:.0f} us per frame)")
    print(f"ratio bus / in-process loop:   {bus / loop:8.1f}x   (medians of {args.repeats} interleaved repeats)")


if __name__ == "__main__":
    main()
