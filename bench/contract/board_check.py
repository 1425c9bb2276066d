"""`bench contract check board`: accept a magnetorquer board from outside, on its CAN bus, as a
flight-software team accepts a board another team delivers.

The check is the flight side on the board's channel and nothing else: it sends the frames of
mtq.dbc (through bench.bus.can.protocol, i.e. cantools and the DBC, with the E2E CRC and alive
counter, and on the `secoc` profile the freshness value and CMAC under the board's key), listens
to what the board sends, and judges it against the contract's numbers: the board configuration of
the scenario (`[can.board]`, `[can.driver]`, `[can.security]`; the bench's defaults unless a
scenario is given). The board is the bench's own (`bench node mtq`), started by `--command` and
connected to the hub the check opens, or a user's, started by `--command` or already running, on a
python-can channel the user names.

In order, each step measured on the check's clock (CLOCK_MONOTONIC, the SecOC time base too):
1. boot: the boot-up message (CiA 301: a heartbeat carrying state 0) at start, then heartbeats in
   pre-operational; no telemetry while pre-operational; a command sent then is not applied.
2. NMT start (MTQ_NMT_AUTH on secoc, plain NMT on e2e) takes it to operational: the next heartbeat
   says so, telemetry starts, the coils off (the pre-operational command was not applied).
3. commands applied, one every command period, held in turn: a dipole, one between DAC steps
   (quantised), one beyond the limit (saturated, the Saturated flag), one with Mode off (zero), a
   steady one: the telemetry's applied dipole within tolerance, the set-point echo exact.
4. refusals, while the steady dipole goes on: a command with a wrong CRC (an authentic MAC over
   it on secoc), one repeating the last alive counter, and on secoc one with a wrong MAC, one with
   an old freshness value, a plain MTQ_CMD and a plain NMT stop; each carries another dipole, and
   is judged refused if the coils do not move (echo, telemetry, heartbeat) and an EMCY 0x8100 with
   its E2E status comes.
5. command timeout: the check stops sending; the command-timeout EMCY (0x8250) within the timeout
   plus the margin, the telemetry's coils off, the echo of the safe state; then commands again:
   the error-reset EMCY (0x0000).
6. NMT enter pre-operational and stop: the heartbeat says so, telemetry stops (only heartbeats
   while stopped), and after the next NMT start the coils are off; NMT reset node: boot-up again.
Throughout: the heartbeat period (median) and its longest gap, the telemetry period, the E2E
check of every protected frame the board sends, each applied command acknowledged by
MTQ_TLM_SETPOINT with its alive counter (what lock-step pairs by; `--real-time-only` for a board
without it), and no EMCY for a genuine command. On secoc a genuine frame the board refused as
stale is the board's fault only if its refusal (or the next answer) came back within the freshness
window; later than that, this host may have held it up (bench/contract/late_arrivals.py): the
frame is excused and counted (an NMT frame is sent again), and more than a tenth of the commands
so excused is a problem of its own (the host too busy to judge).

It prints one line on a pass, or FAIL and each problem, and writes the verdict with the contract's
numbers and the measured ones to <run_dir>/contract_check.json; every frame sent and heard goes to
<run_dir>/can.log (candump format), the board's output (if the check started it) to
<run_dir>/logs/outside.log.
"""
from __future__ import annotations

import json
import shlex
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import can
import msgspec
import numpy as np

from bench.bus import data_auth, keys
from bench.bus.can import protocol as p
from bench.bus.can import run_key, secoc
from bench.bus.can.config import BusSpec, CanConfig
from bench.bus.can.transport import TransportUnavailable, open_bus
from bench.bus.schemas import SCHEMA_VERSION
from bench.bus.session import SessionOptions, free_loopback_port, loopback_endpoint, open_session
from bench.contract.check import OUTSIDE_LOG, Verdict
from bench.contract.late_arrivals import explained_emcys, may_have_arrived_stale
from bench.runtime.priority import set_realtime_priority
from bench.scenario import Scenario, ScenarioError, load_scenario, parse_scenario

STARTUP_TIMEOUT_S = 60.0      # until the board's first heartbeat (a node's start on a loaded host)
DEFAULT_MARGIN_S = 0.03       # beyond a period or a timeout, for the board's reaction and the bus
HOLD_S = 0.25                 # each commanded dipole is held this long
PROBE_LEAD_S = 0.1            # steady commands before each refused frame
EXIT_TIMEOUT_S = 10.0
LATE_NMT_RETRIES = 2          # an NMT frame refused only because this host delivered it stale: sent again
LATE_SHARE_LIMIT = 0.1        # more genuine commands than this share late on arrival: the host is too busy to judge
CAPTURE_NAME = "can.log"
VERDICT_NAME = "contract_check.json"
# The default contract: the bench's board with its set-point echo, which lock-step needs.
DEFAULT_SCENARIO = {"name": "board_contract", "run": {"seed": 1}, "can": {"board": {"setpoint_echo": True}}}

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
    t_s: float                 # arrival on the check's clock
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
            t_s = time.monotonic()
            frame = self.reader.decode(msg)
            with self._lock:
                self._capture.on_message_received(msg)
                if frame is None:
                    self.unknown += 1
                    continue
                self.heard.append(Heard(t_s, frame.name, frame.signals, frame.counter, frame.crc_ok))

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


