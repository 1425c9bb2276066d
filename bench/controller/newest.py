"""Real time: a controller (or the planner) acts on the newest estimate it has, as flight software does.

A host that holds the controller up (a loaded machine, a long solve) leaves estimates queued
behind the one in hand. Worked through in order, each would give a command from a state the
spacecraft has left: stale before it is sent, and the loop's sense -> actuation latency grows by
the backlog. So the estimates queued behind are passed over for the newest and counted
(`deadline_controller.json`: `stale_estimates_skipped`; the report's deadline table). Lock-step
pairs every plant step with its own command: there every estimate is used, in order
(bench/runtime/time_model.py).
"""
from __future__ import annotations

import queue

from bench.runtime.time_model import TimeModel


class NewestEstimate:
    def __init__(self, time_model: TimeModel):
        self.takes_every_estimate = time_model.takes_every_message
        self.skipped = 0

    def take(self, estimates: queue.Queue, first):
        """`first`, or in real time the newest estimate queued behind it (by header seq)."""
        if self.takes_every_estimate:
            return first
        newest = first
        while True:
            try:
                queued = estimates.get_nowait()
            except queue.Empty:
                return newest
            self.skipped += 1
            if queued.header.seq > newest.header.seq:
                newest = queued
