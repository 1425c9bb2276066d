"""When a received CAN frame was on the wire, on this process's monotonic clock.

python-can stamps a received frame with the time it was on the wire: SocketCAN's kernel stamp,
the bench's Zenoh transport's stamp at its sender's send (bench/bus/can/zenoh_interface.py), both
on the wall clock. A node that judges another's timing from that stamp rather than from its own
arrival leaves out the time the frame spent in this host's queues and in its own receive thread
(what candump and a bus analyser show too). A stamp further before the arrival than
MAX_TRANSPORT_DELAY_NS, or after it, is some other clock's (a USB adapter's counter, another host):
the arrival is used then.
"""
from __future__ import annotations

import time

import can

MAX_TRANSPORT_DELAY_NS = 1_000_000_000


class WireClock:
    def __init__(self):
        self.wall_minus_monotonic_ns = time.time_ns() - time.monotonic_ns()

    def sent_ns(self, msg: can.Message, arrival_ns: int) -> int:
        """msg's time on the wire (monotonic ns), or arrival_ns if its stamp is not on this host's clock."""
        if msg.timestamp:
            sent_ns = round(msg.timestamp * 1e9) - self.wall_minus_monotonic_ns
            if 0 <= arrival_ns - sent_ns <= MAX_TRANSPORT_DELAY_NS:
                return sent_ns
        return arrival_ns
