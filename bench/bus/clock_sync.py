"""Monotonic-clock offsets between bench processes, by ping-pong over Zenoh.

Header stamps are `time.monotonic_ns()` of the process that wrote them. On one host every process
shares the same monotonic clock; on several hosts they do not, and a latency across hosts is only
meaningful after the offset is removed. Each process answers presence queries (bench/bus/presence.py:
`bench/<run_id>/presence/<process>`, signed under the run's key) with its monotonic time; the asking process (the recorder, the reference clock) notes
when it sent the query (t0) and when the reply came back (t1):

    offset = t_remote - (t0 + t1) / 2,   uncertainty = (t1 - t0) / 2

The remote stamp was taken somewhere inside [t0, t1], so the true offset is within the
uncertainty. Of several rounds the one with the shortest round trip is kept (NTP's rule).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

from bench.bus.presence import PresenceQuery


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


def one_round(query: PresenceQuery) -> dict[str, ClockOffset]:
    """Ping every process once (one presence query: bench/bus/presence.py, so each reading is
    authenticated under the run's key) and compute each one's offset."""
    return {process: ClockOffset(process, answer.host,
                                 answer.monotonic_ns - (answer.sent_ns + answer.received_ns) // 2,
                                 (answer.received_ns - answer.sent_ns + 1) // 2)
            for process, answer in query.ask().items()}


def best_of(current: ClockOffset | None, new: ClockOffset) -> ClockOffset:
    """Keep the reading with the smaller uncertainty (the shorter round trip)."""
    rounds = (current.rounds if current else 0) + 1
    keep = new if current is None or new.uncertainty_ns < current.uncertainty_ns else current
    return ClockOffset(keep.process, keep.host, keep.offset_ns, keep.uncertainty_ns, rounds)


def estimate_offsets(query: PresenceQuery, rounds: int = 5,
                     known: dict[str, ClockOffset] | None = None) -> dict[str, ClockOffset]:
    """Offsets of every process answering on this run, best of `rounds` pings each."""
    offsets = dict(known or {})
    for _ in range(rounds):
        for process, reading in one_round(query).items():
            offsets[process] = best_of(offsets.get(process), reading)
    return offsets
