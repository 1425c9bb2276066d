"""The magnetorquer protocol: frames of mtq.dbc through cantools, E2E protection, bad-frame counts.

The DBC is the single definition of the protocol; this module adds what a DBC cannot say:
- identifiers for a node id other than the DBC's 0x10 (CANopen: function code + node id);
- AUTOSAR E2E profile 2 on the protected frames: CRC-8 (poly 0x2F) in byte 0 over bytes 1..7 and
  the data id that the 4-bit alive counter selects from the frame's E2EDataIDList (a DBC
  attribute). The data id never travels on the bus, so a frame from a source configured for
  another data element fails the CRC even when its payload and counter look right;
- the receive-side check, AUTOSAR E2E_P02Check's state machine: repeated, out-of-sequence and
  corrupted frames are told apart and rejected, the tolerated counter jump grows by one at every
  check (so lost and corrupted frames widen it), a receiver that lost the sequence re-synchronises
  only after a configured number of valid frames in a row, and `reset` starts it again (the board
  calls it when its command timeout expires);
- the command profile: "e2e" (MTQ_CMD and plain NMT, classic CAN, integrity only: anyone on the
  bus can command the coils or stop the board) or "secoc" (the default: MTQ_CMD_AUTH, CAN FD, the
  same E2E plus a freshness value and a truncated CMAC, and NMT only as MTQ_NMT_AUTH, the same
  freshness value and CMAC on NMT's command; see secoc.py).

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

from bench.bus.can import secoc

DBC_PATH = Path(__file__).with_name("mtq.dbc")
DBC_NODE_ID = 0x10          # the node id the DBC's identifiers are written for
COUNTER_MODULO = 16         # E2E profile 2 alive counter: 4 bits
COUNTER_BITS = range(8, 12)  # its place in every protected frame (byte 1, low nibble)
E2E_PROTECTED_BYTES = 8      # profile 2 protects the first 8 bytes (the authentic PDU of MTQ_CMD_AUTH)

CMD = "MTQ_CMD"
CMD_AUTH = "MTQ_CMD_AUTH"
COMMANDS = (CMD, CMD_AUTH)
PROFILES = {"e2e": CMD, "secoc": CMD_AUTH}   # command profile -> the command frame it uses
TLM_DIPOLE = "MTQ_TLM_DIPOLE"
TLM_COIL = "MTQ_TLM_COIL"
TLM_SETPOINT = "MTQ_TLM_SETPOINT"   # command acknowledgement: the coil drivers' set-point (BoardConfig.setpoint_echo)
HEARTBEAT = "MTQ_HEARTBEAT"
EMCY = "MTQ_EMCY"
NMT = "NMT"                  # CiA 301 module control: identifier 0 whatever the node id
NMT_AUTH = "MTQ_NMT_AUTH"    # the same, authenticated (secoc profile): RPDO3 0x400 + node id
NMT_FRAMES = {"e2e": NMT, "secoc": NMT_AUTH}   # command profile -> the NMT frame the board obeys
SECURED = (CMD_AUTH, NMT_AUTH)   # frames that carry a freshness value and a MAC
BOARD_FRAMES = (TLM_DIPOLE, TLM_COIL, TLM_SETPOINT, HEARTBEAT, EMCY)
AXES = ("X", "Y", "Z")

MODE_OFF = 0
MODE_DIPOLE = 1

# CANopen NMT states carried by the heartbeat.
NMT_BOOT_UP = 0x00
NMT_STOPPED = 0x04
NMT_OPERATIONAL = 0x05
NMT_PRE_OPERATIONAL = 0x7F
NMT_STATES = {NMT_BOOT_UP, NMT_STOPPED, NMT_OPERATIONAL, NMT_PRE_OPERATIONAL}
# NMT command specifiers (CiA 301 7.2.8.3.1).
NMT_START = 0x01
NMT_STOP = 0x02
NMT_ENTER_PRE_OPERATIONAL = 0x80
NMT_RESET_NODE = 0x81
NMT_RESET_COMMUNICATION = 0x82
NMT_COMMANDS = {NMT_START, NMT_STOP, NMT_ENTER_PRE_OPERATIONAL, NMT_RESET_NODE, NMT_RESET_COMMUNICATION}

# CANopen emergency error codes the board uses (CiA 301 table 21).
EMCY_NO_ERROR = 0x0000          # error reset
EMCY_COMMAND_TIMEOUT = 0x8250   # RPDO timeout: no valid command within the command timeout
EMCY_E2E_CHECK_FAILED = 0x8100  # communication, generic (E2eStatus says what: E2E, SecOC, lost)
EMCY_PDO_LENGTH = 0x8210        # PDO not processed due to length error


class E2EStatus(enum.IntEnum):
    """Receive-side verdict on a protected frame; it travels in MTQ_EMCY.E2eStatus.

    0-7 are E2E_P02Check's statuses; 8-10 are the board's SecOC verdicts on MTQ_CMD_AUTH.
    """
    OK = 0
    WRONG_CRC = 1
    REPEATED = 2
    WRONG_SEQUENCE = 3
    OK_SOME_LOST = 4
    INITIAL = 5
    SYNC = 6              # valid, but the receiver is re-synchronising: not used
    NO_NEW_DATA = 7
    WRONG_MAC = 8
    STALE = 9             # authentic but too old (or not newer than the last accepted)
    NOT_AUTHENTICATED = 10  # a plain MTQ_CMD where the profile wants MTQ_CMD_AUTH

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
    """Write the profile-2 CRC into byte 0 (over bytes 1..7 and the data id); the counter must
    already be in byte 1's low nibble. Bytes beyond the 8th (SecOC's) are left as they are."""
    head = bytes(payload[:E2E_PROTECTED_BYTES])
    return bytes(apply_profile2_crc(head, data_ids[head[1] & 0x0F])) + bytes(payload[E2E_PROTECTED_BYTES:])


def e2e_crc_ok(payload: bytes, data_ids: tuple[int, ...]) -> bool:
    head = bytes(payload[:E2E_PROTECTED_BYTES])
    return bool(check_profile2_crc(head, data_ids[head[1] & 0x0F]))


# The DBC's GenMsgSendType as a transmission mode (AUTOSAR COM): periodic only, on change only,
# or mixed (on change, and periodically as a keep-alive).
TRANSMISSION_MODES = {"Cyclic": "cyclic", "Spontaneous": "on_change", "CyclicAndSpontaneous": "mixed"}


def cycle_time_s(name: str) -> float | None:
    """The DBC's GenMsgCycleTime of a cyclic (or mixed) frame in seconds (None for a spontaneous one)."""
    message = database().get_message_by_name(name)
    if transmission_mode(name) == "on_change" or not message.cycle_time:
        return None
    return message.cycle_time / 1000.0


