"""Monotonic-clock offsets between bench processes, by ping-pong over Zenoh.

Header stamps are `time.monotonic_ns()` of the process that wrote them. On one host every process
shares the same monotonic clock; on several hosts they do not, and a latency across hosts is only
meaningful after the offset is removed. Each process answers queries on `bench/<run_id>/clock/
<process>` with its monotonic time; the asking process (the recorder, the reference clock) notes
when it sent the query (t0) and when the reply came back (t1):

    offset = t_remote - (t0 + t1) / 2,   uncertainty = (t1 - t0) / 2

The remote stamp was taken somewhere inside [t0, t1], so the true offset is within the
uncertainty. Of several rounds the one with the shortest round trip is kept (NTP's rule).
"""
from __future__ import annotations

import json
import socket
import threading
import time
from dataclasses import asdict, dataclass

import zenoh

from bench.bus import keys

CLOCK = "clock"     # bench/<run_id>/clock/<process>


@dataclass(frozen=True)
class ClockOffset:
    """remote monotonic ns minus reference monotonic ns, within +- uncertainty_ns."""

    process: str
    host: str
    offset_ns: int
    uncertainty_ns: int
    rounds: int = 1

    def to_dict(self) -> dict:
        return asdict(self)


def declare_clock_responder(session: zenoh.Session, run_id: str, process: str,
                            host: str | None = None) -> zenoh.Queryable:
    """Answer clock pings for `process`; keep the returned queryable alive as long as the node.

    host: the deployment's name of this host (default: the host name). Reports correct stamps of
    processes whose host differs from the recorder's (network namespaces share one host name).
    """
    host = host or socket.gethostname()
    key_expr = keys.key(run_id, f"{CLOCK}/{process}")

    def on_query(query: zenoh.Query) -> None:
        payload = json.dumps({"process": process, "host": host, "monotonic_ns": time.monotonic_ns()})
        query.reply(key_expr, payload)

    return session.declare_queryable(key_expr, on_query)


def _one_round(session: zenoh.Session, run_id: str, timeout_s: float) -> dict[str, ClockOffset]:
    """Ping every responder once (one wildcard query) and compute each one's offset."""
    found: dict[str, ClockOffset] = {}
    t0_ns = time.monotonic_ns()

    def on_reply(reply: zenoh.Reply) -> None:
        t1_ns = time.monotonic_ns()   # taken in the callback, before any queueing
        if reply.ok is None:
            return
        try:
            data = json.loads(reply.ok.payload.to_bytes())
            remote_ns, process, host = int(data["monotonic_ns"]), str(data["process"]), str(data["host"])
        except (ValueError, KeyError, TypeError):
            return   # a garbled reply is not a clock reading
        found[process] = ClockOffset(process, host, remote_ns - (t0_ns + t1_ns) // 2, (t1_ns - t0_ns + 1) // 2)

    done = threading.Event()
    # A Callback handler timestamps each reply as it lands; `drop` runs when the query is over
    # (every responder answered, or the timeout passed).
    session.get(keys.key(run_id, f"{CLOCK}/*"), zenoh.handlers.Callback(on_reply, done.set), timeout=timeout_s)
    done.wait(timeout_s + 1.0)
    return found


def best_of(current: ClockOffset | None, new: ClockOffset) -> ClockOffset:
    """Keep the reading with the smaller uncertainty (the shorter round trip)."""
    rounds = (current.rounds if current else 0) + 1
    keep = new if current is None or new.uncertainty_ns < current.uncertainty_ns else current
    return ClockOffset(keep.process, keep.host, keep.offset_ns, keep.uncertainty_ns, rounds)


def estimate_offsets(session: zenoh.Session, run_id: str, rounds: int = 5, timeout_s: float = 0.5,
                     known: dict[str, ClockOffset] | None = None) -> dict[str, ClockOffset]:
    """Offsets of every process answering on this run, best of `rounds` pings each."""
    offsets = dict(known or {})
    for _ in range(rounds):
        for process, reading in _one_round(session, run_id, timeout_s).items():
            offsets[process] = best_of(offsets.get(process), reading)
    return offsets
