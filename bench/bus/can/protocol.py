"""The magnetorquer protocol: frames of mtq.dbc through cantools, E2E protection, bad-frame counts.

The DBC is the single definition of the protocol; this module adds what a DBC cannot say:
- identifiers for a node id other than the DBC's 0x10 (CANopen: function code + node id);
- AUTOSAR E2E profile 2 on the protected frames: CRC-8 (poly 0x2F) in byte 0 over bytes 1..7 and
  the data id that the 4-bit alive counter selects from the frame's E2EDataIDList (a DBC
  attribute). The data id never travels on the bus, so a frame from a source configured for
  another data element fails the CRC even when its payload and counter look right;
- the receive-side check (E2E_P02Check without its sync phase): repeated, out-of-sequence and
  corrupted frames are told apart and rejected.

Nothing here raises on a bad frame from the bus: `decode` returns None and counts why.
"""
from __future__ import annotations

import enum
from collections import Counter
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import can
import cantools
from cantools.autosar.end_to_end import apply_profile2_crc, check_profile2_crc

DBC_PATH = Path(__file__).with_name("mtq.dbc")
DBC_NODE_ID = 0x10          # the node id the DBC's identifiers are written for
COUNTER_MODULO = 16         # E2E profile 2 alive counter: 4 bits
COUNTER_BITS = range(8, 12)  # its place in every protected frame (byte 1, low nibble)

CMD = "MTQ_CMD"
TLM_DIPOLE = "MTQ_TLM_DIPOLE"
TLM_COIL = "MTQ_TLM_COIL"
HEARTBEAT = "MTQ_HEARTBEAT"
EMCY = "MTQ_EMCY"
BOARD_FRAMES = (TLM_DIPOLE, TLM_COIL, HEARTBEAT, EMCY)
AXES = ("X", "Y", "Z")

MODE_OFF = 0
MODE_DIPOLE = 1

# CANopen NMT states carried by the heartbeat.
NMT_BOOT_UP = 0x00
NMT_STOPPED = 0x04
NMT_OPERATIONAL = 0x05
NMT_PRE_OPERATIONAL = 0x7F
NMT_STATES = {NMT_BOOT_UP, NMT_STOPPED, NMT_OPERATIONAL, NMT_PRE_OPERATIONAL}

# CANopen emergency error codes the board uses (CiA 301 table 21).
EMCY_NO_ERROR = 0x0000
EMCY_COMMAND_TIMEOUT = 0x8130   # life guard / heartbeat error: the master went quiet
EMCY_E2E_CHECK_FAILED = 0x8100  # communication, generic
EMCY_PDO_LENGTH = 0x8210        # PDO not processed due to length error


class E2EStatus(enum.IntEnum):
    """Receive-side verdict on a protected frame (values 1-3 travel in MTQ_EMCY.E2eStatus)."""
    OK = 0
    WRONG_CRC = 1
    REPEATED = 2
    WRONG_SEQUENCE = 3
    OK_SOME_LOST = 4
    INITIAL = 5

    @property
    def accepted(self) -> bool:
        return self in (E2EStatus.OK, E2EStatus.OK_SOME_LOST, E2EStatus.INITIAL)


@lru_cache(maxsize=1)
def database() -> cantools.database.can.Database:
    return cantools.database.load_file(str(DBC_PATH))


def data_id_list(name: str) -> tuple[int, ...] | None:
    """The E2E data ids of a protected frame, indexed by alive counter; None if unprotected."""
    attribute = database().get_message_by_name(name).dbc.attributes.get("E2EDataIDList")
    if attribute is None or not attribute.value:
        return None
    ids = tuple(int(text, 0) for text in attribute.value.split(","))
    if len(ids) != COUNTER_MODULO:
        raise ValueError(f"{name}: E2EDataIDList needs {COUNTER_MODULO} data ids, has {len(ids)}")
    return ids


def e2e_protect(payload: bytes, data_ids: tuple[int, ...]) -> bytes:
    """Write the profile-2 CRC into byte 0; the counter must already be in byte 1's low nibble."""
    return bytes(apply_profile2_crc(payload, data_ids[payload[1] & 0x0F]))


def e2e_crc_ok(payload: bytes, data_ids: tuple[int, ...]) -> bool:
    return bool(check_profile2_crc(payload, data_ids[payload[1] & 0x0F]))


class E2EReceiver:
    """State of one protected data element at its receiver (AUTOSAR E2E_P02Check, simplified).

    max_delta_counter: how far the counter may jump and the frame still count, i.e. how many
    frames in a row may be lost. A frame further ahead is WRONG_SEQUENCE: rejected, but the
    receiver resynchronises on it so that one glitch costs one frame, not the stream.
    """

    def __init__(self, max_delta_counter: int = 2):
        if not 1 <= max_delta_counter < COUNTER_MODULO:
            raise ValueError(f"max_delta_counter {max_delta_counter} must be in [1, {COUNTER_MODULO - 1}]")
        self.max_delta_counter = max_delta_counter
        self.last_counter: int | None = None

    def check(self, counter: int, crc_ok: bool) -> E2EStatus:
        if not crc_ok:
            return E2EStatus.WRONG_CRC
        if self.last_counter is None:
            self.last_counter = counter
            return E2EStatus.INITIAL
        delta = (counter - self.last_counter) % COUNTER_MODULO
        if delta == 0:
            return E2EStatus.REPEATED
        self.last_counter = counter
        if delta > self.max_delta_counter:
            return E2EStatus.WRONG_SEQUENCE
        return E2EStatus.OK if delta == 1 else E2EStatus.OK_SOME_LOST


