"""What the CAN bus model's parts pass between them: the nodes of a bench bus, the channels of
the capture, a frame's attempt on the wire (InFlight: from its start of frame to its end or its
error frame), and a frame delivered to the nodes that hear it (Delivery).
"""
from __future__ import annotations

from dataclasses import dataclass

import can

from bench.bus.can import errors
from bench.bus.can.injector import Transmission

FLIGHT = "flight"
BOARD = "board"
NODES = (FLIGHT, BOARD)   # the nodes of a bench bus; BusModel(nodes=...) takes any number
CHANNEL_BUS, CHANNEL_DROPPED, CHANNEL_REPLACED = "bus", "dropped", "replaced"
CHANNEL_ERRORS = "errors"   # error reports to nodes other than the flight side (not on the wire)
RECESSIVE_RUN_BITS = 11                                   # ISO 11898-1: one occurrence for bus-off recovery


@dataclass(frozen=True)
class Delivery:
    msg: can.Message            # stamped with the wall time its last bit passed
    destinations: tuple[str, ...]


@dataclass
class InFlight:
    tx: Transmission | None     # None: a babbler frame
    msg: can.Message
    start_ns: int
    end_ns: int
    destroyed_by: object | None = None          # the error_frames fault that destroys it
    error: errors.BusError | None = None        # a bus error the bus itself causes (collision, no ACK)
    together: tuple[Transmission, ...] = ()     # other transmitters of the same frame (equal id, equal data)
    collided: tuple[Transmission, ...] = ()     # other transmitters in an equal-id collision
    # Error-passive transmitters that lost at a data bit: their error flag is recessive, the frame
    # goes on without them (ISO 11898-1); each has a bit error all the same.
    passive_losers: tuple[Transmission, ...] = ()
    # Recessive bits at the attempt's end (ACK delimiter, end of frame, intermission; or an error
    # delimiter and intermission): what a bus-off node counts towards its recovery.
    recessive_tail_bits: int = RECESSIVE_RUN_BITS


def stamped_frame(msg: can.Message, timestamp_s: float, channel: str) -> can.Message:
    return can.Message(timestamp=timestamp_s, arbitration_id=msg.arbitration_id, is_extended_id=msg.is_extended_id,
                       is_remote_frame=msg.is_remote_frame, is_error_frame=msg.is_error_frame, dlc=msg.dlc,
                       is_fd=msg.is_fd, data=bytes(msg.data), channel=channel, is_rx=False)

