"""The CAN nodes on a simulated clock, in one process: each node's end of the bus model.

The board, the driver and the bus model take a clock and a bus; here the clock is simulated time
(ns) that the caller advances, and a node's bus hands frames to `BusModel.submit` at that time and
reads what the model delivered to its inbox. Every frame then takes its exact bit time, queue and
arbitration, and the result does not depend on the host (fault campaigns, tests).
"""
from __future__ import annotations

from collections import deque

import can

from bench.bus.can.busmodel import BusModel


class SimClock:
    """Simulated time in ns; called, it gives seconds (the nodes' clock interface)."""

    def __init__(self, t_ns: int):
        self.t_ns = t_ns

    def __call__(self) -> float:
        return self.t_ns / 1e9


class SimBus:
    """One node's end of the bus model: the calls the board and the driver make."""

    def __init__(self, model: BusModel, side: str, clock: SimClock):
        self.model, self.side, self.clock = model, side, clock
        self.inbox: deque[can.Message] = deque()

    def send(self, msg: can.Message, timeout=None) -> None:
        self.model.submit(self.side, msg, self.clock.t_ns)

    def recv(self, timeout=0.0):
        return self.inbox.popleft() if self.inbox else None

    def shutdown(self) -> None:
        pass