# --- the check ----------------------------------------------------------------------------------
@dataclass
class BoardCheck:
    flight: FlightSide
    contract: BoardContract
    started_by_check: bool
    process: subprocess.Popen | None = None
    log_path: str = OUTSIDE_LOG          # where the board's command writes its output
    problems: list[str] = field(default_factory=list)
    measured: dict = field(default_factory=dict)
    probe_windows: list[tuple[float, float]] = field(default_factory=list)   # EMCYs expected in these
    timeout_window: tuple[float, float] | None = None                        # the command timeout's
    echo_free: list[tuple[float, float]] = field(default_factory=list)      # no echo expected here
    late: list[Sent] = field(default_factory=list)   # genuine frames this host may have delivered stale

    def problem(self, text: str) -> None:
        self.problems.append(text)

    # --- steps ---------------------------------------------------------------------------
    def run(self, startup_timeout_s: float, t_started_s: float) -> None:
        if not self.boot(startup_timeout_s, t_started_s):
            return
        if not self.start_operational("NMT start"):
            return
        self.commands()
        self.refusals()
        self.command_timeout()
        self.nmt_states()
        self.reset_node()
        self.throughout()

    def boot(self, startup_timeout_s: float, t_started_s: float) -> bool:
        c, f = self.contract, self.flight
        first = None
        deadline = time.monotonic() + startup_timeout_s
        while first is None and time.monotonic() < deadline:
            first = f.wait_for(p.HEARTBEAT, t_started_s, min(deadline, time.monotonic() + 0.2) - t_started_s)
            if first is None and self.process is not None and self.process.poll() is not None:
                self.problem(f"the board's command exited with code {self.process.returncode} before its first "
                             f"heartbeat (its output: {self.log_path})")
                return False
        if first is None:
            self.problem(f"no heartbeat from the board (node id {c.node_id:#04x}, MTQ_HEARTBEAT "
                         f"{f.protocol.frame_ids[p.HEARTBEAT]:#05x}) within {startup_timeout_s:g} s")
            return False
        state = int(first.signals["NmtState"])
        boot = {"first_heartbeat_state": state_name(state), "first_heartbeat_after_s": round(first.t_s - t_started_s, 3)}
        self.measured["boot"] = boot
        booted_s = first.t_s
        if state != p.NMT_BOOT_UP:
            if self.started_by_check:
                self.problem(f"boot-up: no boot-up message at start (CiA 301: a heartbeat with state 0 first); the "
                             f"first heartbeat said {state_name(state)}")
            if state != p.NMT_PRE_OPERATIONAL:        # already running: boot it to a known state
                boot["reset_node_at_start"] = True
                if not self.reset_node(at_start=True):
                    return False
                booted_s = time.monotonic()      # after its pre-operational heartbeat: frames from before are gone
        after = f.frames(p.HEARTBEAT)[-1].t_s
        # Pre-operational, as it comes up: heartbeats only, and a command is not applied.
        sleep_until(after + 0.5 * c.heartbeat_period_s)
        f.command([0.5 * c.max_dipole_am2] * 3, judged=False, kind="pre-operational command")
        sleep_until(after + 4.5 * c.heartbeat_period_s)
        states = [int(h.signals["NmtState"]) for h in f.frames(p.HEARTBEAT, after + 1e-9)]
        wrong = sorted({state_name(s) for s in states if s != p.NMT_PRE_OPERATIONAL})
        if wrong:
            self.problem(f"boot: heartbeats said {', '.join(wrong)} before any NMT command (CiA 301: pre-operational "
                         f"after boot-up)")
        early = f.frames(PROTECTED, booted_s)
        if early:
            self.problem(f"boot: {len(early)} telemetry frame(s) while pre-operational ({early[0].name} first; "
                         f"PDOs only when operational)")
        boot["pre_operational_heartbeats"] = len(states)
        return True

    def start_operational(self, what: str) -> bool:
        """NMT start; the heartbeat says operational, telemetry starts, coils off. False if it did not."""
        c, f = self.contract, self.flight
        sent, beat = self.nmt(p.NMT_START, p.NMT_OPERATIONAL, 3 * c.heartbeat_period_s + c.margin_s)
        bound = c.heartbeat_period_s + c.margin_s
        tlm = f.wait_for(p.TLM_DIPOLE, sent.t_s, c.telemetry_period_s + c.margin_s + c.heartbeat_period_s)
        entry = {"operational_heartbeat_after_s": _after(beat, sent), "first_telemetry_after_s": _after(tlm, sent)}
        self.measured.setdefault("nmt", {}).setdefault(what, []).append(entry)
        if beat is None:
            self.problem(f"{what}: no heartbeat saying operational within {ms(3 * c.heartbeat_period_s + c.margin_s)} "
                         f"(it said {state_name(f.state_at(time.monotonic()))})")
            return False
        if beat.t_s - sent.t_s > bound:
            self.problem(f"{what}: operational heartbeat {ms(beat.t_s - sent.t_s)} after the NMT start, over one "
                         f"heartbeat period + margin ({ms(bound)})")
        if tlm is None:
            self.problem(f"{what}: no telemetry (MTQ_TLM_DIPOLE) within {ms(c.telemetry_period_s + c.margin_s)} of "
                         f"becoming operational")
        elif not tlm.signals["SafeState"] or np.max(np.abs(applied_am2(tlm))) > c.dipole_tolerance_am2:
            self.problem(f"{what}: coils not off when it became operational (SafeState {tlm.signals['SafeState']}, "
                         f"applied {fmt(applied_am2(tlm))} A m^2): a command it had while not operational was applied "
                         f"or kept")
        return True

    def commands(self) -> None:
        """Dipoles held in turn; the telemetry follows within tolerance, the echo is exact."""
        c, f = self.contract, self.flight
        m, r = c.max_dipole_am2, c.dipole_resolution_am2
        holds = [
            ("dipole", [0.5 * m, -0.25 * m, 0.1 * m], p.MODE_DIPOLE),
            ("quantised", [r * (round(0.2 * m / r) + 0.4), -r * (round(0.4 * m / r) + 0.3), r * 3.4], p.MODE_DIPOLE),
            ("saturated", [1.75 * m, -2.5 * m, 0.5 * m], p.MODE_DIPOLE),
            ("mode off", [0.5 * m, 0.5 * m, 0.5 * m], p.MODE_OFF),
            ("steady", STEADY(m), p.MODE_DIPOLE),
        ]
        results = []
        for name, dipole, mode in holds:
            start = time.monotonic()
            f.command_for(HOLD_S, dipole, mode)
            end = time.monotonic()
            sent = [s for s in f.sent if s.kind == "command" and start <= s.t_s < end]
            expected, saturated = sent[-1].expected_am2, sent[-1].saturated
            settled = f.frames(p.TLM_DIPOLE, start + c.settle_s, end)
            result = {"hold": name, "commanded_am2": [float(x) for x in dipole], "mode": mode,
                      "expected_am2": expected.tolist(), "expected_saturated": saturated, "telemetry_frames": len(settled)}
            results.append(result)
            if not settled:
                self.problem(f"commands: no telemetry while the {name} hold was settled (MTQ_TLM_DIPOLE every "
                             f"{ms(c.telemetry_period_s)})")
                continue
            worst = max(settled, key=lambda h: np.max(np.abs(applied_am2(h) - expected)))
            error = float(np.max(np.abs(applied_am2(worst) - expected)))
            result["applied_am2"] = applied_am2(worst).round(6).tolist()
            result["max_error_am2"] = round(error, 6)
            flags = {bool(h.signals["Saturated"]) for h in settled}
            result["saturated_flag"] = sorted(flags)
            if error > c.dipole_tolerance_am2:
                self.problem(f"commands: {name} {fmt(dipole)} A m^2: telemetry applied {fmt(applied_am2(worst))}, the "
                             f"contract's {fmt(expected)} (quantised to {r:g}, saturated at {m:g}; tolerance "
                             f"{c.dipole_tolerance_am2:g} A m^2)")
            if flags != {saturated}:
                self.problem(f"commands: {name}: telemetry Saturated {'/'.join(str(int(x)) for x in sorted(flags))}, "
                             f"the contract's {int(saturated)}")
            if any(h.signals["SafeState"] or h.signals["CommandTimeout"] for h in settled):
                self.problem(f"commands: {name}: telemetry said safe state or command timeout while commanded every "
                             f"{ms(c.command_period_s)}")
            if c.setpoint_echo:
                echoes = f.frames(p.TLM_SETPOINT, start + c.settle_s, end)
                if echoes:
                    last = echoes[-1]
                    result["echo_am2"] = echoed_am2(last).round(6).tolist()
                    if np.max(np.abs(echoed_am2(last) - expected)) > 0.5e-4:
                        self.problem(f"commands: {name} {fmt(dipole)} A m^2: set-point echoed {fmt(echoed_am2(last))}, "
                                     f"the contract's {fmt(expected)} (DAC step {r:g}, each axis at most {m:g} A m^2)")
        self.measured["commands"] = results

    def refusals(self) -> None:
        c, f = self.contract, self.flight
        steady = STEADY(c.max_dipole_am2)
        wrong = [-0.75 * c.max_dipole_am2, 0.75 * c.max_dipole_am2, -0.75 * c.max_dipole_am2]
        probes = [("bad-crc", p.E2EStatus.WRONG_CRC), ("repeated-counter", p.E2EStatus.REPEATED)]
        if c.profile == "secoc":
            probes += [("bad-mac", p.E2EStatus.WRONG_MAC), ("old-freshness", p.E2EStatus.STALE),
                       ("plain-command", p.E2EStatus.NOT_AUTHENTICATED),
                       ("plain-nmt-stop", p.E2EStatus.NOT_AUTHENTICATED)]
        # After a refused frame the steady commands pause long enough for a telemetry frame to show
        # the coils if they moved (a board without the echo), and short enough to stay inside the
        # command timeout with the margin to spare (0.05 s with the defaults).
        pause_s = max(c.command_period_s, min(1.5 * c.telemetry_period_s,
                                              c.command_timeout_s - c.command_period_s - c.margin_s))
        expected_steady = None
        results = []
        for kind, status in probes:
            f.command_for(PROBE_LEAD_S, steady)
            expected_steady = [s for s in f.sent if s.kind == "command"][-1].expected_am2
            sleep_until(f.sent[-1].t_s + 0.5 * c.command_period_s)
            probe = f.probe(kind, wrong)
            sleep_until(probe.t_s + pause_s)
            f.command_for(PROBE_LEAD_S, steady)
            end = time.monotonic()
            self.probe_windows.append((probe.t_s, end))
            results.append(self._judge_probe(kind, status, probe, end, expected_steady))
            if kind == "plain-nmt-stop" and f.state_at(time.monotonic()) != p.NMT_OPERATIONAL:
                self.start_operational("NMT start after an obeyed plain NMT stop")
        f.command_for(PROBE_LEAD_S, steady)
        self.measured["refusals"] = results

    def _judge_probe(self, kind: str, status: p.E2EStatus, probe: Sent, end_s: float, steady: np.ndarray) -> dict:
        c, f = self.contract, self.flight
        what = PROBE_WORDS[kind]
        emcys = f.frames(p.EMCY, probe.t_s, end_s)
        match = next((h for h in emcys if h.signals["ErrorCode"] == p.EMCY_E2E_CHECK_FAILED
                      and h.signals["E2eStatus"] == status
                      and (probe.counter is None or h.signals["RejectedCounter"] == probe.counter)), None)
        moved = []
        for h in f.frames(p.TLM_SETPOINT, probe.t_s, end_s):
            if np.max(np.abs(echoed_am2(h) - steady)) > 0.5e-4:
                moved.append(f"set-point echoed {fmt(echoed_am2(h))}")
                break
        for h in f.frames(p.TLM_DIPOLE, probe.t_s, end_s):
            if np.max(np.abs(applied_am2(h) - steady)) > c.dipole_tolerance_am2:
                moved.append(f"telemetry applied {fmt(applied_am2(h))}")
                break
        if kind == "plain-nmt-stop":
            states = {int(h.signals["NmtState"]) for h in f.frames(p.HEARTBEAT, probe.t_s, end_s)}
            if states - {p.NMT_OPERATIONAL}:
                moved.append(f"heartbeat said {', '.join(state_name(s) for s in sorted(states))}")
        result = {"probe": kind, "expected_emcy": f"0x{p.EMCY_E2E_CHECK_FAILED:04X} {status.name}",
                  "emcy_after_s": _after(match, probe), "moved": moved,
                  "emcys": [_emcy_words(h) for h in emcys]}
        if moved or match is None:
            said = (f"; EMCYs heard: {', '.join(result['emcys'])}" if emcys and match is None else "")
            self.problem(f"{what}: " + " and ".join(
                (["not refused: " + ", ".join(moved) + f" (the steady dipole {fmt(steady)}, the frame's "
                  f"{fmt([-0.75 * c.max_dipole_am2, 0.75 * c.max_dipole_am2, -0.75 * c.max_dipole_am2])})"] if moved else [])
                + ([f"no EMCY 0x{p.EMCY_E2E_CHECK_FAILED:04X} with E2eStatus {status.name} ({int(status)})"
                    + ("" if probe.counter is None else f" and RejectedCounter {probe.counter}") + said]
                   if match is None else [])))
        return result

    def command_timeout(self) -> None:
        c, f = self.contract, self.flight
        last = [s for s in f.sent if s.kind == "command"][-1]
        bound = c.command_timeout_s + c.margin_s
        listen_s = bound + c.telemetry_period_s + c.settle_s + 0.1
        sleep_until(last.t_s + listen_s)
        self.timeout_window = (last.t_s, last.t_s + listen_s)
        emcy = next((h for h in f.frames(p.EMCY, last.t_s, last.t_s + listen_s)
                     if h.signals["ErrorCode"] == p.EMCY_COMMAND_TIMEOUT), None)
        off = next((h for h in f.frames(p.TLM_DIPOLE, last.t_s, last.t_s + listen_s)
                    if h.signals["SafeState"] and np.max(np.abs(applied_am2(h))) <= c.dipole_tolerance_am2), None)
        echo = next((h for h in f.frames(p.TLM_SETPOINT, last.t_s, last.t_s + listen_s)
                     if h.signals["SafeState"] and not h.signals["CommandApplied"]
                     and np.max(np.abs(echoed_am2(h))) <= 0.5e-4), None)
        result = {"emcy_after_s": _after(emcy, last), "coils_off_telemetry_after_s": _after(off, last),
                  "safe_state_echo_after_s": _after(echo, last), "bound_s": round(bound, 4)}
        self.measured["command_timeout"] = result
        if emcy is None:
            self.problem(f"command timeout: no EMCY 0x{p.EMCY_COMMAND_TIMEOUT:04X} within {ms(listen_s)} of the last "
                         f"command (contract: safe state after {ms(c.command_timeout_s)} without a valid command)")
        elif not c.command_timeout_s - 0.002 <= emcy.t_s - last.t_s <= bound:
            self.problem(f"command timeout: EMCY 0x{p.EMCY_COMMAND_TIMEOUT:04X} {ms(emcy.t_s - last.t_s)} after the "
                         f"last command, the contract's {ms(c.command_timeout_s)} (+ {ms(c.margin_s)})")
        if off is None:
            held = [applied_am2(h) for h in f.frames(p.TLM_DIPOLE, last.t_s + bound, last.t_s + listen_s)]
            self.problem(f"command timeout: no safe state: the telemetry never said coils off within {ms(listen_s)} of "
                         f"the last command" + (f" (applied {fmt(held[-1])} A m^2)" if held else ""))
        elif off.t_s - last.t_s > bound + c.telemetry_period_s + c.settle_s:
            self.problem(f"command timeout: the telemetry said coils off {ms(off.t_s - last.t_s)} after the last "
                         f"command (timeout {ms(c.command_timeout_s)} + margin + one telemetry period)")
        if c.setpoint_echo and (echo is None or echo.t_s - last.t_s > bound):
            self.problem(f"command timeout: no set-point echo of the safe state (MTQ_TLM_SETPOINT SafeState 1, "
                         f"CommandApplied 0, set-point 0) within {ms(bound)}" if echo is None else
                         f"command timeout: set-point echo of the safe state {ms(echo.t_s - last.t_s)} after the last "
                         f"command, over {ms(bound)}")
        # Commands again: the error is gone, and the board says so (CiA 301 error reset).
        first = f.command(STEADY(c.max_dipole_am2))
        f.command_for(2 * HOLD_S, STEADY(c.max_dipole_am2))
        reset = next((h for h in f.frames(p.EMCY, first.t_s) if h.signals["ErrorCode"] == p.EMCY_NO_ERROR), None)
        result["error_reset_emcy_after_s"] = _after(reset, first)
        if reset is None and emcy is not None:
            self.problem(f"command timeout: no error-reset EMCY (0x0000) when commands came back (CiA 301: a cleared "
                         f"error is announced)")

    def nmt_states(self) -> None:
        c, f = self.contract, self.flight
        steady = STEADY(c.max_dipole_am2)
        for command, state, what in ((p.NMT_ENTER_PRE_OPERATIONAL, p.NMT_PRE_OPERATIONAL, "NMT enter pre-operational"),
                                     (p.NMT_STOP, p.NMT_STOPPED, "NMT stop")):
            f.command_for(HOLD_S, steady)
            sent, beat = self.nmt(command, state, 3 * c.heartbeat_period_s)
            bound = c.heartbeat_period_s + c.margin_s
            entry = {"heartbeat_after_s": _after(beat, sent)}
            self.measured.setdefault("nmt", {}).setdefault(what, []).append(entry)
            if beat is None:
                self.problem(f"{what}: no heartbeat saying {state_name(state)} within {ms(3 * c.heartbeat_period_s)} "
                             f"(it said {state_name(f.state_at(time.monotonic()))})")
            elif beat.t_s - sent.t_s > bound:
                self.problem(f"{what}: {state_name(state)} heartbeat {ms(beat.t_s - sent.t_s)} after the command, "
                             f"over one heartbeat period + margin ({ms(bound)})")
            # Not operational: commands are not processed, nothing but heartbeats (and, pre-operational,
            # EMCY) is sent. A frame the board would refuse when operational must not be answered when stopped.
            quiet_from = sent.t_s + c.margin_s
            f.command_for(2 * c.heartbeat_period_s, steady, judged=False)
            if state == p.NMT_STOPPED:
                f.probe("bad-crc", steady)
            sleep_until(time.monotonic() + c.heartbeat_period_s)
            self.echo_free.append((quiet_from, time.monotonic()))
            sent_frames = f.frames(PROTECTED + ((p.EMCY,) if state == p.NMT_STOPPED else ()), quiet_from)
            entry["frames_while_not_operational"] = len(sent_frames)
            if sent_frames:
                names = sorted({h.name for h in sent_frames})
                self.problem(f"{what}: {len(sent_frames)} frame(s) ({', '.join(names)}) while {state_name(state)} "
                             f"(CiA 301: " + ("only heartbeats when stopped)" if state == p.NMT_STOPPED
                                              else "no PDOs when pre-operational)"))
            if beat is None:
                continue
            self.start_operational(f"NMT start after {what.removeprefix('NMT ')}")

    def reset_node(self, at_start: bool = False) -> bool:
        c, f = self.contract, self.flight
        sent, boot = self.nmt(p.NMT_RESET_NODE, p.NMT_BOOT_UP, 3 * c.heartbeat_period_s)
        bound = c.heartbeat_period_s + c.margin_s
        pre = f.wait_for(p.HEARTBEAT, boot.t_s if boot else sent.t_s, 3 * c.heartbeat_period_s,
                         lambda h: h.signals["NmtState"] == p.NMT_PRE_OPERATIONAL)
        self.measured.setdefault("nmt", {})["NMT reset node"] = {"boot_up_after_s": _after(boot, sent),
                                                                 "pre_operational_after_s": _after(pre, sent)}
        if boot is None:
            self.problem(f"NMT reset node: no boot-up message (heartbeat state 0) within {ms(3 * c.heartbeat_period_s)}")
        elif boot.t_s - sent.t_s > bound:
            self.problem(f"NMT reset node: boot-up {ms(boot.t_s - sent.t_s)} after the command, over {ms(bound)}")
        if pre is None:
            self.problem(f"NMT reset node: no pre-operational heartbeat after it")
            return False
        if not at_start:
            sleep_until(time.monotonic() + c.heartbeat_period_s)
        return True

    def nmt(self, command: int, state: int, within_s: float) -> tuple[Sent, Heard | None]:
        """Send an NMT command; the first heartbeat saying `state` within within_s, or None. A frame
        the board refused as stale that this host may have delivered late (late_arrivals) is not the
        board's fault: it is sent again, at most LATE_NMT_RETRIES times, and noted."""
        f = self.flight
        for _ in range(LATE_NMT_RETRIES + 1):
            sent = f.nmt(command)
            beat = f.wait_for(p.HEARTBEAT, sent.t_s, within_s, lambda h: h.signals["NmtState"] == state)
            if beat is not None or not self._arrived_stale(sent):
                break
            self.late.append(sent)
        return sent, beat

    def _arrived_stale(self, sent: Sent) -> bool:
        f = self.flight
        if self.contract.profile != "secoc":
            return False                 # no freshness window on e2e
        frames = f.frames()
        index = next(i for i, s in enumerate(f.sent) if s is sent)
        return may_have_arrived_stale(index, f.sent, frames, self.contract.freshness_max_age_s)

    # --- over the whole check ----------------------------------------------------------------
    def throughout(self) -> None:
        c, f = self.contract, self.flight
        self._late_commands()
        beats = f.frames(p.HEARTBEAT)
        gaps = [b.t_s - a.t_s for a, b in zip(beats, beats[1:]) if b.signals["NmtState"] != p.NMT_BOOT_UP]
        hb = {"count": len(beats), "states": [state_name(s) for s in _runs(int(b.signals["NmtState"]) for b in beats)]}
        self.measured["heartbeat"] = hb
        if gaps:
            median, longest = float(np.median(gaps)), float(max(gaps))
            hb.update(period_median_s=round(median, 5), period_max_s=round(longest, 5),
                      contract_period_s=c.heartbeat_period_s, consumer_timeout_s=round(c.heartbeat_timeout_s, 5))
            if abs(median - c.heartbeat_period_s) > 0.1 * c.heartbeat_period_s:
                self.problem(f"heartbeat: period {ms(median)} (median of {len(gaps)}), the contract's "
                             f"{ms(c.heartbeat_period_s)} (within 10 %)")
            if longest > c.heartbeat_timeout_s:
                self.problem(f"heartbeat: a gap of {ms(longest)}, longer than the flight side's consumer time "
                             f"{ms(c.heartbeat_timeout_s)}: the board was lost")
        tlm = f.frames(p.TLM_DIPOLE)
        nmt_sent = [s.t_s for s in f.sent if s.kind in ("nmt", "plain-nmt-stop")]
        op = [b.t_s - a.t_s for a, b in zip(tlm, tlm[1:]) if f.state_at(a.t_s) == p.NMT_OPERATIONAL
              and not any(a.t_s <= t < b.t_s for t in nmt_sent)]
        if op:
            median = float(np.median(op))
            self.measured["telemetry"] = {"period_median_s": round(median, 5), "period_max_s": round(max(op), 5),
                                          "contract_period_s": c.telemetry_period_s, "frames": len(tlm)}
            if abs(median - c.telemetry_period_s) > 0.1 * c.telemetry_period_s:
                self.problem(f"telemetry: period {ms(median)} (median), the contract's {ms(c.telemetry_period_s)}")
            if max(op) > c.telemetry_timeout_s:
                self.problem(f"telemetry: a gap of {ms(max(op))} while operational, over the flight side's "
                             f"{ms(c.telemetry_timeout_s)}")
        self._e2e_of_board_frames()
        self._echoes()
        self._unexpected_emcys()

    def _late_commands(self) -> None:
        """Genuine commands the board did not apply (no echo) or refused as stale, that this host
        may have delivered past the freshness window: excused, counted, and too many of them is a
        problem of its own (the check cannot judge the board on a host this busy)."""
        c, f = self.contract, self.flight
        if c.profile != "secoc":
            return
        heard = f.frames()
        answers: dict[str, dict[int, list[float]]] = {"echo": {}, "stale": {}}   # counter -> times heard
        for h in heard:
            if h.name == p.TLM_SETPOINT and h.signals["CommandApplied"]:
                answers["echo"].setdefault(int(h.signals["CommandCounter"]), []).append(h.t_s)
            elif (h.name == p.EMCY and h.signals["ErrorCode"] == p.EMCY_E2E_CHECK_FAILED
                  and h.signals["E2eStatus"] == p.E2EStatus.STALE):
                answers["stale"].setdefault(int(h.signals["RejectedCounter"]), []).append(h.t_s)
        judged = [(i, s) for i, s in enumerate(f.sent) if s.judged]
        for i, s in judged:
            later = next((t.t_s for t in f.sent[i + 1:] if t.counter == s.counter), float("inf"))
            named = {kind: any(s.t_s < t < later for t in times.get(s.counter, ())) for kind, times in answers.items()}
            if ((named["stale"] or (c.setpoint_echo and not named["echo"]))
                    and may_have_arrived_stale(i, f.sent, heard, c.freshness_max_age_s)):
                self.late.append(s)
        commands = [s for s in self.late if s.kind == "command"]
        self.measured["late_on_arrival"] = {"commands": len(commands), "nmt": len(self.late) - len(commands),
                                            "freshness_window_s": c.freshness_max_age_s}
        if len(commands) > LATE_SHARE_LIMIT * max(1, len(judged)):
            self.problem(f"this host held {len(commands)} of {len(judged)} commands past the freshness window "
                         f"({ms(c.freshness_max_age_s)}) before the board had them: too many to judge the board; "
                         f"run the check on a less loaded host")

    def _e2e_of_board_frames(self) -> None:
        f = self.flight
        receivers = {name: p.E2EReceiver() for name in PROTECTED}
        bad: dict[str, int] = {}
        for h in f.frames((*PROTECTED, p.HEARTBEAT)):
            if h.name == p.HEARTBEAT:
                if h.signals["NmtState"] == p.NMT_BOOT_UP:     # a booted node counts from zero again
                    for r in receivers.values():
                        r.reset()
                continue
            status = receivers[h.name].check(h.counter, h.crc_ok)
            if status in (p.E2EStatus.WRONG_CRC, p.E2EStatus.REPEATED):
                bad[f"{h.name} {status.name}"] = bad.get(f"{h.name} {status.name}", 0) + 1
        self.measured["board_frames_e2e"] = bad
        if bad:
            self.problem("E2E of the board's frames: " + ", ".join(f"{k} x{n}" for k, n in sorted(bad.items()))
                         + " (CRC-8 0x2F over bytes 1-7 and the data id, counter +1 per frame: mtq.dbc)")

    def _echoes(self) -> None:
        c, f = self.contract, self.flight
        if not c.setpoint_echo:
            self.measured["echo"] = "not checked (--real-time-only)"
            return
        judged = [s for s in f.sent if s.judged]
        echoes = [h for h in f.frames(p.TLM_SETPOINT) if h.signals["CommandApplied"]]
        latencies, missing, wrong = [], [], []
        late = {id(s) for s in self.late}
        for i, s in enumerate(f.sent):
            if not s.judged or id(s) in late:
                continue
            later = next((t.t_s for t in f.sent[i + 1:] if t.counter == s.counter), float("inf"))
            echo = next((h for h in echoes if s.t_s <= h.t_s < later and h.signals["CommandCounter"] == s.counter),
                        None)
            if echo is None:
                missing.append(s)
                continue
            latencies.append(echo.t_s - s.t_s)
            if np.max(np.abs(echoed_am2(echo) - s.expected_am2)) > 0.5e-4 or echo.signals["SafeState"]:
                wrong.append((s, echo))
        result = {"commands": len(judged), "echoed": len(latencies)}
        if latencies:
            result.update(latency_p50_s=round(float(np.median(latencies)), 6), latency_max_s=round(max(latencies), 6))
        self.measured["echo"] = result
        if not echoes:
            self.problem(f"set-point echo: no MTQ_TLM_SETPOINT with CommandApplied 1 for {len(judged)} applied commands "
                         f"(lock-step pairs each step's command with it: a board without it runs in real time only; "
                         f"--real-time-only to check it so)")
            return
        if missing:
            self.problem(f"set-point echo: {len(missing)} of {len(judged)} applied commands not acknowledged with their "
                         f"alive counter (first: counter {missing[0].counter})")
        if wrong:
            s, e = wrong[0]
            self.problem(f"set-point echo: {len(wrong)} echo(es) with a set-point other than the command's (first: counter "
                         f"{s.counter}: {fmt(echoed_am2(e))}, the contract's {fmt(s.expected_am2)})")
        slow = [x for x in latencies if x > c.command_timeout_s]
        if slow:
            self.problem(f"set-point echo: {len(slow)} echo(es) later than the command timeout ({ms(c.command_timeout_s)}) "
                         f"after their command, worst {ms(max(slow))} (it must follow the command it acknowledges)")
        stray = [h for a, b in self.echo_free for h in f.frames(p.TLM_SETPOINT, a, b)]
        if stray:
            self.problem(f"set-point echo: {len(stray)} echo(es) while not operational")

    def _unexpected_emcys(self) -> None:
        c, f = self.contract, self.flight
        windows = list(self.probe_windows)
        if self.timeout_window:
            windows.append(self.timeout_window)
        explained = {id(h) for h in explained_emcys(self.late, f.sent, f.frames())}
        odd = [h for h in f.frames(p.EMCY)
               if h.signals["ErrorCode"] != p.EMCY_NO_ERROR and not any(a <= h.t_s < b for a, b in windows)
               and id(h) not in explained]
        self.measured["unexpected_emcys"] = [_emcy_words(h) for h in odd]
        self.measured["check_max_command_gap_s"] = round(f.max_gap_s, 5)
        if odd:
            host = (f" (the check itself once went {ms(f.max_gap_s)} without a command: this host held it up)"
                    if f.max_gap_s > c.freshness_max_age_s else "")
            self.problem(f"EMCY for genuine commands: {', '.join(_emcy_words(h) for h in odd[:5])}"
                         f"{' ...' if len(odd) > 5 else ''}{host}")


