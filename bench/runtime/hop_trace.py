"""Where a hop between two nodes spends its time, message by message: an instrument for
benchmarks/bench_hop_trace.py, off unless a node's environment sets BENCH_HOP_TRACE=1.

A hop is one message from the sender's `NodeContext.publish` to the receiving node's thread taking
it from its subscription queue. The trace stamps, on the one monotonic clock of the host:

- published: `publish` began (encoding), the payload was encoded and signed, Zenoh's `put` returned;
- received: Zenoh's callback began in the receiver, the MAC was checked and the message decoded,
  the message was in the node's queue;
- taken: the node's thread took it from the queue.

The message's topic and step (`header.seq`) pair a sender's row with the receiver's. Each node writes
its rows to `hop_trace_<node>.json` in the run directory at its end; the rows stay in memory
until then, so tracing is for benchmark runs of a few thousand steps, not for soaks.
"""
from __future__ import annotations

import json
import os
import queue
import time
from pathlib import Path

ENV = "BENCH_HOP_TRACE"
FILE_PATTERN = "hop_trace_{node}.json"


class HopTrace:
    def __init__(self):
        self.published: list[tuple[str, int, int, int, int]] = []   # topic, seq, start, signed, put returned
        self.received: list[tuple[str, int, int, int, int]] = []    # topic, seq, callback, decoded, queued
        self.taken: list[tuple[str, int, int]] = []                 # topic, seq, taken by the node's thread

    def write(self, run_dir: Path, node: str) -> None:
        rows = {"published": self.published, "received": self.received, "taken": self.taken}
        (Path(run_dir) / FILE_PATTERN.format(node=node)).write_text(json.dumps(rows))


def from_environment() -> HopTrace | None:
    return HopTrace() if os.environ.get(ENV) == "1" else None


class TracedQueue(queue.Queue):
    """A subscription queue that stamps when the node's thread takes each message."""

    def __init__(self, trace: HopTrace, topic: str):
        super().__init__()
        self._trace, self._topic = trace, topic

    def get(self, block=True, timeout=None):
        message = super().get(block, timeout)
        self._trace.taken.append((self._topic, message.header.seq, time.monotonic_ns()))
        return message
