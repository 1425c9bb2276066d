"""The virtual magnetorquer board: what a real coil-driver board does on its CAN bus.

It applies only commands of its profile's frame that pass, in this order, SecOC (profile "secoc":
the MAC, then the freshness value: age at most one command period plus the stated margin, newer
than the last applied) and the E2E profile-2 receiver state machine (protocol.E2EReceiver, ticked
once per command period without a command and reset when the command timeout expires). It
quantises each axis to its driver's resolution and saturates it, drives coil currents that follow
with a first-order lag (the coil's L/R), turns the coils off when commands stop (safe state) or
while the magnetometer samples, and sends heartbeat and telemetry at fixed periods. Every rejected
command, and every command that shows earlier ones were lost, is reported by an emergency frame,
no two closer than the EMCY inhibit time (CiA 301 0x1015): what is rejected within it is reported
by the next one, with the running count of rejected frames.

As a CANopen node (CiA 301) it boots into pre-operational (boot-up heartbeat, then heartbeats
carrying its NMT state) and processes commands and sends telemetry only once an NMT master has
started it (operational); stop and enter-pre-operational turn the coils off, reset node and
reset communication boot it again. On the "e2e" profile it obeys plain NMT (identifier 0) from
anyone, as CiA 301 says. On "secoc" it changes its NMT state only on MTQ_NMT_AUTH whose MAC and
freshness verify (its own SecOC data id and newer-than-last, the same age window as commands):
a plain NMT frame is refused (rejected as NMT_NOT_AUTHENTICATED, reported by EMCY), so a node
without the key can neither stop nor reset the board to switch its coils off. A cleared error (commands back after a timeout) is announced
by an error-reset EMCY (code 0x0000).

Its object dictionary is mtq.eds (CiA 306): the heartbeat time, EMCY inhibit time and command
timeout come from it unless the scenario sets them, and a CANopen tool reads and writes them,
the identity and the error history over SDO (canopen's SDO server, board_sdo.py), except while
stopped.

Its hardware is bench/bus/can/coils.py's: the scenario's hardware faults act on its coils (the
physical dipole, `output_dipole_am2`, and the current sensor in series with each coil, which its
telemetry reports, can then differ) and on its power supply: without power it sends nothing, hears
nothing and drives no coil, and when power returns it boots as after a reset node (boot-up
heartbeat, pre-operational: the driver's NMT start makes it operational again). Each loss, boot
and start is logged with its time (`power_log`, can/board.json).

The parts: the NMT slave and boot (board_nmt.py), what it sends, emergency frames included
(board_transmit.py), its SDO server (board_sdo.py), its coils' hardware (coils.py).

`step(now_s)` handles what arrived and what is due at `now_s`; `run(stop)` is the process loop.
Time comes from the caller's clock, so unit tests drive the board deterministically.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Callable

import can
import msgspec
import numpy as np

from bench.bus.can import canopen_od
from bench.bus.can import protocol as p
from bench.bus.can import secoc
from bench.bus.can.board_nmt import NmtSlave
from bench.bus.can.board_sdo import BoardSdoServer
from bench.bus.can.board_transmit import ERROR_HISTORY_ENTRIES, ERROR_REGISTER_COMMUNICATION, BoardTransmitter
from bench.bus.can.coils import CoilHardware
from bench.bus.can.config import BoardConfig, SecurityConfig
from bench.bus.can.host_lateness import HostLateLog

log = logging.getLogger(__name__)


@dataclass
class AppliedCommand:
    """One accepted command, for whoever publishes the applied dipole (the node)."""
    dipole_am2: np.ndarray          # after quantisation and saturation: the coil driver's target
    alive_counter: int
    received_ns: int                # board decoded the frame
    applied_ns: int                 # board set the coil targets
    age_s: float | None = None      # secoc: age from its freshness value when applied (board clock)


def applied_record(command: AppliedCommand) -> dict:
    """One command the board applied, as can/board.json lists it."""
    return {"counter": command.alive_counter, "dipole_am2": command.dipole_am2.tolist(),
            "applied_ns": command.applied_ns, "age_s": command.age_s}


@dataclass
class BoardState:
    target_dipole_am2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    coil_current_a: np.ndarray = field(default_factory=lambda: np.zeros(3))
    safe_state: bool = True          # coils off until the first valid command
    command_timeout: bool = False
    actuation_paused: bool = False
    saturated: bool = False
    mode: int = p.MODE_OFF
    last_command_counter: int = 0
    command_rejected_since_tlm: bool = False


def coil_driver_dipole(requested_am2: np.ndarray, config: BoardConfig) -> tuple[np.ndarray, bool]:
    """What the coil drivers are set to for a requested dipole: quantised to the DAC step, then
    saturated per axis; True when an axis saturated. (Also the in-process loop's board model.)"""
    quantised = np.round(np.asarray(requested_am2, float) / config.dipole_resolution_am2) * config.dipole_resolution_am2
    saturated = np.clip(quantised, -config.max_dipole_am2, config.max_dipole_am2)
    return saturated, bool(np.any(saturated != quantised))


class MagnetorquerBoard(NmtSlave, BoardTransmitter):
    def __init__(self, bus: can.BusABC, config: BoardConfig, protocol: p.Protocol,
                 clock: Callable[[], float] = time.monotonic,
                 on_applied: Callable[[AppliedCommand], None] | None = None,
                 on_coils_changed: Callable[[BoardState], None] | None = None,
                 security: SecurityConfig | None = None, hardware: CoilHardware | None = None):
        """on_applied: each accepted command. on_coils_changed: the coil target changed without a
        command (safe state entered, magnetometer window began or ended), so that whoever
        publishes the applied dipole never leaves a stale one standing.

        The CANopen parameters (heartbeat time, EMCY inhibit time, command timeout) are mtq.eds's
        where `config` keeps BoardConfig's defaults; a CANopen tool may change them over SDO
        (board_sdo.py), and NMT reset communication / reset node restores them.

        hardware: the coils and power supply under the scenario's hardware faults (coils.py); the
        injector's where the board shares the bus model's process (armed with the first command
        frame), else the board's own, armed with the first command it accepts."""
        od = canopen_od.object_dictionary(protocol.node_id)
        canopen_od.check_cob_ids(od, protocol)
        self.bus = bus
        self.config = self._configured = canopen_od.board_config(config, od)
        self.protocol = protocol
        self.clock = clock
        self.on_applied = on_applied
        self.on_coils_changed = on_coils_changed
        self.state = BoardState()
        self.hardware = hardware if hardware is not None else CoilHardware([])
        self._powered = True
        self._hardware_state: tuple = ()
        self._hw_now_s = 0.0                   # the time the coils' outputs are for (update)
        self.power_log: list[dict] = []        # {"event": power_lost | booted | operational, "t_s": board clock}
        self.e2e = p.E2EReceiver(config.max_delta_counter, config.sync_counter, config.max_no_new_or_repeated)
        self.command_name = protocol.command_name
        self.command_period_s = p.cycle_time_s(self.command_name)
        self.freshness: secoc.FreshnessVerifier | None = None
        self.nmt_freshness: secoc.FreshnessVerifier | None = None
        self.nmt_name = p.NMT_FRAMES[protocol.profile]   # the only NMT frame this board obeys
        if protocol.profile == "secoc":
            security = security or SecurityConfig(profile="secoc")
            if protocol.key is None:
                raise ValueError("the secoc profile needs the key in the board's Protocol "
                                 "(can.security.key_hex is empty: run it from the launcher's scenario.json)")
            window = dict(max_age_s=self.command_period_s + security.freshness_margin_s,
                          max_future_s=security.max_future_s)
            self.freshness = secoc.FreshnessVerifier(protocol.key, p.secoc_data_id(self.command_name), **window)
            self.nmt_freshness = secoc.FreshnessVerifier(protocol.key, p.secoc_data_id(p.NMT_AUTH), **window)
        self.last_command_age_s: float | None = None
        self.rejected: Counter = Counter()     # by E2E status name or "wrong_length"
        self.accepted = 0
        self.lost_commands = 0
        # Periodic frames sent more than half a period late, on the board's clock.
        self.host_lateness = HostLateLog()
        self.sent: Counter = Counter()
        self.received: Counter = Counter()     # every frame heard, by name (frame accounting)
        self._tx_counter: Counter = Counter()  # alive counters of the board's own protected frames
        self._started_s: float | None = None
        self._last_update_s: float | None = None
        self._last_command_s: float | None = None
        self._next_no_data_s: float | None = None    # next E2E check without a new command
        self._last_emcy_s: float | None = None
        self._pending_emcy: list[dict] = []         # held back by the inhibit time
        self._next_heartbeat_s = 0.0
        self._next_telemetry_s = 0.0
        self.nmt_state = p.NMT_BOOT_UP
        self.ignored: Counter = Counter()      # frames not for this NMT state (CiA 301: not processed)
        self.error_register = 0                # CiA 301 0x1001: as in the last EMCY sent
        self.error_history: deque[int] = deque(maxlen=ERROR_HISTORY_ENTRIES)   # 0x1003, newest first
        self._now_s = 0.0                      # the time of the frame being handled (SDO writes)
        self.sdo = BoardSdoServer(protocol.node_id, self._send, read_parameter=lambda name: getattr(self.config, name),
                                  write_parameter=self._write_parameter, error_register=lambda: self.error_register,
                                  error_history=lambda: list(self.error_history),
                                  clear_error_history=self.error_history.clear,
                                  writable=protocol.profile == "e2e")

    @property
    def applied_dipole_am2(self) -> np.ndarray:
        """The dipole the current sensors measure now (it lags the target by the coil time
        constant): what the telemetry reports, which a hardware fault after the sensor (a coil
        wired backwards, a weak coil) does not show."""
        return self.state.coil_current_a * self.config.coil_gain_am2_per_a

    @property
    def setpoint_am2(self) -> np.ndarray:
        """The dipole the coil drivers are set to: zero in safe state and magnetometer windows."""
        s = self.state
        return np.zeros(3) if (s.safe_state or s.actuation_paused) else s.target_dipole_am2.copy()

    @property
    def output_dipole_am2(self) -> np.ndarray:
        """The dipole the coils put into the field (what the plant turns into torque): the coil
        drivers' set-point, through the hardware faults acting at the last update; zero without
        power."""
        if not self.hardware.windows:
            return self.setpoint_am2
        return self.hardware.physical_am2(self.setpoint_am2, self._hw_now_s)

    def _write_parameter(self, name: str, value_s: float) -> None:
        """A CANopen tool wrote a parameter over SDO; a new heartbeat time counts from now."""
        self.config = msgspec.structs.replace(self.config, **{name: value_s})
        if name == "heartbeat_period_s":
            self._next_heartbeat_s = self._first_heartbeat_s(self._now_s)

    # --- power supply (board_power_loss) --------------------------------------------------
    def _powered_at(self, now_s: float) -> bool:
        """Whether the board has power at now_s; losing it or getting it back happens here."""
        if not self.hardware.windows:
            return True
        powered = self.hardware.powered(now_s)
        if powered != self._powered:
            self._power_off(now_s) if not powered else self._power_on(now_s)
        return powered

    def _power_off(self, now_s: float) -> None:
        """Power gone: no coil current, nothing sent or heard; whatever the board held in RAM (its
        state, the E2E receiver, queued EMCYs, its counters) is lost."""
        self._powered = False
        self.power_log.append({"event": "power_lost", "t_s": now_s})
        self.state = BoardState()             # safe state, coils off
        self.nmt_state = p.NMT_BOOT_UP        # no NMT state until it boots again
        self._last_command_s = self._next_no_data_s = self._last_emcy_s = None
        self._pending_emcy.clear()
        self._hw_now_s = now_s
        if self.on_coils_changed is not None:
            self.on_coils_changed(self.state)

    def _power_on(self, now_s: float) -> None:
        """Power back: the board boots as after a reset node (CiA 301): parameters from its object
        dictionary, a new E2E receiver, its own counters from zero, boot-up heartbeat and
        pre-operational until the NMT master starts it. The SecOC freshness it accepted last is
        kept (non-volatile: a reboot must not reopen the window for a replay)."""
        self._powered = True
        self.power_log.append({"event": "booted", "t_s": now_s})
        self.config = self._configured
        self.e2e.reset()
        self._tx_counter.clear()
        self.error_register = 0
        self._last_update_s = now_s
        self._hw_now_s = now_s
        self._hardware_state = self.hardware.state(now_s)
        self.start(now_s)

    def step(self, now_s: float | None = None) -> None:
        """Handle every frame waiting on the bus, then advance the coils and send what is due."""
        now_s = self.clock() if now_s is None else now_s
        if self._started_s is None:
            self.start(now_s)
        while (msg := self.bus.recv(timeout=0.0)) is not None:
            self.handle(msg, now_s)
        self.update(now_s)

    def run(self, stop: threading.Event) -> None:
        """Process loop: wake on every frame or when the next periodic frame is due."""
        self.start(self.clock())
        while not stop.is_set():
            # The telemetry's time only when operational: it stands still until the NMT start, and
            # waiting for it made this loop spin (a CPU burnt until then; at SCHED_FIFO on one CPU
            # the driver that would send the start never ran). The 10 ms cap covers the rest of
            # next_due_s (the command timeout, held EMCYs), which costs too much per frame in a flood.
            due_s = self._next_heartbeat_s
            if self.nmt_state == p.NMT_OPERATIONAL:
                due_s = min(due_s, self._next_telemetry_s)
            if self.hardware.windows:   # a power loss's or a coil fault's edge
                due_s = min(due_s, self.hardware.next_edge_s(self.clock()) or math.inf)
                if not self._powered:
                    due_s = min(due_s, self.clock() + 0.01)
            wait_s = max(0.0, due_s - self.clock())
            msg = self.bus.recv(timeout=min(wait_s, 0.01))
            now_s = self.clock()
            if msg is not None:
                self.handle(msg, now_s)
            self.update(now_s)

    # --- receiving ------------------------------------------------------------------------
    def handle(self, msg: can.Message, now_s: float) -> None:
        """One frame from the bus. Anything but a valid command is counted and ignored."""
        if not self._powered_at(now_s):
            self.ignored["without power"] += 1      # a board without power hears nothing
            return
        received_ns = time.monotonic_ns()
        self.received[p.frame_kind(self.protocol, msg)] += 1
        if self.sdo.is_request(msg) and self.nmt_state != p.NMT_STOPPED:   # CiA 301: no SDO when stopped
            self._now_s = now_s
            if self.sdo.handle(msg):
                return
        command_id = self.protocol.frame_ids[self.command_name]
        if (msg.arbitration_id == command_id and self.nmt_state == p.NMT_OPERATIONAL
                and not msg.is_error_frame and not msg.is_remote_frame
                and not msg.is_extended_id
                and len(msg.data) != self.protocol.db.get_message_by_name(self.command_name).length):
            self._reject("wrong_length", None, p.EMCY_PDO_LENGTH, 0, now_s)
        frame = self.protocol.decode(msg)
        if frame is not None and frame.name in (p.NMT, p.NMT_AUTH):
            if self._nmt_authentic(frame, msg, now_s):
                self._on_nmt(frame, now_s)
            return
        if frame is None or frame.name not in p.COMMANDS:
            return  # other nodes' frames (our own telemetry echoed, a babbler) are not for us
        if self.nmt_state != p.NMT_OPERATIONAL:
            self.ignored[f"{frame.name} while {_NMT_NAMES[self.nmt_state]}"] += 1   # PDOs run only when operational
            return
        if frame.name != self.command_name:
            # A plain command where the profile wants an authenticated one (a downgrade).
            status = p.E2EStatus.NOT_AUTHENTICATED if self.freshness is not None else None
            if status is not None:
                self._reject(status.name, frame.counter, p.EMCY_E2E_CHECK_FAILED, int(status), now_s)
            return
        freshness = None
        if self.freshness is not None:
            verdict, freshness, age_s = self.freshness.verify(bytes(msg.data), now_s)
            if verdict is not secoc.Verdict.OK:
                # Before E2E: a forged or stale frame must not move the receiver's state.
                status = p.E2EStatus[verdict.value]
                self._reject(status.name, frame.counter, p.EMCY_E2E_CHECK_FAILED, int(status), now_s)
                return
            self.last_command_age_s = age_s
        status = self.e2e.check(frame.counter, frame.crc_ok)
        self._next_no_data_s = now_s + 1.5 * self.command_period_s
        if not status.accepted:
            self._reject(status.name, frame.counter, p.EMCY_E2E_CHECK_FAILED, int(status), now_s)
            return
        if freshness is not None:
            self.freshness.accept(freshness)
        if status is p.E2EStatus.OK_SOME_LOST:
            # Accepted, but commands were lost on the way: the flight side must hear of it.
            self.lost_commands += self.e2e.lost_data
            self._emergency(p.EMCY_E2E_CHECK_FAILED, int(status), frame.counter, now_s)
        self.update(now_s)  # coils run up to now on the old target before it changes
        self._apply(frame, now_s, received_ns)

    def _apply(self, frame: p.Frame, now_s: float, received_ns: int) -> None:
        s, c = self.state, self.config
        requested = np.array([frame.signals[f"Dipole{a}"] for a in p.AXES])
        saturated, s.saturated = coil_driver_dipole(requested, c)
        s.mode = int(frame.signals["Mode"])
        s.target_dipole_am2 = saturated if s.mode == p.MODE_DIPOLE else np.zeros(3)
        s.last_command_counter = frame.counter
        if s.command_timeout:
            # CiA 301: the error is gone; say so with an error-reset EMCY and the error register now.
            self._emergency(p.EMCY_NO_ERROR, 0, frame.counter, now_s, error_register=0)
        s.safe_state = s.command_timeout = False
        self._last_command_s = now_s
        self.accepted += 1
        if not self.hardware.armed:
            self.hardware.arm(now_s)     # a board alone: its hardware faults count from its first command
        if self.on_applied is not None:
            self.on_applied(AppliedCommand(s.target_dipole_am2.copy(), frame.counter, received_ns, time.monotonic_ns(),
                                           self.last_command_age_s if self.freshness is not None else None))
        self._echo_setpoint(command_applied=True)

    def _reject(self, reason: str, counter: int | None, error_code: int, e2e_status: int, now_s: float) -> None:
        self.rejected[reason] += 1
        self.state.command_rejected_since_tlm = True
        self._emergency(error_code, e2e_status, counter, now_s)

    # --- time -----------------------------------------------------------------------------
    def update(self, now_s: float) -> None:
        """Safe state and magnetometer windows, coil currents up to now, periodic frames."""
        s, c = self.state, self.config
        changed = False
        if self.hardware.windows:
            if not self._powered_at(now_s):
                return                                # no frames, no coil current
            state = self.hardware.state(now_s)
            changed = state != self._hardware_state != ()   # a coil fault began or ended: the coils changed
            self._hardware_state = state
        self._hw_now_s = now_s
        if (self._last_command_s is not None and not s.safe_state
                and now_s - self._last_command_s > c.command_timeout_s):
            self._enter_safe_state(now_s)
            changed = True
        while self._next_no_data_s is not None and now_s >= self._next_no_data_s:
            self.e2e.no_new_data()    # one E2E check per command period that brought none
            self._next_no_data_s += self.command_period_s
        self._flush_emergency(now_s)
        paused = self._in_mag_window(now_s)
        changed |= paused != s.actuation_paused
        s.actuation_paused = paused
        if changed:
            if self.on_coils_changed is not None:
                self.on_coils_changed(s)
            self._echo_setpoint(command_applied=False)
        target = np.zeros(3) if (s.safe_state or s.actuation_paused) else s.target_dipole_am2
        if self.hardware.windows:
            target = self.hardware.sensed_am2(target, now_s)   # what flows through the current sensor
        self._advance_coils(target / c.coil_gain_am2_per_a, now_s)
        if now_s >= self._next_telemetry_s and self.nmt_state == p.NMT_OPERATIONAL:
            self._count_late(now_s - self._next_telemetry_s, c.telemetry_period_s)
            self._send_telemetry()
            self._next_telemetry_s = _next_tick(self._next_telemetry_s, c.telemetry_period_s, now_s)
        if now_s >= self._next_heartbeat_s:
            self._count_late(now_s - self._next_heartbeat_s, c.heartbeat_period_s)
            self._send(self.protocol.encode(p.HEARTBEAT, {"NmtState": self.nmt_state}))
            self._next_heartbeat_s = _next_tick(self._next_heartbeat_s, c.heartbeat_period_s, now_s)

    def next_due_s(self, now_s: float) -> float:
        """The earliest time after now_s at which `update` has something to do: a periodic frame,
        the command timeout, an E2E check without new data, a held EMCY, a magnetometer window
        edge. An event-driven caller (lock-step on simulated time) wakes the board then."""
        c, s = self.config, self.state
        edge_s = self.hardware.next_edge_s(now_s) if self.hardware.windows else None
        if not self._powered_at(now_s):
            return edge_s if edge_s is not None else math.inf     # nothing happens until power returns
        due = [self._next_heartbeat_s] + ([edge_s] if edge_s is not None else [])
        if self.nmt_state == p.NMT_OPERATIONAL:
            due.append(self._next_telemetry_s)
        if self._last_command_s is not None and not s.safe_state:
            due.append(self._last_command_s + c.command_timeout_s + 1e-9)   # update() tests "longer than"
        if self._next_no_data_s is not None:
            due.append(self._next_no_data_s)
        if self._pending_emcy and self._last_emcy_s is not None:
            due.append(self._last_emcy_s + c.emcy_inhibit_s)
        if c.mag_window_period_s > 0 and c.mag_window_s > 0 and self._started_s is not None:
            phase_s = (now_s - self._started_s) % c.mag_window_period_s
            window_start_s = now_s - phase_s
            due += [edge for edge in (window_start_s + c.mag_window_s, window_start_s + c.mag_window_period_s)
                    if edge > now_s]
        return max(now_s, min(due))

    def _count_late(self, late_s: float, period_s: float) -> None:
        """A periodic frame more than half its period late: this process was not scheduled in
        time (a host overrun, which the flight side would otherwise take for a bus fault)."""
        if late_s > 0.5 * period_s:
            self.host_lateness.note(round(self.clock() * 1e9), late_s)

    def _enter_safe_state(self, now_s: float) -> None:
        self.state.safe_state = self.state.command_timeout = True
        # The stream is gone: whatever comes next starts a new one (E2E state reset after a timeout).
        self.e2e.reset()
        self._next_no_data_s = None
        log.warning("no valid command for %.3f s: coils off", self.config.command_timeout_s)
        self._emergency(p.EMCY_COMMAND_TIMEOUT, 0, None, now_s, ERROR_REGISTER_COMMUNICATION)

    def _in_mag_window(self, now_s: float) -> bool:
        c = self.config
        if c.mag_window_period_s <= 0 or c.mag_window_s <= 0:
            return False
        return (now_s - self._started_s) % c.mag_window_period_s < c.mag_window_s

    def _advance_coils(self, target_current_a: np.ndarray, now_s: float) -> None:
        # Exact discretisation of di/dt = (i_target - i) / tau over the elapsed time.
        dt_s = max(0.0, now_s - self._last_update_s)
        self._last_update_s = now_s
        decay = math.exp(-dt_s / self.config.coil_time_constant_s)
        s = self.state
        s.coil_current_a = target_current_a + (s.coil_current_a - target_current_a) * decay


_NMT_NAMES = {p.NMT_BOOT_UP: "boot_up", p.NMT_STOPPED: "stopped", p.NMT_OPERATIONAL: "operational",
              p.NMT_PRE_OPERATIONAL: "pre_operational"}


def _next_tick(previous_s: float, period_s: float, now_s: float) -> float:
    """The next periodic deadline after now, without bursts after a late wake-up."""
    nxt = previous_s + period_s
    return nxt if nxt > now_s else now_s + period_s