STEADY = lambda m: [0.4 * m, -0.3 * m, 0.2 * m]    # noqa: E731 - the steady dipole for a limit m

PROBE_WORDS = {
    "bad-crc": "bad CRC (a command whose E2E CRC is wrong, its MAC authentic on secoc)",
    "repeated-counter": "repeated alive counter (the last command's counter again, otherwise valid)",
    "bad-mac": "bad MAC (an authenticated command whose CMAC is wrong by one bit)",
    "old-freshness": "old freshness (an authentic command whose freshness value is ten windows old)",
    "plain-command": "plain MTQ_CMD on secoc (valid E2E, no MAC)",
    "plain-nmt-stop": "plain NMT stop on secoc (identifier 0, no MAC)",
}


def _after(h: Heard | None, sent: Sent) -> float | None:
    return None if h is None else round(h.t_s - sent.t_s, 5)


def _emcy_words(h: Heard) -> str:
    code, status = int(h.signals["ErrorCode"]), int(h.signals["E2eStatus"])
    name = p.E2EStatus(status).name if status in p.E2EStatus._value2member_map_ else str(status)
    return f"0x{code:04X}" + (f" {name} counter {int(h.signals['RejectedCounter'])}" if code == p.EMCY_E2E_CHECK_FAILED else "")