def transmission_mode(name: str) -> str:
    """"cyclic", "on_change" or "mixed", from the frame's GenMsgSendType."""
    return TRANSMISSION_MODES.get(database().get_message_by_name(name).send_type, "on_change")


def secoc_data_id(name: str) -> int | None:
    attribute = database().get_message_by_name(name).dbc.attributes.get("SecOCDataId")
    return int(attribute.value) if attribute is not None and attribute.value else None


class E2EReceiver:
    """AUTOSAR E2E_P02Check: the receive-side state of one protected data element.

    Called once per received frame (`check`) and once per expected period in which none came
    (`no_new_data`). Every call widens the tolerated counter jump by one, up to 15, so that frames
    lost or corrupted in a row are tolerated by the next valid one (after two CRC failures the
    next valid frame, its counter 3 ahead, is OK_SOME_LOST, not WRONG_SEQUENCE); an accepted frame
    narrows it back to `max_delta_counter` (MaxDeltaCounterInit).

    A jump beyond the tolerance is WRONG_SEQUENCE: the receiver takes the new counter as its
    reference but reports the next `sync_counter` valid frames as SYNC (not to be used), so one
    forged or stray frame cannot steer the stream. More than `max_no_new_or_repeated` periods
    without new data also costs a re-synchronisation. `reset` forgets the stream (the next valid
    frame is INITIAL); the board calls it when its command timeout expires.
    """

    def __init__(self, max_delta_counter: int = 1, sync_counter: int = 2, max_no_new_or_repeated: int = 14):
        if not 1 <= max_delta_counter < COUNTER_MODULO:
            raise ValueError(f"max_delta_counter {max_delta_counter} must be in [1, {COUNTER_MODULO - 1}]")
        if not 0 <= sync_counter < COUNTER_MODULO or not 0 <= max_no_new_or_repeated <= 14:
            raise ValueError("sync_counter must be in [0, 15] and max_no_new_or_repeated in [0, 14]")
        self.max_delta_counter_init = max_delta_counter
        self.sync_counter_init = sync_counter
        self.max_no_new_or_repeated = max_no_new_or_repeated
        self.reset()

    def reset(self) -> None:
        self.wait_for_first_data = True
        self.last_counter: int | None = None
        self.max_delta_counter = self.max_delta_counter_init
        self.sync_counter = 0
        self.no_new_or_repeated = 0
        self.lost_data = 0

    def _widen(self) -> None:
        self.max_delta_counter = min(self.max_delta_counter + 1, COUNTER_MODULO - 1)

    def no_new_data(self) -> E2EStatus:
        self._widen()
        self.no_new_or_repeated = min(self.no_new_or_repeated + 1, 14)
        return E2EStatus.NO_NEW_DATA

    def check(self, counter: int, crc_ok: bool) -> E2EStatus:
        self._widen()
        if not crc_ok:
            return E2EStatus.WRONG_CRC
        if self.wait_for_first_data:
            self.wait_for_first_data = False
            self.max_delta_counter = self.max_delta_counter_init
            self.last_counter = counter
            return E2EStatus.INITIAL
        delta = (counter - self.last_counter) % COUNTER_MODULO
        if delta == 0:
            self.no_new_or_repeated = min(self.no_new_or_repeated + 1, 14)
            return E2EStatus.REPEATED
        if delta <= self.max_delta_counter:
            self.max_delta_counter = self.max_delta_counter_init
            self.last_counter = counter
            self.lost_data = delta - 1
            if self.no_new_or_repeated > self.max_no_new_or_repeated:
                self.sync_counter = self.sync_counter_init
            self.no_new_or_repeated = 0
            if self.sync_counter > 0:
                self.sync_counter -= 1
                return E2EStatus.SYNC
            return E2EStatus.OK if delta == 1 else E2EStatus.OK_SOME_LOST
        self.no_new_or_repeated = 0
        self.sync_counter = self.sync_counter_init
        if self.sync_counter > 0:
            self.max_delta_counter = self.max_delta_counter_init
            self.last_counter = counter
        return E2EStatus.WRONG_SEQUENCE


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
    """Encoding and decoding of the magnetorquer frames for one node id and command profile.

    `key` (16 bytes) is the SecOC key: needed to send MTQ_CMD_AUTH; without it (a spoofer, a
    sniffer) frames decode but cannot be authenticated.
    """

    def __init__(self, node_id: int = DBC_NODE_ID, profile: str = "e2e", key: bytes | None = None):
        if not 1 <= node_id <= 0x7F:
            raise ValueError(f"CANopen node id {node_id} must be in [1, 127]")
        if profile not in PROFILES:
            raise ValueError(f"command profile {profile!r} is not one of {', '.join(PROFILES)}")
        self.node_id = node_id
        self.profile = profile
        self.command_name = PROFILES[profile]
        self.key = key
        self.db = database()
        offset = node_id - DBC_NODE_ID
        self.frame_ids = {m.name: m.frame_id + (offset if m.name != NMT else 0) for m in self.db.messages}
        self._by_id = {frame_id: self.db.get_message_by_name(name) for name, frame_id in self.frame_ids.items()}
        self.data_ids = {m.name: data_id_list(m.name) for m in self.db.messages}
        self.bad = BadFrames()

    def resolve(self, name: str) -> str:
        """A frame name, with MTQ_CMD meaning "the command frame of this profile"."""
        return self.command_name if name == CMD else name

    # --- building frames ------------------------------------------------------------------
    def encode(self, name: str, signals: dict, counter: int | None = None, freshness: int | None = None) -> can.Message:
        """A frame with the given signal values (physical units); protected frames get counter and
        CRC, MTQ_CMD_AUTH also its freshness value (10 us ticks) and MAC (needs the key).

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
        secured = name in SECURED
        if secured:
            if freshness is None or self.key is None:
                raise ValueError(f"{name} is authenticated: give its freshness value, and the key to the Protocol")
            values["Mac"] = 0
        payload = message.encode(values, scaling=True, strict=True)
        if data_ids is not None:
            payload = e2e_protect(payload, data_ids)
        if secured:
            payload = secoc.secure(self.key, secoc_data_id(name), payload, freshness)
        return can.Message(arbitration_id=self.frame_ids[name], is_extended_id=False, data=payload,
                           is_fd=message.is_fd)

    def command(self, dipole_am2, counter: int, mode: int = MODE_DIPOLE, *, sent_s: float | None = None) -> can.Message:
        """The profile's command frame; `sent_s` (sender clock, s) is its freshness for "secoc"."""
        signals = {"Mode": mode, **{f"Dipole{a}": float(v) for a, v in zip(AXES, dipole_am2)}}
        freshness = secoc.freshness_ticks(sent_s) if sent_s is not None else None
        return self.encode(self.command_name, signals, counter, freshness)

    def nmt(self, command: int, node_id: int | None = None, *, sent_s: float | None = None) -> can.Message:
        """The profile's NMT frame: plain NMT on "e2e", MTQ_NMT_AUTH on "secoc" (`sent_s`, the
        sender's clock in s, is its freshness value). node_id defaults to this protocol's; 0 is
        every node (plain NMT only: the authenticated frame is addressed by its identifier)."""
        name = NMT_FRAMES[self.profile]
        signals = {"Command": command, "NodeId": self.node_id if node_id is None else node_id}
        if name == NMT_AUTH:
            if sent_s is None:
                raise ValueError(f"{name} is authenticated: give the time it is sent (sent_s)")
            return self.encode(name, signals, freshness=secoc.freshness_ticks(sent_s))
        return self.encode(name, signals)

    def reprotect(self, msg: can.Message, *, data_ids: tuple[int, ...] | None = None) -> can.Message:
        """The same frame with its CRC recomputed (fault injection: a frame that passes E2E; the
        MAC of a secured frame is left as it was, so that frame no longer authenticates)."""
        name = self._by_id[msg.arbitration_id].name
        payload = e2e_protect(bytes(msg.data), data_ids or self.data_ids[name])
        return can.Message(arbitration_id=msg.arbitration_id, is_extended_id=False, data=payload, is_fd=msg.is_fd)

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
        if message is None or msg.is_extended_id:
            self.bad.count("unknown_id")
            return None
        if msg.is_remote_frame:
            self.bad.count("remote_request")   # CiA 301: RPDOs and these TPDOs are not RTR-served
            return None
        if msg.is_fd != message.is_fd:
            self.bad.count("wrong_format")
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
        if message.name in (NMT, NMT_AUTH) and signals["Command"] not in NMT_COMMANDS:
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
