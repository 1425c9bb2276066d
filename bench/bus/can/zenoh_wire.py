"""How one CAN frame is laid out in a Zenoh payload for the `zenoh` python-can interface.

A fixed little-endian header followed by the data bytes. The sender id and per-sender sequence
number let a receiver drop its own frames (a CAN controller does not receive what it sent unless
asked) and notice frames Zenoh did not deliver. Decoding validates everything through
`can.Message(check=True)`, so a payload that is not a valid CAN frame raises MalformedFrame and
never produces a half-built message.
"""
from __future__ import annotations

import struct

import can

WIRE_VERSION = 1
# version, flags, dlc, data length, arbitration id, timestamp [s], sender id, sequence number
_HEADER = struct.Struct("<BBBBIdQI")
HEADER_SIZE_BYTES = _HEADER.size
MAX_DATA_BYTES = 64  # CAN FD

_EXTENDED = 0x01
_ERROR = 0x02
_REMOTE = 0x04
_FD = 0x08
_BRS = 0x10
_ESI = 0x20
_KNOWN_FLAGS = _EXTENDED | _ERROR | _REMOTE | _FD | _BRS | _ESI


class MalformedFrame(ValueError):
    """A payload on a CAN key expression that is not a frame of this wire format."""


def encode(msg: can.Message, *, timestamp_s: float, sender_id: int, sequence: int) -> bytes:
    """Bytes for one frame; raises ValueError naming the problem if `msg` is not a valid frame.

    python-can builds messages unchecked by default, so the check happens here, before anything
    reaches the bus: a bad frame is the sender's error, not every receiver's.
    """
    data = bytes(msg.data or b"")
    dlc = len(data) if msg.dlc is None else msg.dlc
    can.Message(
        arbitration_id=msg.arbitration_id, is_extended_id=msg.is_extended_id,
        is_remote_frame=msg.is_remote_frame, is_error_frame=msg.is_error_frame, dlc=dlc,
        data=data, is_fd=msg.is_fd, bitrate_switch=msg.bitrate_switch,
        error_state_indicator=msg.error_state_indicator, check=True,
    )
    flags = (
        (_EXTENDED if msg.is_extended_id else 0) | (_ERROR if msg.is_error_frame else 0)
        | (_REMOTE if msg.is_remote_frame else 0) | (_FD if msg.is_fd else 0)
        | (_BRS if msg.bitrate_switch else 0) | (_ESI if msg.error_state_indicator else 0)
    )
    header = _HEADER.pack(WIRE_VERSION, flags, dlc, len(data), msg.arbitration_id, timestamp_s,
                          sender_id, sequence & 0xFFFFFFFF)
    return header + data


def decode(payload: bytes, channel: str) -> tuple[can.Message, int, int]:
    """(message, sender id, sequence number) from a payload; raises MalformedFrame otherwise."""
    if len(payload) < HEADER_SIZE_BYTES:
        raise MalformedFrame(f"{len(payload)} bytes is shorter than the {HEADER_SIZE_BYTES}-byte header")
    version, flags, dlc, data_len, arbitration_id, timestamp_s, sender_id, sequence = (
        _HEADER.unpack_from(payload)
    )
    if version != WIRE_VERSION:
        raise MalformedFrame(f"wire version {version}, expected {WIRE_VERSION}")
    if flags & ~_KNOWN_FLAGS:
        raise MalformedFrame(f"unknown flag bits 0x{flags & ~_KNOWN_FLAGS:02x}")
    if len(payload) != HEADER_SIZE_BYTES + data_len or data_len > MAX_DATA_BYTES:
        raise MalformedFrame(
            f"payload of {len(payload)} bytes does not hold the {data_len} data bytes its header announces"
        )
    try:
        msg = can.Message(
            timestamp=timestamp_s, arbitration_id=arbitration_id,
            is_extended_id=bool(flags & _EXTENDED), is_error_frame=bool(flags & _ERROR),
            is_remote_frame=bool(flags & _REMOTE), is_fd=bool(flags & _FD),
            bitrate_switch=bool(flags & _BRS), error_state_indicator=bool(flags & _ESI),
            dlc=dlc, data=payload[HEADER_SIZE_BYTES:], channel=channel, is_rx=True, check=True,
        )
    except (ValueError, TypeError) as exc:
        raise MalformedFrame(str(exc)) from exc
    return msg, sender_id, sequence
