"""Where each hop of the lock-step translational loop spends its time, beside a raw Zenoh hop.

Each repeat measures a raw hop (benchmarks/bench_loop.py: two processes, ping-pong, one hop =
round trip / 2) and then runs `bench run rendezvous_lqr --steps N` with BENCH_HOP_TRACE=1, so every
node stamps each message through its stages (bench/runtime/hop_trace.py). Per hop of the loop
(plant -> estimator, estimator -> controller, controller -> plant) it prints the p50 of:

- encode + sign: the sender encodes the message and computes its MAC;
- put: Zenoh's `put` call in the sender;
- Zenoh: from the start of `put` to the start of the receiver's callback (Zenoh's transmit and
  receive threads, the loopback socket, and whatever else the two cores run meanwhile);
- check + decode: the receiver's callback checks the MAC and decodes;
- hand-off: into the node's queue and until the node's thread takes it;
- hop: from the start of encoding to the node's thread taking it (the sum).

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_hop_trace.py [--repeats 3] [--steps 2000]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_loop import CHECKOUT, raw_hop_us  # noqa: E402

from bench.bus import keys  # noqa: E402
from bench.runtime.hop_trace import ENV, FILE_PATTERN  # noqa: E402

HOPS = (("plant", keys.TRUTH, "estimator"), ("estimator", keys.ESTIMATE_TRANSLATION, "controller"),
        ("controller", keys.COMMAND_THRUST, "plant"))
PARTS = ("encode + sign", "put", "Zenoh", "check + decode", "hand-off", "hop")
WARM_UP_STEPS = 50


def traced_run(steps: int, runs_dir: Path, run_id: str) -> Path:
    cmd = [sys.executable, "-m", "bench.cli", "run", "rendezvous_lqr", "--steps", str(steps), "--run-id", run_id,
           "--runs-dir", str(runs_dir), "--no-progress", "--no-report"]
    result = subprocess.run(cmd, cwd=CHECKOUT, capture_output=True, text=True, env=os.environ | {ENV: "1"})
    if result.returncode != 0:
        raise SystemExit(f"bench run exited with {result.returncode}:\n{result.stderr[-2000:]}")
    return runs_dir / run_id


def hop_parts_us(run_dir: Path) -> dict[str, dict[str, np.ndarray]]:
    """Hop name -> part -> microseconds per message (steps after the warm-up, in both traces)."""
    traces = {node: json.loads((run_dir / FILE_PATTERN.format(node=node)).read_text())
              for node in ("plant", "estimator", "controller")}
    out = {}
    for sender, topic, receiver in HOPS:
        published = {row[1]: row[2:] for row in traces[sender]["published"] if row[0] == topic}
        received = {row[1]: row[2:] for row in traces[receiver]["received"] if row[0] == topic}
        taken = {row[1]: row[2] for row in traces[receiver]["taken"] if row[0] == topic}
        steps = sorted(k for k in set(published) & set(received) & set(taken) if k >= WARM_UP_STEPS)
        p = np.array([published[k] for k in steps], dtype=np.int64)    # start, signed, put returned
        r = np.array([received[k] for k in steps], dtype=np.int64)     # callback, decoded, queued
        t = np.array([taken[k] for k in steps], dtype=np.int64)
        out[f"{sender} -> {receiver}"] = {
            "encode + sign": (p[:, 1] - p[:, 0]) / 1e3, "put": (p[:, 2] - p[:, 1]) / 1e3,
            "Zenoh": (r[:, 0] - p[:, 1]) / 1e3, "check + decode": (r[:, 1] - r[:, 0]) / 1e3,
            "hand-off": (t - r[:, 1]) / 1e3, "hop": (t - p[:, 0]) / 1e3}
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--steps", type=int, default=2000)
    args = parser.parse_args()
    if args.repeats < 1 or args.steps <= WARM_UP_STEPS:
        parser.error(f"--repeats at least 1, --steps more than {WARM_UP_STEPS}")
    load_before = os.getloadavg()[0]
    raw: list[np.ndarray] = []
    parts: dict[str, dict[str, list[np.ndarray]]] = {}
    with tempfile.TemporaryDirectory() as runs:
        for repeat in range(args.repeats):
            raw.append(raw_hop_us(2000))
            for hop, values in hop_parts_us(traced_run(args.steps, Path(runs), f"trace{repeat}")).items():
                for part, v in values.items():
                    parts.setdefault(hop, {}).setdefault(part, []).append(v)
    raw_p50 = float(np.median(np.concatenate(raw)))
    print(f"rendezvous_lqr, {args.steps} steps x {args.repeats} repeats; 1-min load average {load_before:.2f} before, "
          f"{os.getloadavg()[0]:.2f} after")
    print(f"raw Zenoh hop (two processes, ping-pong): p50 {raw_p50:.1f} us\n")
    print(f"{'hop (p50, us)':28s}" + "".join(f"{part:>16s}" for part in PARTS) + f"{'hop / raw':>11s}")
    summary = {"raw_hop_p50_us": raw_p50, "hops": {}}
    for hop, values in parts.items():
        p50 = {part: float(np.median(np.concatenate(values[part]))) for part in PARTS}
        summary["hops"][hop] = p50
        print(f"{hop:28s}" + "".join(f"{p50[part]:16.1f}" for part in PARTS) + f"{p50['hop'] / raw_p50:11.2f}")
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
