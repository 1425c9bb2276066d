"""Where a hop inside the loop spends its time above a raw Zenoh hop: the same ping-pong between
two processes, the answering side doing one more of the nodes' steps in each variant.

- raw: the answer is put from Zenoh's callback thread (benchmarks/bench_loop.py's raw hop);
- + hand-off: the callback queues the sample and the process's own thread answers, as a node's
  logic runs on its one thread (bench/runtime/node.py: `subscribe_queue`, a `queue.Queue`);
- + message work: the callback checks the MAC and decodes, the thread encodes and signs, as
  `NodeContext.subscribe` and `NodeContext.publish` do with the run's data key;
- + recorder: as the last, with a third process subscribed to both keys whose callback queues
  every sample for its own thread, as the recorder does; run with `--recorder-nice N` it also
  runs at that nice value.

Variants alternate within each repeat, so all see the same load; each variant's hop is round
trip / 2 of an estimate-sized message (the loop's middle hop), sessions from the project's factory.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_hop_parts.py [--repeats 3] [--samples 1500]
"""
from __future__ import annotations

import argparse
import multiprocessing
import os
import queue
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_loop import _publisher_options, loop_sized_payload  # noqa: E402

PING_KEY, PONG_KEY = "bench-hop/ping", "bench-hop/pong"
VARIANTS = ("raw", "+ hand-off", "+ message work", "+ recorder")
DATA_KEY = bytes(range(32))     # a run's data key stands in: the MAC costs the same


def _answer(endpoint: str, ready, variant: str) -> None:
    """The answering process of one variant; killed by the parent."""
    from bench.bus import data_auth
    from bench.bus.schemas import TranslationEstimate, decode, encode
    from bench.bus.session import SessionOptions, open_session

    session = open_session(SessionOptions(connect=(endpoint,)))
    publisher = session.declare_publisher(PONG_KEY, **_publisher_options())
    if variant == "raw":
        subscriber = session.declare_subscriber(PING_KEY, lambda sample: publisher.put(sample.payload.to_bytes()))
        ready.set()
        time.sleep(3600)
        subscriber.undeclare()
        return
    work = variant != "+ hand-off"
    signer, verifier = data_auth.Signer(DATA_KEY, "answer"), data_auth.Verifier(DATA_KEY)
    inbox: queue.Queue = queue.Queue()

    def on_sample(sample) -> None:
        data = sample.payload.to_bytes()
        if work:
            verifier.check(str(sample.key_expr), data, data_auth.attachment_bytes(sample))
            data = decode(data, TranslationEstimate)
        inbox.put(data)

    subscriber = session.declare_subscriber(PING_KEY, on_sample)
    ready.set()
    try:
        while True:
            item = inbox.get()
            if work:
                payload = encode(item)
                publisher.put(payload, attachment=signer(PONG_KEY, payload))
            else:
                publisher.put(item)
    finally:
        subscriber.undeclare()


def _record(endpoint: str, ready, nice: int) -> None:
    """A recorder stand-in: every sample of both keys queued for its own thread."""
    from bench.bus.session import SessionOptions, open_session

    if nice:
        os.nice(nice)      # before the session: Zenoh's threads inherit it
    session = open_session(SessionOptions(connect=(endpoint,)))
    samples: queue.SimpleQueue = queue.SimpleQueue()
    subscribers = [session.declare_subscriber(key, lambda sample: samples.put(sample.payload.to_bytes()))
                   for key in (PING_KEY, PONG_KEY)]
    ready.set()
    try:
        while True:
            samples.get()
    finally:
        for subscriber in subscribers:
            subscriber.undeclare()