def _runs(values):
    out = []
    for v in values:
        if not out or out[-1] != v:
            out.append(v)
    return out


# --- the run ------------------------------------------------------------------------------------
def board_scenario(path: str | None) -> Scenario:
    scenario = load_scenario(path) if path else parse_scenario(DEFAULT_SCENARIO, "board check")
    if scenario.can is None:
        raise ScenarioError(f"contract check board: scenario {scenario.name!r} has no [can] section (the board's "
                            f"contract)")
    return scenario


def read_secoc_key(path: Path) -> str:
    """The 16-byte SecOC key as 32 hex digits from a file only its owner can read (secoc.key)."""
    import stat
    try:
        mode = stat.S_IMODE(path.stat().st_mode)
        text = path.read_text().strip()
    except OSError as exc:
        raise ValueError(f"--key-file {str(path)!r}: {exc.strerror}") from None
    if mode & 0o077:
        raise ValueError(f"--key-file {str(path)!r} is readable by others (mode {mode:04o}); chmod 600 it")
    try:
        ok = len(bytes.fromhex(text)) == secoc.KEY_BYTES
    except ValueError:
        ok = False
    if not ok:
        raise ValueError(f"--key-file {str(path)!r} must hold {2 * secoc.KEY_BYTES} hexadecimal digits (AES-128)")
    return text


