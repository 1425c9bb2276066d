"""This host's stalls, told apart from the board's faults in the board check.

The check judges the board's timing (its command timeout, the gaps in its heartbeat and
telemetry) on this host's clock, and on a loaded host three things other than the board can make
the board look late:
- the frame's delivery: the time a frame waits in this host's queues and in the check's receive
  thread. The check stamps what it hears with the frame's time on the wire instead
  (bench/bus/can/wire_time.py), so delivery is not the board's;
- the check itself: a command it stamped and then sent late starts the board's timeout late.
  `StallWatch`, a thread of the check's, wakes every TICK_S and notes each wake-up more than
  STALL_S late: the check's process was not run then;
- the board's process, when the board is the bench's own on this host: it notes its own periodic
  frames more than half a period late (bench/bus/can/host_lateness.py) in <run_dir>/can/board.json,
  which the check reads once the board has stopped.
A timed step that fails while the board went silent or the check stalled is repeated (the board
check's command timeout); a gap in the heartbeat or the telemetry that these records explain is
excused, counted and reported. A board that is late while it keeps sending on time, or silent
while no record says the host held it up, is judged as it is.
"""
from __future__ import annotations

import threading
import time
from pathlib import Path

from bench.bus.can.host_lateness import HostLate, HostLateLog, held_s, load_host_late_records

TICK_S = 0.005
STALL_S = 0.02


class StallWatch:
    """The check's own stalls: wake-ups of a thread of its process more than STALL_S late."""

    def __init__(self):
        self.log = HostLateLog()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="board-check-stalls", daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        due_s = time.monotonic() + TICK_S
        while not self._stop.wait(max(0.0, due_s - time.monotonic())):
            now_s = time.monotonic()
            if now_s - due_s > STALL_S:
                self.log.note(round(now_s * 1e9), now_s - due_s)
            due_s = now_s + TICK_S

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)

    def records(self) -> list[HostLate]:
        return [HostLate("check", t_ns, late_s) for t_ns, late_s in list(self.log.host_late_ns_s)]

    def longest_s(self, from_s: float, to_s: float) -> float:
        """The longest stall the check noted that overlaps [from_s, to_s]."""
        return max((late_s for t_ns, late_s in list(self.log.host_late_ns_s)
                    if t_ns / 1e9 - late_s <= to_s and t_ns / 1e9 >= from_s), default=0.0)


def silence_s(times_s: list[float], from_s: float, to_s: float) -> float:
    """The longest stretch of [from_s, to_s] with none of times_s in it."""
    edges = [from_s, *sorted(t for t in times_s if from_s < t < to_s), to_s]
    return max(b - a for a, b in zip(edges, edges[1:]))


def board_records(run_dir: Path) -> list[HostLate]:
    """What the bench's own board noted of its lateness in the check's run directory (nothing for
    a board that writes no <run_dir>/can/board.json: a user's)."""
    try:
        return [r for r in load_host_late_records(run_dir / "can") if r.node == "board"]
    except (OSError, ValueError, KeyError, TypeError):    # not the bench's board's report: nothing it says counts
        return []


def held_up_s(records: list[HostLate], from_s: float, to_s: float) -> float:
    """How long within [from_s, to_s] the records say the host held a process up."""
    return held_s(records, round(from_s * 1e9), round(to_s * 1e9))