def hop_us(variant: str, samples: int, recorder_nice: int, interval_s: float = 0.0) -> np.ndarray:
    import zenoh

    from bench.bus import data_auth
    from bench.bus.session import SessionOptions, free_loopback_port, loopback_endpoint, open_session

    endpoint = loopback_endpoint(free_loopback_port())
    session = open_session(SessionOptions(listen=(endpoint,)))
    context = multiprocessing.get_context("spawn")
    children = [(_answer, (variant,))] + ([(_record, (recorder_nice,))] if variant == "+ recorder" else [])
    processes = []
    try:
        for target, args in children:
            ready = context.Event()
            processes.append(context.Process(target=target, args=(endpoint, ready, *args), daemon=True))
            processes[-1].start()
            if not ready.wait(60.0):
                raise SystemExit(f"{variant}: a child process did not start within 60 s")
        pongs = session.declare_subscriber(PONG_KEY, zenoh.handlers.FifoChannel(16))
        ping = session.declare_publisher(PING_KEY, **_publisher_options())
        deadline = time.monotonic() + 10.0
        while not ping.matching_status.matching:
            if time.monotonic() > deadline:
                raise SystemExit(f"{variant}: the answering process never subscribed")
            time.sleep(0.01)
        time.sleep(0.3)     # the recorder's subscriptions too
        payload = loop_sized_payload()
        # The sender signs as a node publishes (raw and hand-off: no key, as a run without one).
        signer = data_auth.Signer(DATA_KEY, "ping") if variant in ("+ message work", "+ recorder") else None
        hops = np.empty(samples)
        for i in range(-100 if interval_s == 0 else -3, samples):
            if interval_s:
                time.sleep(interval_s)     # every process asleep in between, as in a paced loop
            started = time.perf_counter_ns()
            ping.put(payload, attachment=signer(PING_KEY, payload) if signer else None)
            pongs.recv()
            if i >= 0:
                hops[i] = (time.perf_counter_ns() - started) / 2e3
        return hops
    finally:
        for process in processes:
            process.kill()
            process.join(5.0)
        session.close()


def step_costs_us(n: int = 20000) -> dict[str, float]:
    """Each step of the message work alone, in a loop in this process (us per call)."""
    import timeit

    from bench.bus import data_auth
    from bench.bus.schemas import TranslationEstimate, decode, encode

    payload, key_expr = loop_sized_payload(), "bench/run/estimate/translation"
    signer, verifier = data_auth.Signer(DATA_KEY, "ping"), data_auth.Verifier(DATA_KEY)
    attachments = iter([signer(key_expr, payload) for _ in range(n)])
    message = decode(payload, TranslationEstimate)
    steps = {"sign": lambda: signer(key_expr, payload),
             "check the MAC": lambda: verifier.check(key_expr, payload, next(attachments)),
             "decode": lambda: decode(payload, TranslationEstimate), "encode": lambda: encode(message)}
    return {name: timeit.timeit(call, number=n) / n * 1e6 for name, call in steps.items()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--samples", type=int, default=1500, help="ping-pongs per variant and repeat")
    parser.add_argument("--recorder-nice", type=int, default=0, help="nice value of the recorder stand-in")
    parser.add_argument("--interval-s", type=float, default=0.0,
                        help="sleep between ping-pongs (0.1: the real-time attitude loop's tick), so that each hop "
                             "wakes idle processes; 0: back to back")
    args = parser.parse_args()
    print(f"1-min load average before: {os.getloadavg()[0]:.2f}")
    hops: dict[str, list[np.ndarray]] = {v: [] for v in VARIANTS}
    for _ in range(args.repeats):
        for variant in VARIANTS:
            hops[variant].append(hop_us(variant, args.samples, args.recorder_nice, args.interval_s))
    raw_p50 = float(np.median(np.concatenate(hops["raw"])))
    print(f"\none-way hop, {args.repeats} x {args.samples} ping-pongs per variant (recorder nice {args.recorder_nice}, "
          f"{args.interval_s:g} s between them)")
    print(f"{'variant':18s} {'p50 us':>8s} {'p90 us':>8s} {'p99 us':>8s} {'p50 / raw':>10s}")
    for variant in VARIANTS:
        values = np.concatenate(hops[variant])
        p50, p90, p99 = np.percentile(values, [50, 90, 99])
        print(f"{variant:18s} {p50:8.1f} {p90:8.1f} {p99:8.1f} {p50 / raw_p50:10.2f}")
    costs = step_costs_us()
    print("\nthe message work's steps alone: " + ", ".join(f"{k} {v:.1f} us" for k, v in costs.items()))
    print(f"\n1-min load average after: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