def cmd_check_board(args) -> int:
    """`bench contract check board` (bench/contract/cli.py)."""
    try:
        scenario = board_scenario(args.scenario)
        if args.key_file:
            scenario = msgspec.structs.replace(scenario, can=run_key.can_with_key(
                scenario.can, read_secoc_key(Path(args.key_file))))
        outside_bus = args.interface is not None and args.interface != "zenoh"
        if args.channel and not outside_bus:     # the bench's board, started from {scenario}, on that channel too
            scenario = msgspec.structs.replace(scenario, can=msgspec.structs.replace(scenario.can,
                                                                                      board_channel=args.channel))
        if args.no_fd and scenario.can.security.authenticated:
            raise ValueError("--no-fd: the secoc profile's authenticated frames are CAN FD (a classic-only board "
                             "needs [can.security] profile = \"e2e\" in --scenario)")
        if outside_bus and run_key.needs_key(scenario):
            raise ValueError("the secoc profile needs the board's key: --key-file FILE (32 hex digits, mode 0600), or "
                             "[can.security] key_hex in --scenario")
        if not 0 < args.margin <= 10:
            raise ValueError(f"--margin must be in (0, 10] s, got {args.margin}")
        startup_s = args.startup_timeout if args.startup_timeout is not None else STARTUP_TIMEOUT_S
        if not 1 <= startup_s <= 3600:
            raise ValueError(f"--startup-timeout must be 1-3600 s, got {startup_s}")
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S")
        run_id = keys.check_run_id(args.run_id or f"contract-board-{stamp}")
        run_dir = Path(args.runs_dir) / run_id
        if run_dir.exists():
            raise ValueError(f"run directory {run_dir} exists: choose another --run-id")
        spec = (BusSpec(interface=args.interface, channel=args.channel or "", bitrate=args.bitrate, fd=not args.no_fd)
                if outside_bus else None)
        verdict = run_board_check(scenario, run_id, run_dir, args.command, spec, args.channel, args.port,
                                  args.margin, args.dipole_tolerance, args.real_time_only, startup_s)
    except (ScenarioError, ValueError, msgspec.ValidationError) as exc:
        print(f"bench contract check: error: {exc}", file=sys.stderr)
        return 2
    except (can.CanError, OSError, TransportUnavailable, NotImplementedError) as exc:
        print(f"bench contract check: error: the board's bus: {exc}", file=sys.stderr)
        return 2
    print(verdict.text("board"))
    return 0 if verdict.passed else 1