@dataclass(frozen=True)
class Frame:
    """A decoded frame of the protocol. `crc_ok` is None for unprotected frames."""
    name: str
    signals: dict
    counter: int | None
    crc_ok: bool | None
    timestamp_s: float


@dataclass
class BadFrames:
    """Frames that are not the protocol, by reason; counted and ignored, never raised."""
    counts: Counter = field(default_factory=Counter)

    def count(self, reason: str) -> None:
        self.counts[reason] += 1

    @property
    def total(self) -> int:
        return sum(self.counts.values())


class Protocol:
    """Encoding and decoding of the magnetorquer frames for one node id."""

    def __init__(self, node_id: int = DBC_NODE_ID):
        if not 1 <= node_id <= 0x7F:
            raise ValueError(f"CANopen node id {node_id} must be in [1, 127]")
        self.node_id = node_id
        self.db = database()
        offset = node_id - DBC_NODE_ID
        self.frame_ids = {m.name: m.frame_id + offset for m in self.db.messages}
        self._by_id = {frame_id: self.db.get_message_by_name(name) for name, frame_id in self.frame_ids.items()}
        self.data_ids = {m.name: data_id_list(m.name) for m in self.db.messages}
        self.bad = BadFrames()

    # --- building frames ------------------------------------------------------------------
    def encode(self, name: str, signals: dict, counter: int | None = None) -> can.Message:
        """A frame with the given signal values (physical units); protected frames get counter and CRC.

        Values beyond a signal's DBC range are clamped to it: a command can saturate, never wrap.
        """
        message = self.db.get_message_by_name(name)
        values = {s.name: _clamp(signals.get(s.name, 0), s) for s in message.signals}
        data_ids = self.data_ids[name]
        if data_ids is not None:
            if counter is None:
                raise ValueError(f"{name} is E2E protected: give its alive counter")
            values["AliveCounter"] = counter % COUNTER_MODULO
            values["Crc"] = 0
        payload = message.encode(values, scaling=True, strict=True)
        if data_ids is not None:
            payload = e2e_protect(payload, data_ids)
        return can.Message(arbitration_id=self.frame_ids[name], is_extended_id=False, data=payload)

    def command(self, dipole_am2, counter: int, mode: int = MODE_DIPOLE) -> can.Message:
        signals = {"Mode": mode, **{f"Dipole{a}": float(v) for a, v in zip(AXES, dipole_am2)}}
        return self.encode(CMD, signals, counter)

    def reprotect(self, msg: can.Message, *, data_ids: tuple[int, ...] | None = None) -> can.Message:
        """The same frame with its CRC recomputed (fault injection: a frame that passes E2E)."""
        name = self._by_id[msg.arbitration_id].name
        payload = e2e_protect(bytes(msg.data), data_ids or self.data_ids[name])
        return can.Message(arbitration_id=msg.arbitration_id, is_extended_id=False, data=payload)

    # --- reading frames -------------------------------------------------------------------
    def name_of(self, frame_id: int) -> str | None:
        message = self._by_id.get(frame_id)
        return message.name if message is not None else None

    def decode(self, msg: can.Message) -> Frame | None:
        """The frame's signals, or None (counted in `bad`) if it is not a frame of this protocol."""
        if msg.is_error_frame:
            self.bad.count("error_frame")
            return None
        message = self._by_id.get(msg.arbitration_id)
        if message is None or msg.is_extended_id or msg.is_remote_frame or msg.is_fd:
            self.bad.count("unknown_id")
            return None
        if len(msg.data) != message.length:
            self.bad.count("wrong_length")
            return None
        try:
            signals = message.decode(bytes(msg.data), decode_choices=False, scaling=True)
        except Exception:  # cantools raises several types on garbage; none may escape
            self.bad.count("garbage")
            return None
        if message.name == HEARTBEAT and signals["NmtState"] not in NMT_STATES:
            self.bad.count("garbage")
            return None
        data_ids = self.data_ids[message.name]
        counter = crc_ok = None
        if data_ids is not None:
            counter = int(signals["AliveCounter"])
            crc_ok = e2e_crc_ok(bytes(msg.data), data_ids)
        return Frame(message.name, signals, counter, crc_ok, msg.timestamp)


def frame_kind(protocol: Protocol, msg: can.Message) -> str:
    """A frame's name for counting: its DBC name, "error_frame", or its identifier in hex."""
    if msg.is_error_frame:
        return "error_frame"
    return protocol.name_of(msg.arbitration_id) or hex(msg.arbitration_id)


def _clamp(value, signal) -> float:
    low = signal.minimum if signal.minimum is not None else float("-inf")
    high = signal.maximum if signal.maximum is not None else float("inf")
    return min(max(value, low), high)
