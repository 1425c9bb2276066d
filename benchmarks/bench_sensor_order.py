"""Does Zenoh keep one publisher's order across topics? The attitude plant publishes a tick's
sense/mag and sense/star before its sense/gyro; the estimator closes the tick on the gyro.

Counts, over N ticks on loopback, the magnetometer and star-tracker samples delivered after their
tick's gyro sample: with three subscribers (one per topic) and with one subscriber on `sense/*`.

    PYTHONPATH=$PWD python benchmarks/bench_sensor_order.py [N]
"""
from __future__ import annotations

import sys
import threading
import time

import zenoh

from bench.bus.session import SessionOptions, free_loopback_port, loopback_endpoint, open_session

TOPICS = ("mag", "star", "gyro")    # publishing order within a tick


def out_of_order(wildcard: bool, n_ticks: int) -> int:
    endpoint = loopback_endpoint(free_loopback_port())
    publisher = open_session(SessionOptions(listen=(endpoint,)))
    subscriber = open_session(SessionOptions(connect=(endpoint,)))
    seen: list[tuple[str, int]] = []
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            seen.append((str(sample.key_expr).rsplit("/", 1)[1], int(sample.payload.to_bytes())))

    try:
        keep = ([subscriber.declare_subscriber("order/sense/*", on_sample)] if wildcard
                else [subscriber.declare_subscriber(f"order/sense/{t}", on_sample) for t in TOPICS])
        pubs = {t: publisher.declare_publisher(f"order/sense/{t}", congestion_control=zenoh.CongestionControl.BLOCK,
                                               reliability=zenoh.Reliability.RELIABLE) for t in TOPICS}
        time.sleep(1.0)
        for k in range(n_ticks):
            for t in TOPICS:
                pubs[t].put(str(k))
            time.sleep(0.0005)
        deadline = time.monotonic() + 10.0
        while len(seen) < 3 * n_ticks and time.monotonic() < deadline:
            time.sleep(0.05)
        closed, late = -1, 0
        for topic, k in seen:
            if topic == "gyro":
                closed = k
            elif k <= closed:
                late += 1
        del keep
        return late
    finally:
        subscriber.close()
        publisher.close()


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 2000
    for wildcard in (False, True):
        late = out_of_order(wildcard, n)
        print(f"{'one subscriber on sense/*' if wildcard else 'three subscribers':28s} "
              f"{late:5d} of {2 * n} mag/star samples after their tick's gyro")


if __name__ == "__main__":
    main()