def run_board_check(scenario: Scenario, run_id: str, run_dir: Path, command: str | None, spec: BusSpec | None,
                    channel: str | None, port: int | None, margin_s: float = DEFAULT_MARGIN_S,
                    tolerance_am2: float | None = None, real_time_only: bool = False,
                    startup_timeout_s: float = STARTUP_TIMEOUT_S, bus_session=None) -> Verdict:
    """Check the board; `spec` None: the bench's zenoh interface on a hub the check opens (`port`),
    else the board's own bus (bus_session: a Zenoh session of the caller's for a `zenoh` spec)."""
    config = scenario.can
    if run_key.needs_key(scenario):            # the bench's board started by the check: a key for this run
        scenario = run_key.with_run_key(scenario)
        config = scenario.can
    contract = BoardContract.of(config, margin_s, tolerance_am2, real_time_only)
    (run_dir / "logs").mkdir(parents=True)
    scenario_path = run_dir / "scenario.json"
    run_key.write_private(scenario_path, msgspec.json.format(msgspec.json.encode(scenario)))
    # The data topics' key, as the launcher writes it: the bench's board signs what it publishes.
    run_key.write_private(run_dir / data_auth.KEY_FILE, (data_auth.new_key().hex() + "\n").encode())
    # The flight side stands for flight software on its own processor, as the bench's driver does.
    priority = config.realtime_priority
    if priority and not set_realtime_priority(priority, inherited=True):
        priority = 0
    session = hub = None
    board_channel = channel or config.board_channel
    if spec is None:
        hub = loopback_endpoint(port or free_loopback_port())
        session = open_session(SessionOptions(listen=(hub,)))
        spec = BusSpec(interface="zenoh", channel=board_channel)
    process = None
    flight = None
    try:
        bus = open_bus(spec, run_id=run_id, session=session or bus_session)
        if priority:
            set_realtime_priority(priority)    # what this thread starts from now on runs at normal priority
        flight = FlightSide(bus, contract, config.security.key if contract.profile == "secoc" else None,
                            run_dir / CAPTURE_NAME, priority)
        where = (f"connect to {hub}, run id {run_id}, scenario {scenario_path}, channel {board_channel}"
                 if hub else f"{spec.interface} channel {spec.channel}")
        t_started_s = time.monotonic()
        # A board on the user's own channel without --command may be running already (no boot-up to see).
        check = BoardCheck(flight, contract, started_by_check=bool(command) or hub is not None,
                           log_path=str(run_dir / "logs" / OUTSIDE_LOG))
        if command:
            argv = [a.format(connect=hub or "", run_id=run_id, scenario=str(scenario_path), run_dir=str(run_dir),
                             channel=board_channel) for a in shlex.split(command)]
            with open(run_dir / "logs" / OUTSIDE_LOG, "w") as log:
                try:
                    process = check.process = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT)
                except OSError as exc:
                    check.problem(f"could not start the board ({' '.join(argv)}): {exc}")
        else:
            print(f"bench: waiting for the board: {where}", file=sys.stderr)
        if not check.problems:
            check.run(startup_timeout_s, t_started_s)
        if (process is not None and process.poll() is not None
                and not any("the board's command exited" in problem for problem in check.problems)):
            check.problem(f"the board's command exited with code {process.returncode} during the check "
                          f"(its output: {run_dir / 'logs' / OUTSIDE_LOG})")
    finally:
        if flight is not None:
            flight.close()
            bus.shutdown()
        if process is not None and process.poll() is None:
            process.send_signal(signal.SIGTERM)     # the board the check started, by its handle
            try:
                process.wait(timeout=EXIT_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(timeout=EXIT_TIMEOUT_S)
        if session is not None:
            session.close()
        if priority:
            set_realtime_priority(0)
    verdict = Verdict(check.problems, summary(check, contract, spec, flight))
    write_board_verdict(run_dir, verdict, contract, check.measured)
    return verdict


def summary(check: BoardCheck, c: BoardContract, spec: BusSpec, flight: FlightSide) -> str:
    m = check.measured
    hb, echo, timeout = m.get("heartbeat", {}), m.get("echo"), m.get("command_timeout", {})
    parts = [f"{c.profile}, node {c.node_id:#04x} on {spec.interface} {spec.channel}"]
    if "period_median_s" in hb:
        parts.append(f"heartbeat {ms(hb['period_median_s'])} (contract {ms(c.heartbeat_period_s)}), "
                     + " -> ".join(hb["states"]))
    if m.get("commands"):
        worst = max((r.get("max_error_am2", 0.0) for r in m["commands"]), default=0.0)
        parts.append(f"{len(m['commands'])} dipoles applied, telemetry within {worst:g} A m^2 (tolerance "
                     f"{c.dipole_tolerance_am2:g}; quantised to {c.dipole_resolution_am2:g}, saturated at "
                     f"{c.max_dipole_am2:g})")
    if not c.setpoint_echo:
        parts.append("set-point echo not required (--real-time-only: a board for real time only)")
    if isinstance(echo, dict) and "latency_p50_s" in echo:
        parts.append(f"{echo['echoed']}/{echo['commands']} commands echoed with their counter (p50 "
                     f"{ms(echo['latency_p50_s'])}, max {ms(echo['latency_max_s'])})")
    if timeout.get("emcy_after_s") is not None:
        parts.append(f"command timeout: EMCY 0x8250 {ms(timeout['emcy_after_s'])}, coils off in telemetry "
                     f"{ms(timeout.get('coils_off_telemetry_after_s'))} after the last command (contract "
                     f"{ms(c.command_timeout_s)} + {ms(c.margin_s)})")
    refused = [r["probe"] for r in m.get("refusals", []) if r["emcy_after_s"] is not None and not r["moved"]]
    if refused:
        parts.append(f"refused with EMCY 0x8100: {', '.join(refused)}")
    late = m.get("late_on_arrival", {})
    if late.get("commands") or late.get("nmt"):
        parts.append(f"excused as late on arrival (this host, over the {ms(late['freshness_window_s'])} freshness "
                     f"window): {late['commands']} command(s), {late['nmt']} NMT frame(s)")
    return "; ".join(parts)


def write_board_verdict(run_dir: Path, verdict: Verdict, contract: BoardContract, measured: dict) -> None:
    (run_dir / VERDICT_NAME).write_text(json.dumps(
        {"node": "board", "passed": verdict.passed, "problems": verdict.problems, "summary": verdict.summary,
         "schema_version": SCHEMA_VERSION, "contract": contract.__dict__, "measured": measured},
        indent=2, default=_jsonable) + "\n")


def _jsonable(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    raise TypeError(type(value).__name__)
