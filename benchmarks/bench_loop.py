"""Lock-step loop rate, the cost of one Zenoh hop inside it, and start-up of `bench run`.

Each repeat measures, one after the other so all three see the same load:

1. the in-process simulation of the same scenario (same plant, estimator and control law, no
   Zenoh, no processes): the baseline rate;
2. a raw Zenoh hop between two processes: this process and a child, each with a session from the
   project's factory (bench/bus/session.py) and publishers set as the nodes' (reliable, blocking),
   ping-pong of a payload the size of the loop's estimate message; the child answers from its
   Zenoh callback, this process receives on a FIFO channel; one hop = round trip / 2;
3. `bench run --steps N` of the default scenario (rendezvous_lqr, plant -> estimator ->
   controller in lock-step): the loop's rate (first sample to last command), each of its three
   hops from the messages' stage stamps (plant sensed -> estimator received, estimated ->
   controller received, commanded -> plant received: encoding, publishing, Zenoh, decoding and
   the hand-off to the node's thread), and the start-up (command start to the plant's first step,
   its "peers ready" log line);
4. the attitude loop through the CAN nodes: `bench run attitude_quick --steps M` (plant,
   estimator, controller with the flight-side driver, bus model, board: lock-step) against the
   in-process attitude loop of the same scenario (bench.sim.simulate_attitude_in_process), each
   from the first step's sample to the last step's.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_loop.py [--repeats 3] [--steps 2000] [--attitude-steps 600]

Prints one line per repeat and measure, then the medians, each loop's physical limit and its
fraction of it, and a JSON summary. A loop of processes cannot cycle faster than its hops allow:
its limit is one cycle of (hops per cycle x the raw hop's p50 + the in-process step), with three
hops for the translational loop (plant -> estimator -> controller -> plant) and four for the
attitude loop through the CAN nodes (plant -> estimator -> controller -> canbus -> plant). Issue
49's targets: the translational loop at least 0.6 of its limit, the attitude loop 0.4, each hop
inside the loop at most 1.5x raw at p50.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import msgspec
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))   # bench_startup, beside this file
from bench_startup import first_step_wall_s  # noqa: E402

from bench.scenario import load_scenario  # noqa: E402
from bench.sim import simulate_attitude_in_process, simulate_in_process  # noqa: E402

import bench  # noqa: E402

# The checkout whose `bench` package is imported (PYTHONPATH): `bench run` runs from it, so the
# same script measures another checkout's code (before/after comparisons).
CHECKOUT = Path(bench.__file__).resolve().parent.parent
SCENARIO = "rendezvous_lqr"           # `bench run`'s default
ATTITUDE_SCENARIO = "attitude_quick"  # the attitude card: lock-step through the CAN nodes
HOPS = (("sensed", "estimator_received"), ("estimated", "controller_received"), ("commanded", "plant_received"))
PING_KEY, PONG_KEY = "bench-loop/raw/ping", "bench-loop/raw/pong"
TRANSLATION_HOPS, ATTITUDE_HOPS = 3, 4   # Zenoh hops per lock-step cycle (the docstring's loops)
TARGET_TRANSLATION_LIMIT_FRACTION = 0.6
TARGET_ATTITUDE_LIMIT_FRACTION = 0.4
TARGET_HOP_RATIO = 1.5


def limit_hz(hops: int, raw_hop_p50_us: float, in_process_steps_per_s: float) -> float:
    """The fastest a lock-step loop of `hops` Zenoh hops a cycle can run: hops raw hops and one
    in-process step per cycle, nothing else."""
    return 1.0 / (hops * raw_hop_p50_us * 1e-6 + 1.0 / in_process_steps_per_s)


def in_process_rate_hz(scenario_name: str, simulate, steps: int) -> float:
    """Steps per second of `simulate` (bench.sim's in-process loop) over the scenario cut to `steps`."""
    scenario = load_scenario(scenario_name)
    scenario = msgspec.structs.replace(scenario, run=msgspec.structs.replace(scenario.run, steps=steps))
    started = time.perf_counter()
    simulate(scenario)
    return steps / (time.perf_counter() - started)


def bench_run(scenario_name: str, steps: int, runs_dir: Path, run_id: str) -> Path:
    """`bench run` of the scenario cut to `steps`, from CHECKOUT, without its report; the run's directory."""
    cmd = [sys.executable, "-m", "bench.cli", "run", scenario_name, "--steps", str(steps), "--run-id", run_id,
           "--runs-dir", str(runs_dir), "--no-progress", "--no-report"]
    result = subprocess.run(cmd, cwd=CHECKOUT, capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f"bench run {scenario_name} exited with {result.returncode}:\n{result.stderr[-2000:]}")
    return runs_dir / run_id


def attitude_multiprocess_rate_hz(scenario_name: str, steps: int, runs_dir: Path, run_id: str) -> float:
    """Steps per second of `bench run` of an attitude scenario from step 0's sample to the last
    step's (start-up and stop excluded)."""
    with np.load(bench_run(scenario_name, steps, runs_dir, run_id) / "trajectory.npz") as data:
        sensed = data["stamp_sensed_ns"]
    return (len(sensed) - 1) / ((sensed[-1] - sensed[0]) / 1e9)


# ---- the raw hop ------------------------------------------------------------------------------
def _publisher_options():
    import zenoh

    # As NodeContext.declare_publisher: reliable and blocking.
    return dict(congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)


def _pong(endpoint: str, ready) -> None:
    """Child process: answer every ping from Zenoh's callback thread."""
    from bench.bus.session import SessionOptions, open_session

    session = open_session(SessionOptions(connect=(endpoint,)))
    publisher = session.declare_publisher(PONG_KEY, **_publisher_options())
    subscriber = session.declare_subscriber(PING_KEY, lambda sample: publisher.put(sample.payload.to_bytes()))
    ready.set()
    try:
        time.sleep(3600)     # killed by the parent
    finally:
        subscriber.undeclare()
        session.close()


def loop_sized_payload() -> bytes:
    """An encoded estimate message as the estimator publishes it (the loop's middle hop)."""
    from bench.bus.schemas import TranslationEstimate, encode, header

    stamps = {stage: time.monotonic_ns() for stage in ("sensed", "estimator_received", "estimated")}
    hdr = header("rendezvous_lqr-20260101T000000-abcd", 123, 73800.0, **stamps)
    return encode(TranslationEstimate(hdr, [1234.5678901234] * 6, None, 0.0011596575, None, 0, False))


def raw_hop_us(samples: int) -> np.ndarray:
    """One-way Zenoh hop between two processes (round trip / 2), in microseconds."""
    import zenoh

    from bench.bus.session import SessionOptions, free_loopback_port, loopback_endpoint, open_session

    endpoint = loopback_endpoint(free_loopback_port())
    session = open_session(SessionOptions(listen=(endpoint,)))
    context = multiprocessing.get_context("spawn")
    ready = context.Event()
    child = context.Process(target=_pong, args=(endpoint, ready), daemon=True)
    child.start()
    try:
        pongs = session.declare_subscriber(PONG_KEY, zenoh.handlers.FifoChannel(16))
        ping = session.declare_publisher(PING_KEY, **_publisher_options())
        if not ready.wait(60.0):
            raise SystemExit("raw hop: the answering process did not start within 60 s")
        deadline = time.monotonic() + 10.0
        while not ping.matching_status.matching:
            if time.monotonic() > deadline:
                raise SystemExit("raw hop: the answering process never subscribed")
            time.sleep(0.01)
        payload = loop_sized_payload()
        warm_up = 100
        hops = np.empty(samples)
        for i in range(-warm_up, samples):
            started = time.perf_counter_ns()
            ping.put(payload)
            pongs.recv()
            if i >= 0:
                hops[i] = (time.perf_counter_ns() - started) / 2e3
        return hops
    finally:
        child.kill()
        child.join(5.0)
        session.close()


# ---- the multi-process loop -------------------------------------------------------------------
def multiprocess_run(steps: int, runs_dir: Path, run_id: str) -> dict:
    """Loop rate, hop latencies (us), sense-to-actuation latency (ms) and start-up (s) of one run."""
    started_wall = time.time()
    with np.load(bench_run(SCENARIO, steps, runs_dir, run_id) / "trajectory.npz") as data:
        stamps = {key[len("stamp_"):-len("_ns")]: data[key] for key in data.files if key.startswith("stamp_")}
    sensed, received = stamps["sensed"], stamps["plant_received"]
    loop_s = (received[-1] - sensed[0]) / 1e9   # first sample to last command: the loop itself
    hops_us = np.stack([(stamps[b] - stamps[a]) / 1e3 for a, b in HOPS])
    return {"rate_hz": steps / loop_s, "hops_us": hops_us, "latency_ms": (received - sensed) / 1e6,
            "startup_s": first_step_wall_s(runs_dir / run_id) - started_wall}


def percentiles(values: np.ndarray) -> dict[str, float]:
    return {f"p{q}": float(np.percentile(values, q)) for q in (50, 90, 99)} | {"max": float(np.max(values))}


def _pct_text(p: dict[str, float], unit: str, digits: int = 0) -> str:
    return f"p50 {p['p50']:.{digits}f} {unit}, p90 {p['p90']:.{digits}f} {unit}, p99 {p['p99']:.{digits}f} {unit}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--steps", type=int, default=2000, help="lock-step steps per run (default 2000)")
    parser.add_argument("--raw-samples", type=int, default=2000, help="raw ping-pongs per repeat (default 2000)")
    parser.add_argument("--attitude-steps", type=int, default=600, help="attitude_quick steps per run (default 600)")
    args = parser.parse_args()
    for name in ("repeats", "steps", "raw_samples", "attitude_steps"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1, got {getattr(args, name)}")
    load_before = os.getloadavg()[0]
    baseline, raw, runs, attitude_baseline, attitude_runs = [], [], [], [], []
    with tempfile.TemporaryDirectory(prefix="bench-loop-") as scratch:
        for i in range(args.repeats):
            baseline.append(in_process_rate_hz(SCENARIO, simulate_in_process, args.steps))
            print(f"repeat {i + 1}: in-process {baseline[-1]:8.0f} steps/s", file=sys.stderr)
            raw.append(raw_hop_us(args.raw_samples))
            print(f"repeat {i + 1}: raw hop {_pct_text(percentiles(raw[-1]), 'us', 1)}", file=sys.stderr)
            runs.append(multiprocess_run(args.steps, Path(scratch), f"bench-loop-{i}"))
            run = runs[-1]
            print(f"repeat {i + 1}: lock-step {run['rate_hz']:8.0f} cycles/s, hop in the loop "
                  f"{_pct_text(percentiles(run['hops_us'].ravel()), 'us', 1)}, start-up {run['startup_s']:.2f} s",
                  file=sys.stderr)
            attitude_baseline.append(in_process_rate_hz(ATTITUDE_SCENARIO, simulate_attitude_in_process, args.attitude_steps))
            attitude_runs.append(attitude_multiprocess_rate_hz(ATTITUDE_SCENARIO, args.attitude_steps, Path(scratch),
                                                               f"bench-loop-att-{i}"))
            print(f"repeat {i + 1}: attitude in-process {attitude_baseline[-1]:8.0f} steps/s, "
                  f"through the CAN nodes {attitude_runs[-1]:8.0f} steps/s", file=sys.stderr)
    load_after = os.getloadavg()[0]
    in_process = float(np.median(baseline))
    lockstep = float(np.median([r["rate_hz"] for r in runs]))
    raw_us = np.concatenate(raw)
    hop_us = np.concatenate([r["hops_us"] for r in runs], axis=1)
    latency_ms = np.concatenate([r["latency_ms"] for r in runs])
    raw_p, hop_p = percentiles(raw_us), percentiles(hop_us.ravel())
    result = {
        "scenario": SCENARIO, "steps": args.steps, "repeats": args.repeats, "cpus": os.cpu_count(),
        "load_average_1min": [load_before, load_after],
        "in_process_steps_per_s_median": in_process,
        "lockstep_cycles_per_s_median": lockstep,
        "lockstep_fraction_of_in_process": lockstep / in_process,
        "raw_hop_us": raw_p,
        "loop_hop_us": hop_p,
        "loop_hop_us_by_hop": {f"{a}->{b}": percentiles(hop_us[j]) for j, (a, b) in enumerate(HOPS)},
        "hop_ratio_p50": hop_p["p50"] / raw_p["p50"],
        "hop_ratio_p90": hop_p["p90"] / raw_p["p90"],
        "sense_to_actuation_ms": percentiles(latency_ms),
        "startup_to_first_step_s": percentiles(np.array([r["startup_s"] for r in runs])),
        "attitude_scenario": ATTITUDE_SCENARIO, "attitude_steps": args.attitude_steps,
        "attitude_in_process_steps_per_s_median": float(np.median(attitude_baseline)),
        "attitude_lockstep_steps_per_s_median": float(np.median(attitude_runs)),
    }
    result["attitude_lockstep_fraction_of_in_process"] = (result["attitude_lockstep_steps_per_s_median"]
                                                          / result["attitude_in_process_steps_per_s_median"])
    result["lockstep_limit_cycles_per_s"] = limit_hz(TRANSLATION_HOPS, raw_p["p50"], in_process)
    result["lockstep_fraction_of_limit"] = lockstep / result["lockstep_limit_cycles_per_s"]
    result["attitude_limit_steps_per_s"] = limit_hz(ATTITUDE_HOPS, raw_p["p50"],
                                                    result["attitude_in_process_steps_per_s_median"])
    result["attitude_fraction_of_limit"] = (result["attitude_lockstep_steps_per_s_median"]
                                            / result["attitude_limit_steps_per_s"])
    print(f"{SCENARIO}, {args.steps} steps, {args.repeats} repeats, {os.cpu_count()} CPUs, "
          f"load average (1 min) {load_before:.2f} before, {load_after:.2f} after")
    print(f"in-process simulation       : {in_process:9.0f} steps/s (baseline)")
    frac = result["lockstep_fraction_of_limit"]
    print(f"multi-process lock-step loop: {lockstep:9.0f} cycles/s ({lockstep / in_process:.2f}x in-process); its limit "
          f"{result['lockstep_limit_cycles_per_s']:.0f} cycles/s ({TRANSLATION_HOPS} raw hops + the in-process step): "
          f"{frac:.2f} of it (target >= {TARGET_TRANSLATION_LIMIT_FRACTION}: "
          f"{'met' if frac >= TARGET_TRANSLATION_LIMIT_FRACTION else 'NOT met'})")
    print(f"raw Zenoh hop, two processes: {_pct_text(raw_p, 'us', 1)}")
    print(f"hop inside the loop         : {_pct_text(hop_p, 'us', 1)} ({result['hop_ratio_p50']:.2f}x raw at p50, "
          f"{result['hop_ratio_p90']:.2f}x at p90; target <= {TARGET_HOP_RATIO}x: "
          f"{'met' if result['hop_ratio_p50'] <= TARGET_HOP_RATIO else 'NOT met'})")
    for (a, b), p in zip(HOPS, result["loop_hop_us_by_hop"].values()):
        print(f"  {a + ' -> ' + b:40s}: {_pct_text(p, 'us', 1)}")
    lat = result["sense_to_actuation_ms"]
    print(f"sense-to-actuation latency  : {_pct_text(lat, 'ms', 2)}, max {lat['max']:.2f} ms ({latency_ms.size} cycles)")
    start = result["startup_to_first_step_s"]
    print(f"bench run to first step     : p50 {start['p50']:.2f} s, max {start['max']:.2f} s")
    fraction = result["attitude_fraction_of_limit"]
    print(f"{ATTITUDE_SCENARIO}, {args.attitude_steps} steps: in process "
          f"{result['attitude_in_process_steps_per_s_median']:.0f} steps/s, through the CAN nodes "
          f"{result['attitude_lockstep_steps_per_s_median']:.0f} steps/s; its limit "
          f"{result['attitude_limit_steps_per_s']:.0f} steps/s ({ATTITUDE_HOPS} raw hops + the in-process step): "
          f"{fraction:.2f} of it (target >= {TARGET_ATTITUDE_LIMIT_FRACTION}: "
          f"{'met' if fraction >= TARGET_ATTITUDE_LIMIT_FRACTION else 'NOT met'})")
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
