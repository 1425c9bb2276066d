"""The board check's contract and its flight side: the numbers a magnetorquer board is judged
against (the scenario's [can] section), and the check's end of the board's bus, which sends the
frames of mtq.dbc through bench.bus.can.protocol (genuine commands, NMT, and the probes the board
must refuse) and records every frame it hears on the check's clock (CLOCK_MONOTONIC) and writes it
to the capture (candump format).
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path

import can
import numpy as np

from bench.bus.can import protocol as p
from bench.bus.can import secoc
from bench.bus.can.config import CanConfig
from bench.bus.can.wire_time import WireClock
from bench.runtime.priority import set_realtime_priority

NMT_NAMES = {p.NMT_BOOT_UP: "boot-up", p.NMT_STOPPED: "stopped", p.NMT_OPERATIONAL: "operational",
             p.NMT_PRE_OPERATIONAL: "pre-operational"}
TELEMETRY = (p.TLM_DIPOLE, p.TLM_COIL)
PROTECTED = (p.TLM_DIPOLE, p.TLM_COIL, p.TLM_SETPOINT)


def state_name(state: int | None) -> str:
    return NMT_NAMES.get(state, f"state {state:#04x}" if state is not None else "none")


def fmt(v) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in np.asarray(v, float)) + "]"


def ms(seconds: float | None) -> str:
    return "-" if seconds is None else f"{seconds * 1e3:.1f} ms"


# --- the contract -----------------------------------------------------------------------------
@dataclass(frozen=True)
class BoardContract:
    """The numbers the board is judged against (the scenario's [can] section)."""
    profile: str
    node_id: int
    heartbeat_period_s: float
    heartbeat_timeout_s: float        # the flight side's consumer time: a board this late is lost
    telemetry_period_s: float
    telemetry_timeout_s: float
    command_period_s: float
    command_timeout_s: float
    max_dipole_am2: float
    dipole_resolution_am2: float
    dipole_tolerance_am2: float
    coil_time_constant_s: float
    freshness_max_age_s: float
    emcy_inhibit_s: float
    margin_s: float
    setpoint_echo: bool               # required: lock-step pairs each command with its echo

    @classmethod
    def of(cls, config: CanConfig, margin_s: float, tolerance_am2: float | None, real_time_only: bool) -> "BoardContract":
        b, d = config.board, config.driver
        return cls(profile=config.security.profile, node_id=config.node_id,
                   heartbeat_period_s=b.heartbeat_period_s,
                   heartbeat_timeout_s=b.heartbeat_period_s * d.heartbeat_timeout_periods,
                   telemetry_period_s=b.telemetry_period_s,
                   telemetry_timeout_s=b.telemetry_period_s * d.telemetry_timeout_periods,
                   command_period_s=d.command_period_s, command_timeout_s=b.command_timeout_s,
                   max_dipole_am2=b.max_dipole_am2, dipole_resolution_am2=b.dipole_resolution_am2,
                   dipole_tolerance_am2=tolerance_am2 if tolerance_am2 is not None else d.dipole_tolerance_am2,
                   coil_time_constant_s=b.coil_time_constant_s,
                   freshness_max_age_s=d.command_period_s + config.security.freshness_margin_s,
                   emcy_inhibit_s=b.emcy_inhibit_s, margin_s=margin_s, setpoint_echo=not real_time_only)

    def setpoint(self, wire_am2: np.ndarray, mode: int) -> tuple[np.ndarray, bool]:
        """What the coil drivers must be set to for a command as it travels (the DBC's 1e-4 A m^2):
        Mode off is zero; else each axis quantised to the DAC step, then saturated at the limit;
        True when an axis saturated."""
        if mode != p.MODE_DIPOLE:
            return np.zeros(3), False
        quantised = np.round(wire_am2 / self.dipole_resolution_am2) * self.dipole_resolution_am2
        limited = np.clip(quantised, -self.max_dipole_am2, self.max_dipole_am2)
        return limited, bool(np.any(limited != quantised))

    @property
    def settle_s(self) -> float:
        """After a new set-point, when the coils' current has followed it (five time constants),
        with a command period for the frame to arrive."""
        return 5 * self.coil_time_constant_s + self.command_period_s


# --- the flight side ----------------------------------------------------------------------------
@dataclass
class Heard:
    t_s: float                 # on the wire, on the check's clock (its arrival if its stamp is another clock's)
    name: str | None           # DBC name; None: not a frame of the protocol
    signals: dict
    counter: int | None
    crc_ok: bool | None


@dataclass
class Sent:
    t_s: float
    kind: str                  # "command" (genuine), a probe's name, "nmt", "pre-operational command"
    counter: int | None = None
    expected_am2: np.ndarray | None = None   # the set-point it asks for (genuine commands)
    saturated: bool = False
    judged: bool = False       # a genuine command the board must apply and acknowledge


class FlightSide:
    """The check's end of the board's bus: sends through the protocol, hears on its own thread."""

    def __init__(self, bus: can.BusABC, contract: BoardContract, key: bytes | None, capture: Path,
                 priority: int = 0):
        self.bus = bus
        self.contract = contract
        self.key = key
        self.protocol = p.Protocol(contract.node_id, contract.profile, key)
        self.reader = p.Protocol(contract.node_id, contract.profile, key)    # the listener's own (its counts)
        self.plain = p.Protocol(contract.node_id, "e2e")                     # unauthenticated frames (probes)
        self.counter = 0
        self.max_gap_s = 0.0       # the longest the check itself went between two commands of a stretch
        self.sent: list[Sent] = []
        self.heard: list[Heard] = []
        self.unknown = 0
        self.stamped_on_arrival = 0   # frames whose stamp was not on this host's clock: timed on arrival
        self._wire_clock = WireClock()
        self._lock = threading.Lock()
        self._capture = can.Logger(str(capture))
        self._stop = threading.Event()
        self._priority = priority
        self._thread = threading.Thread(target=self._listen, name="board-check-listen", daemon=True)
        self._thread.start()

    def _listen(self) -> None:
        if self._priority:
            set_realtime_priority(self._priority)
        while not self._stop.is_set():
            try:
                msg = self.bus.recv(timeout=0.05)
            except can.CanError:
                return
            if msg is None:
                continue
            arrival_ns = time.monotonic_ns()
            on_wire_ns = self._wire_clock.sent_ns(msg, arrival_ns)
            frame = self.reader.decode(msg)
            with self._lock:
                self.stamped_on_arrival += on_wire_ns == arrival_ns
                self._capture.on_message_received(msg)
                if frame is None:
                    self.unknown += 1
                    continue
                self.heard.append(Heard(on_wire_ns / 1e9, frame.name, frame.signals, frame.counter, frame.crc_ok))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        with self._lock:
            self._capture.stop()

    # --- sending ------------------------------------------------------------------------
    def send(self, msg: can.Message, sent: Sent) -> Sent:
        sent.t_s = time.monotonic()
        self.bus.send(msg)
        with self._lock:
            msg.timestamp = time.time()
            msg.is_rx = False
            self._capture.on_message_received(msg)
            self.sent.append(sent)
        return sent

    def _expected(self, msg: can.Message, mode: int) -> tuple[np.ndarray, bool]:
        frame = self.protocol.decode(msg)
        return self.contract.setpoint(np.array([frame.signals[f"Dipole{a}"] for a in p.AXES]), mode)

    def command(self, dipole_am2, mode: int = p.MODE_DIPOLE, judged: bool = True, kind: str = "command") -> Sent:
        """One genuine command with the next alive counter (and now's freshness)."""
        counter = self.counter
        msg = self.protocol.command(dipole_am2, counter, mode, sent_s=self._fresh_s())
        expected, saturated = self._expected(msg, mode)
        self.counter = (counter + 1) % p.COUNTER_MODULO
        return self.send(msg, Sent(0.0, kind, counter, expected, saturated, judged))

    def _fresh_s(self) -> float | None:
        return time.monotonic() if self.contract.profile == "secoc" else None

    def nmt(self, command: int) -> Sent:
        msg = self.protocol.nmt(command, sent_s=time.monotonic() if self.contract.profile == "secoc" else None)
        return self.send(msg, Sent(0.0, "nmt"))

    def probe(self, kind: str, dipole_am2) -> Sent:
        """A frame the board must refuse, carrying `dipole_am2`."""
        counter, auth = self.counter, self.contract.profile == "secoc"
        if kind == "bad-crc":
            msg = self.protocol.command(dipole_am2, counter, sent_s=self._fresh_s())
            data = bytearray(msg.data)
            data[0] ^= 0x5A                   # the CRC byte
            if auth:                          # an authentic sender with a broken E2E layer: the MAC over it
                freshness = secoc.freshness_ticks(time.monotonic())
                data = bytearray(secoc.secure(self.key, p.secoc_data_id(p.CMD_AUTH), bytes(data), freshness))
            msg = _with_data(msg, data)
        elif kind == "repeated-counter":      # the last command's alive counter again, otherwise valid
            counter = (counter - 1) % p.COUNTER_MODULO
            msg = self.protocol.command(dipole_am2, counter, sent_s=self._fresh_s())
        elif kind == "bad-mac":
            msg = self.protocol.command(dipole_am2, counter, sent_s=self._fresh_s())
            data = bytearray(msg.data)
            data[secoc.MAC_OFFSET] ^= 0x01
            msg = _with_data(msg, data)
        elif kind == "old-freshness":         # authentic, but sent ten freshness windows ago
            msg = self.protocol.command(dipole_am2, counter,
                                        sent_s=time.monotonic() - 10 * self.contract.freshness_max_age_s)
        elif kind == "plain-command":         # MTQ_CMD, valid E2E, no MAC: a downgrade
            msg = self.plain.command(dipole_am2, counter)
        elif kind == "plain-nmt-stop":        # NMT stop (identifier 0) without a MAC
            msg, counter = self.plain.nmt(p.NMT_STOP), None
        else:
            raise ValueError(kind)
        return self.send(msg, Sent(0.0, kind, counter))

    def command_for(self, duration_s: float, dipole_am2, mode: int = p.MODE_DIPOLE, judged: bool = True) -> float:
        """Command every command period for duration_s (the first at once); returns the last send time."""
        period = self.contract.command_period_s
        end_s = time.monotonic() + duration_s
        next_s = last_s = time.monotonic()
        previous_s = None
        while (now := time.monotonic()) < end_s:
            if now >= next_s:
                last_s = self.command(dipole_am2, mode, judged).t_s
                if previous_s is not None:
                    self.max_gap_s = max(self.max_gap_s, last_s - previous_s)
                previous_s = last_s
                next_s += period
                if next_s <= now:            # held up: no burst to catch up
                    next_s = now + period
            time.sleep(max(0.0, min(next_s, end_s) - time.monotonic()))
        return last_s

    # --- hearing -------------------------------------------------------------------------
    def frames(self, names=None, after_s: float = 0.0, before_s: float = float("inf")) -> list[Heard]:
        if isinstance(names, str):
            names = (names,)
        with self._lock:
            return [h for h in self.heard if after_s <= h.t_s < before_s and (names is None or h.name in names)]

    def wait_for(self, names, after_s: float, within_s: float, test=lambda h: True) -> Heard | None:
        """The first frame of `names` heard after after_s that passes `test`, waiting until
        after_s + within_s at most."""
        deadline = after_s + within_s
        while True:
            found = next((h for h in self.frames(names, after_s, deadline) if test(h)), None)
            if found is not None or time.monotonic() >= deadline:
                return found
            time.sleep(0.002)

    def state_at(self, t_s: float) -> int | None:
        beats = self.frames(p.HEARTBEAT, 0.0, t_s)
        return int(beats[-1].signals["NmtState"]) if beats else None


def _with_data(msg: can.Message, data) -> can.Message:
    return can.Message(arbitration_id=msg.arbitration_id, is_extended_id=False, data=bytes(data), is_fd=msg.is_fd)


def sleep_until(t_s: float) -> None:
    time.sleep(max(0.0, t_s - time.monotonic()))


def applied_am2(h: Heard) -> np.ndarray:
    return np.array([h.signals[f"AppliedDipole{a}"] for a in p.AXES])


def echoed_am2(h: Heard) -> np.ndarray:
    return np.array([h.signals[f"Setpoint{a}"] for a in p.AXES])

