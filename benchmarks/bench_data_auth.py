"""Cost of the data topics' MAC (bench/bus/data_auth.py) per message: sign (publisher) and verify
with the replay guard (subscriber), on payloads of the loop's real messages, encoded as the nodes
encode them. Pure CPU, no Zenoh: the cost a node pays per message on top of the transport.

    .venv/bin/python benchmarks/bench_data_auth.py [--messages 20000] [--rounds 5]
"""
from __future__ import annotations

import argparse
import statistics
import time

from bench.bus import data_auth, keys
from bench.bus.schemas import ThrustCommand, TranslationEstimate, encode, header


def _payloads() -> dict[str, bytes]:
    hdr = header("bench-run", 123, 73800.0, sensed=1, estimator_received=2, estimated=3,
                 controller_received=4, commanded=5)
    estimate = TranslationEstimate(hdr, [1e4, -2e3, 5e2, 1.0, -0.5, 0.1], [0.1] * 36, 0.0011, 3.2, 3, False)
    return {
        "command/thrust": encode(ThrustCommand(hdr, [0.1, -0.2, 0.3], True, "solved", 1e-4, 7)),
        "estimate/translation (with covariance)": encode(estimate),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--messages", type=int, default=20000)
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    key = data_auth.new_key()
    key_expr = keys.key("bench-run", keys.COMMAND_THRUST)
    for name, payload in _payloads().items():
        sign_us, verify_us = [], []
        for _ in range(args.rounds):
            signer, verifier = data_auth.Signer(key, "controller"), data_auth.Verifier(key)
            start = time.perf_counter()
            tags = [signer(key_expr, payload) for _ in range(args.messages)]
            sign_us.append((time.perf_counter() - start) / args.messages * 1e6)
            start = time.perf_counter()
            for tag in tags:
                if verifier.check(key_expr, payload, tag) is not None:
                    raise AssertionError("a genuine tag did not verify")
            verify_us.append((time.perf_counter() - start) / args.messages * 1e6)
        # The best round is the CPU cost; the median shows what a loaded machine adds.
        print(f"{name}: {len(payload)} B payload, {len(tags[0])} B attachment; per message: sign "
              f"{min(sign_us):.2f} us (median {statistics.median(sign_us):.2f}), verify {min(verify_us):.2f} us "
              f"(median {statistics.median(verify_us):.2f}); {args.rounds} rounds of {args.messages}")


if __name__ == "__main__":
    main()
