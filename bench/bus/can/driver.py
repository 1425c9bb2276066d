"""Flight-side magnetorquer driver: what the on-board computer runs to command the board.

`command(dipole_am2)` sends one E2E-protected command; `poll()` reads what the board sent and
checks the deadlines; `health()` says whether the board can be trusted. Every anomaly becomes a
`FaultEvent` with the time it was detected and the driver's estimate of how long after the fault
it noticed (the latency): a lost heartbeat counts from when the next one was due, a bad frame
from when it was on the bus, a rejected command from when the driver sent it.

What the driver detects, and from what evidence:
- board lost / back: heartbeat (CANopen consumer) and telemetry deadlines; as the NMT master it
  starts the board (NMT start; MTQ_NMT_AUTH on the secoc profile) whenever a heartbeat says
  boot-up or pre-operational;
  the heartbeat, the EMCY and plain NMT are canopen's: a `RemoteNode` built from mtq.eds on a
  passive `canopen.Network` (`node`), fed the board's heartbeat and EMCY frames from `handle`
  (no listener thread, no timer: the deadlines stay on the driver's clock, real or simulated);
- corrupted, repeated, out-of-sequence or lost telemetry: the E2E check of each telemetry frame;
- commands the board rejected (corrupted, repeated, out of sequence, re-synchronising, forged,
  stale, wrong length), commands lost on the way (the board's E2E check saw the counter jump) and
  its command timeout: the board's emergency frames;
- spoofed or replayed commands: a frame with the command identifier that this driver did not
  send (a CAN controller never receives its own frames, so any such frame has another source);
  likewise an NMT frame (plain or authenticated): the driver is the bus's only NMT master;
- a coil that does not follow its commands (open, stuck) or a command corrupted before
  protection: the applied dipole the current sensors report against the range the commands allow
  (`_check_plausibility`); a coil wired backwards or weaker than its datasheet, after the sensor,
  is not for the driver to see (the FDIR actuator monitor's, from the dynamics);
- its own controller's error-passive, bus-off and restart: SocketCAN error frames; back from
  bus-off also when the board is heard again after the ISO 11898 recovery time (128 x 11
  recessive bits at the bitrate), so that one stray bus-off error frame cannot leave it bus-off;
  every return to error-active is reported;
- its own lateness: a command period that started more than half a period late is a host
  overrun (counted and reported apart from bus faults); a board command timeout that followed a
  gap in the driver's own commands is reported as caused by the host, not the bus.

`health().ok` is false while the board is lost, in safe state or bus-off, while either telemetry
frame is overdue (each has its own deadline; the applied dipole then shown is the last heard, and
`telemetry_fresh` is false), and for `fault_hold_s` after a spoofed command, an implausible applied dipole or a
corrupted, repeated or out-of-sequence telemetry frame.
"""
from __future__ import annotations

import contextlib
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Callable

import can
import canopen
import numpy as np

from bench.bus.can import canopen_od, errors
from bench.bus.can import protocol as p
from bench.bus.can.board import coil_driver_dipole
from bench.bus.can.config import BoardConfig, CanConfig, DriverConfig

MAX_EVENTS_KEPT = 10_000
RECENT_COMMANDS = 64
EMCY_KEPT = 64     # canopen's EMCY consumer keeps a log; a long run keeps only this many


@dataclass(frozen=True)
class FaultEvent:
    kind: str                 # see KINDS
    detected_ns: int          # when detected: time.monotonic_ns(), or bus time on simulated time (sim_window)
    latency_s: float          # driver's estimate of detection latency (see module docstring)
    frame: str = ""
    detail: str = ""


KINDS = (
    "heartbeat_timeout", "heartbeat_resumed", "board_rebooted", "telemetry_timeout",
    "telemetry_corrupted", "telemetry_repeated", "telemetry_out_of_sequence", "telemetry_lost",
    "command_rejected", "command_lost", "board_command_timeout", "spoofed_command", "actuator_mismatch",
    "error_warning", "error_passive", "bus_off", "bus_restarted", "error_active", "host_overrun",
    "board_error_reset",
)
# Events after which the board's word cannot be trusted for DriverConfig.fault_hold_s.
HEALTH_FAULTS = frozenset({"spoofed_command", "actuator_mismatch", "telemetry_corrupted", "telemetry_repeated",
                           "telemetry_out_of_sequence"})


@dataclass
class BoardHealth:
    """What the driver knows about the board now; `ok` is the one bit a controller needs."""
    alive: bool
    nmt_state: int | None
    safe_state: bool
    actuation_paused: bool
    applied_dipole_am2: list[float]
    coil_current_a: list[float]
    temperature_c: float | None
    heartbeat_age_s: float | None
    bus_state: str
    events: dict[str, int]
    bad_frames: dict[str, int]
    telemetry_fresh: bool = True          # every telemetry frame within its deadline
    recent_faults: list[str] = field(default_factory=list)   # HEALTH_FAULTS within fault_hold_s
    host_overruns: int = 0                # command periods the driver itself started late

    @property
    def ok(self) -> bool:
        return (self.alive and self.nmt_state == p.NMT_OPERATIONAL and not self.safe_state
                and self.bus_state != errors.ErrorState.BUS_OFF.value and self.telemetry_fresh and not self.recent_faults)


@dataclass
class _Sent:
    counter: int
    dipole_am2: np.ndarray      # the set-point it gives the board's coil drivers (DBC scaling, DAC step, limit)
    sent_s: float


@dataclass
class _Deadline:
    """A frame expected every period_s; late by timeout_s means lost."""
    period_s: float
    timeout_s: float
    last_s: float | None = None
    lost: bool = False


class MagnetorquerDriver:
    """One board's driver. Not thread-safe: command, poll and health from the owner's loop."""

    def __init__(self, bus: can.BusABC, config: DriverConfig, board: BoardConfig, protocol: p.Protocol,
                 clock: Callable[[], float] = time.monotonic, wall_clock: Callable[[], float] = time.time,
                 bitrate_bps: int = 1_000_000, event_clock_ns: Callable[[], int] = time.monotonic_ns):
        if protocol.profile == "secoc" and protocol.key is None:
            raise ValueError("the secoc profile needs the key in the driver's Protocol "
                             "(can.security.key_hex is empty: run it from the launcher's scenario.json)")
        self.bus = bus
        self.config = config
        self.board = board
        self.protocol = protocol
        self.clock = clock
        self.wall_clock = wall_clock
        self.event_clock_ns = event_clock_ns
        self.events: deque[FaultEvent] = deque(maxlen=MAX_EVENTS_KEPT)
        self.event_counts: Counter = Counter()
        self.sent_frames = 0                 # commands (NMT frames are counted in nmt_sent)
        self.nmt_sent: Counter = Counter()
        self.last_sent_ns: int | None = None
        self.received: Counter = Counter()   # every frame heard, by name (frame accounting)
        self._counter = 0
        self._sent: deque[_Sent] = deque(maxlen=RECENT_COMMANDS)
        self._command_ids = {protocol.frame_ids[name] for name in p.COMMANDS}
        self._nmt_ids = {protocol.frame_ids[name] for name in (p.NMT, p.NMT_AUTH)}
        self._rx_e2e = {name: p.E2EReceiver(config.max_delta_counter) for name in (p.TLM_DIPOLE, p.TLM_COIL)}
        self._heartbeat = _Deadline(board.heartbeat_period_s, board.heartbeat_period_s * config.heartbeat_timeout_periods)
        self._telemetry = {name: _Deadline(board.telemetry_period_s, board.telemetry_period_s * config.telemetry_timeout_periods)
                           for name in (p.TLM_DIPOLE, p.TLM_COIL)}
        self._fault_seen_s: dict[str, float] = {}
        self._bus_off_s: float | None = None
        self.bus_off_recovery_s = errors.BUS_OFF_RECOVERY_BITS / bitrate_bps
        self.host_overruns = 0
        self.frames_in_last_poll = 0
        self._last_command_s: float | None = None
        self._largest_gap_s = 0.0       # longest time between two of our commands, since the last timeout
        self._nmt_state: int | None = None
        self._tlm: dict[str, dict] = {}
        self._bus_state = errors.ErrorState.ACTIVE
        self._mismatch_since_s: float | None = None
        # Lock-step on simulated time (windowed_driver.py): a reply the driver owes (the NMT start
        # for a board that booted) leaves only at the next window's start, so it is built then
        # (`send_owed`), with that time's freshness value; built when the boot-up was heard, it was
        # a step old when it left (100 ms at 10 Hz), and the board refused it as stale, for good.
        self.defer_replies = False
        self._owed_nmt: int | None = None
        self._coils_off_s: float | None = None   # last telemetry that said the coils were off
        self._start_s = clock()
        self._new_events: list[FaultEvent] = []
        self._now_s = self._start_s      # the time of the frame being handled (canopen's callbacks)
        self.canopen_network = canopen.Network(bus)
        self.node = canopen.RemoteNode(protocol.node_id, canopen_od.object_dictionary(protocol.node_id))
        self.canopen_network.add_node(self.node)
        self.node.nmt.add_heartbeat_callback(self._on_heartbeat)
        self.node.emcy.add_callback(self._on_emergency)

    @classmethod
    def from_config(cls, bus: can.BusABC, config: CanConfig, **clocks) -> "MagnetorquerDriver":
        """The driver for a scenario's [can] section, on an open bus (its flight channel)."""
        return cls(bus, config.driver, config.board, config.protocol(), bitrate_bps=config.bitrate_bps, **clocks)

    # --- commanding -----------------------------------------------------------------------
    def command(self, dipole_am2, mode: int = p.MODE_DIPOLE) -> int:
        """Send one command; returns its alive counter. Raises can.CanError if the bus refuses it.

        `last_sent_ns` is then the monotonic time it went to the bus (the "can_sent" stamp).
        """
        counter = self._counter
        sent_s = self.clock()
        msg = self.protocol.command(dipole_am2, counter, mode, sent_s=sent_s if self.protocol.profile == "secoc" else None)
        self.last_sent_ns = time.monotonic_ns()
        self.bus.send(msg)
        self._counter = (counter + 1) % p.COUNTER_MODULO
        self.sent_frames += 1
        self._sent.append(_Sent(counter, self._setpoint_am2(msg, mode), sent_s))
        if self._last_command_s is not None:
            self._largest_gap_s = max(self._largest_gap_s, sent_s - self._last_command_s)
        self._last_command_s = sent_s
        return counter

    def _setpoint_am2(self, msg: can.Message, mode: int) -> np.ndarray:
        """What the board's coil drivers are set to for this command: the frame's values (DBC
        scaling, 1e-4 A m^2) quantised to the DAC step and saturated, as the board does."""
        frame = self.protocol.decode(msg)
        if mode != p.MODE_DIPOLE or frame is None:
            return np.zeros(3)
        return coil_driver_dipole(np.array([frame.signals[f"Dipole{a}"] for a in p.AXES]), self.board)[0]

    # --- receiving ------------------------------------------------------------------------
    def poll(self, timeout_s: float = 0.0, max_frames: int = 1000, lock=None) -> list[FaultEvent]:
        """Handle the frames that arrived (waiting up to timeout_s for the first), check deadlines.

        Returns the events detected since the previous call (during it, and in between: a host
        overrun the command loop reported). lock: held while frames are handled, not while waiting
        for the first (CommandLoop: another thread may send a command meanwhile).
        """
        msg = self.bus.recv(timeout=timeout_s)
        with lock if lock is not None else contextlib.nullcontext():
            handled = 0
            while msg is not None:
                self.handle(msg)
                handled += 1
                if handled >= max_frames:
                    break  # a flood must not starve the deadline checks below
                msg = self.bus.recv(timeout=0.0)
            self.frames_in_last_poll = handled
            self.check_deadlines(self.clock())
            return self.take_events()

    def take_events(self) -> list[FaultEvent]:
        """The events detected since the last `poll` or `take_events` (a caller that hands the
        driver its frames with `handle` and checks its deadlines itself: lock-step)."""
        events, self._new_events = self._new_events, []
        return events

    def handle(self, msg: can.Message) -> None:
        now_s = self.clock()
        self.received[p.frame_kind(self.protocol, msg)] += 1
        if msg.is_error_frame:
            self._on_error_frame(msg)
            return
        if self._bus_state is errors.ErrorState.BUS_OFF and now_s - self._bus_off_s >= self.bus_off_recovery_s:
            # A controller in bus-off hears nothing: a frame heard after the recovery time means it
            # is back, whether or not a restart was reported (a stray bus-off error frame).
            self._bus_state = errors.ErrorState.ACTIVE
            self._event("error_active", 0.0, detail="frames heard after bus-off recovery time")
        if msg.arbitration_id in self._command_ids and not msg.is_extended_id:
            # Our own identifier, sent by someone else.
            self._event("spoofed_command", self._wire_age_s(msg), p.CMD, f"data {bytes(msg.data).hex()}")
            return
        if msg.arbitration_id in self._nmt_ids and not msg.is_extended_id:
            # NMT from another master: the board obeys it only if authentic (secoc), but it is an attack.
            self._event("spoofed_command", self._wire_age_s(msg), p.frame_kind(self.protocol, msg),
                        f"data {bytes(msg.data).hex()}")
            return
        frame = self.protocol.decode(msg)
        if frame is None:
            return
        if frame.name in (p.HEARTBEAT, p.EMCY):
            # Checked by the DBC above (length, a known NMT state); canopen's NMT master and EMCY
            # consumer parse them and call _on_heartbeat / _on_emergency.
            self._now_s = now_s
            self.canopen_network.notify(msg.arbitration_id, bytes(msg.data), msg.timestamp)
        elif frame.name in self._rx_e2e:
            self._on_telemetry(frame, msg, now_s)

    def _on_heartbeat(self, state: int) -> None:
        """canopen's NMT master heard a heartbeat (state as sent: 0 is boot-up, which its
        `node.nmt.state` already shows as pre-operational)."""
        now_s = self._now_s
        if state == p.NMT_BOOT_UP:
            if self._nmt_state is not None:
                self._event("board_rebooted", 0.0, p.HEARTBEAT)
            # A node that boots starts its own alive counters again, and its coils from rest.
            for receiver in self._rx_e2e.values():
                receiver.reset()
            self._mismatch_since_s = None
        self._nmt_state = state
        self._arrived(self._heartbeat, now_s, "heartbeat_resumed", p.HEARTBEAT)
        if self.config.nmt_auto_start and state in (p.NMT_BOOT_UP, p.NMT_PRE_OPERATIONAL):
            if self.defer_replies:
                self._owed_nmt = p.NMT_START
            else:
                self.nmt(p.NMT_START)

    def send_owed(self) -> None:
        """Send the reply owed since the last window (defer_replies), built now."""
        if self._owed_nmt is not None:
            command, self._owed_nmt = self._owed_nmt, None
            self.nmt(command)

    def nmt(self, command: int) -> None:
        """Send a CiA 301 NMT command (p.NMT_START, ...) to this driver's board."""
        try:
            if self.protocol.profile == "e2e":
                self.node.nmt.send_command(command)    # plain CiA 301 NMT, identifier 0
            else:
                self.bus.send(self.protocol.nmt(command, sent_s=self.clock()))   # MTQ_NMT_AUTH (SecOC)
            self.nmt_sent[command] += 1
        except can.CanError:
            self.nmt_sent["send_failed"] += 1

    def _on_emergency(self, emcy: canopen.emcy.EmcyError) -> None:
        """canopen's EMCY consumer heard an emergency; its manufacturer bytes (mtq.dbc's MTQ_EMCY)
        are E2eStatus, RejectedCounter and RejectedFrames."""
        for kept in (self.node.emcy.log, self.node.emcy.active):
            del kept[:-EMCY_KEPT]
        code = emcy.code
        if code == p.EMCY_NO_ERROR:
            self._event("board_error_reset", 0.0, p.EMCY, f"error register {emcy.register:#04x}")
        elif code == p.EMCY_COMMAND_TIMEOUT:
            # Our own silence longer than the board's timeout is the host's doing, not the bus's.
            host = self._largest_gap_s > self.board.command_timeout_s
            detail = f"cause host_overrun: driver command gap {self._largest_gap_s * 1e3:.1f} ms" if host else "cause bus"
            if self._sent and self._last_command_s is not None and self.clock() - self._last_command_s > self.board.command_timeout_s:
                detail = "cause driver stopped commanding"
            self._event("board_command_timeout", self._age_s(emcy.timestamp), p.EMCY, detail)
            self._largest_gap_s = 0.0
        elif code in (p.EMCY_E2E_CHECK_FAILED, p.EMCY_PDO_LENGTH):
            status, counter = emcy.data[0], emcy.data[1]
            if code == p.EMCY_E2E_CHECK_FAILED and status == p.E2EStatus.OK_SOME_LOST:
                self._event("command_lost", self._command_age_s(counter, emcy.timestamp), p.EMCY,
                            f"commands before counter {counter} lost")
                return
            if code == p.EMCY_PDO_LENGTH:
                reason = "WRONG_LENGTH"
            else:
                reason = p.E2EStatus(status).name if status in p.E2EStatus._value2member_map_ else f"status {status}"
            self._event("command_rejected", self._command_age_s(counter, emcy.timestamp), p.EMCY,
                        f"{reason} counter {counter}")

    def _on_telemetry(self, frame: p.Frame, msg: can.Message, now_s: float) -> None:
        status = self._rx_e2e[frame.name].check(frame.counter, frame.crc_ok)
        kind = {p.E2EStatus.WRONG_CRC: "telemetry_corrupted", p.E2EStatus.REPEATED: "telemetry_repeated",
                p.E2EStatus.WRONG_SEQUENCE: "telemetry_out_of_sequence",
                p.E2EStatus.OK_SOME_LOST: "telemetry_lost"}.get(status)
        if kind is not None:
            self._event(kind, self._wire_age_s(msg), frame.name, f"counter {frame.counter}")
        if not status.accepted:
            return
        self._tlm[frame.name] = frame.signals
        self._arrived(self._telemetry[frame.name], now_s, None, frame.name)
        if frame.name == p.TLM_DIPOLE:
            # judged at the time the frame was on the bus (its wire stamp), the time it reports
            self._check_plausibility(frame.signals, now_s, now_s - min(max(self._wire_age_s(msg), 0.0), now_s - self._start_s))

    def _on_error_frame(self, msg: can.Message) -> None:
        state, restarted = errors.read_error_frame(msg)
        if restarted:
            self._bus_state = errors.ErrorState.ACTIVE
            self._event("bus_restarted", self._wire_age_s(msg))
            return
        if state is not self._bus_state:
            # Every change, the return to error-active included (SocketCAN: CAN_ERR_CRTL_ACTIVE).
            self._event(state.value, self._wire_age_s(msg), detail=f"tec {msg.data[6] if len(msg.data) > 6 else '?'}")
        if state is errors.ErrorState.BUS_OFF and self._bus_state is not errors.ErrorState.BUS_OFF:
            self._bus_off_s = self.clock()
        self._bus_state = state

    # --- deadlines and plausibility -------------------------------------------------------
    def check_deadlines(self, now_s: float) -> None:
        deadlines = [(self._heartbeat, "heartbeat_timeout", p.HEARTBEAT)]
        deadlines += [(deadline, "telemetry_timeout", name) for name, deadline in self._telemetry.items()]
        for deadline, kind, frame in deadlines:
            # Before the first frame, count from the driver's start: a board that never comes
            # up is as lost as one that went quiet.
            last_s = deadline.last_s if deadline.last_s is not None else self._start_s
            if not deadline.lost and now_s - last_s > deadline.timeout_s:
                deadline.lost = True
                self._event(kind, now_s - (last_s + deadline.period_s), frame)

    def _arrived(self, deadline: _Deadline, now_s: float, resumed_kind: str | None, frame: str) -> None:
        if deadline.lost and resumed_kind is not None:
            self._event(resumed_kind, 0.0, frame)
        deadline.lost = False
        deadline.last_s = now_s

    def _check_plausibility(self, tlm: dict, now_s: float, sampled_s: float) -> None:
        """The applied dipole the current sensors report at `sampled_s` (the frame's time on the
        bus, on this driver's clock), outside what the coils can be doing then, for too long. A
        coil's current follows its driver's set-point with a first-order lag (L/R), so whatever the
        commands did, it is a weighted mean of the set-points since it last settled: on each axis
        between the least and the greatest of the set-points of the newest command sent settle_s
        before the sample and of every command after it up to the sample (and zero after the coils
        were off). Each set-point is the board's own (DBC scaling, DAC step, limit), so the
        tolerance covers the telemetry's resolution, not the board's quantisation.

        Judged as it was before (the applied dipole against each command, at the frame's arrival),
        a coil commanded faster than it settles was found "far from every command" while it did
        just what it was told: a lock-step run on the wall clock sends a new dipole every ~4 ms of
        wall time to coils of 5 ms, and attitude_slew_milqr raised 2-3 actuator_mismatch a run
        (issue 45)."""
        if tlm["SafeState"] or tlm["ActuationPaused"] or not self._sent:
            self._mismatch_since_s = None
            self._coils_off_s = now_s
            return
        applied = np.array([tlm[f"AppliedDipole{a}"] for a in p.AXES])
        settled = [s for s in self._sent if sampled_s - s.sent_s >= self.config.settle_s]
        if not settled:
            return
        candidates = [settled[-1].dipole_am2] + [s.dipole_am2 for s in self._sent
                                                 if settled[-1].sent_s < s.sent_s <= sampled_s]
        if self._coils_off_s is not None and now_s - self._coils_off_s < self.config.settle_s:
            candidates.append(np.zeros(3))          # the coils were off a moment ago: still rising
        reachable = np.array(candidates)
        tolerance = self.config.dipole_tolerance_am2
        outside = (applied < reachable.min(axis=0) - tolerance) | (applied > reachable.max(axis=0) + tolerance)
        if not outside.any():
            self._mismatch_since_s = None
            return
        if self._mismatch_since_s is None:
            self._mismatch_since_s = now_s
        elif now_s - self._mismatch_since_s >= self.config.mismatch_time_s:
            axes = "".join(a for a, out in zip(p.AXES, outside) if out).lower()
            self._event("actuator_mismatch", now_s - self._mismatch_since_s + self.config.settle_s, p.TLM_DIPOLE,
                        f"axis {axes}: applied {np.round(applied, 4).tolist()} commanded {np.round(candidates[-1], 4).tolist()}")
            self._mismatch_since_s = None  # report again if it persists another mismatch_time_s

    # --- reporting ------------------------------------------------------------------------
    def _event(self, kind: str, latency_s: float, frame: str = "", detail: str = "") -> None:
        event = FaultEvent(kind, self.event_clock_ns(), max(0.0, latency_s), frame, detail)
        if kind in HEALTH_FAULTS:
            self._fault_seen_s[kind] = self.clock()
        self.events.append(event)
        self._new_events.append(event)
        self.event_counts[kind] += 1

    def _wire_age_s(self, msg: can.Message) -> float:
        return self._age_s(msg.timestamp)

    def _age_s(self, timestamp: float) -> float:
        # python-can stamps a received frame with the (wall-clock) time it was on the wire.
        return self.wall_clock() - timestamp if timestamp else 0.0

    def _command_age_s(self, counter: int, timestamp: float) -> float:
        for sent in reversed(self._sent):
            if sent.counter == counter:
                return self.clock() - sent.sent_s
        return self._age_s(timestamp)

    def health(self) -> BoardHealth:
        now_s = self.clock()
        # The last values heard; telemetry_fresh (and ok) say whether they are still the board's.
        dipole = self._tlm.get(p.TLM_DIPOLE, {})
        coil = self._tlm.get(p.TLM_COIL, {})
        recent = sorted(k for k, t in self._fault_seen_s.items() if now_s - t < self.config.fault_hold_s)
        return BoardHealth(
            alive=self._heartbeat.last_s is not None and not self._heartbeat.lost,
            nmt_state=self._nmt_state,
            safe_state=bool(dipole.get("SafeState", True)),
            actuation_paused=bool(dipole.get("ActuationPaused", False)),
            applied_dipole_am2=[float(dipole.get(f"AppliedDipole{a}", 0.0)) for a in p.AXES],
            coil_current_a=[float(coil.get(f"CoilCurrent{a}", 0.0)) for a in p.AXES],
            temperature_c=float(coil["Temperature"]) if coil else None,
            heartbeat_age_s=now_s - self._heartbeat.last_s if self._heartbeat.last_s is not None else None,
            bus_state=self._bus_state.value,
            events=dict(self.event_counts),
            bad_frames=dict(self.protocol.bad.counts),
            telemetry_fresh=all(d.last_s is not None and not d.lost for d in self._telemetry.values()),
            recent_faults=recent,
            host_overruns=self.host_overruns,
        )

    def host_overrun(self, late_s: float) -> None:
        """The owner's loop woke late_s late, for a command period or after a poll (CommandLoop
        calls this)."""
        self.host_overruns += 1
        self._event("host_overrun", late_s, p.CMD, f"loop woke {late_s * 1e3:.1f} ms late")


class CommandLoop:
    """Commands the board with the current dipole, polling in between, in one of AUTOSAR COM's
    transmission modes: "cyclic" (every command period), "on_change" (at once when `set_dipole`
    gives a dipole), or "mixed" (both: at once, and every period as a keep-alive).

    The board goes to its safe state when commands stop for command_timeout_s (0.1 s by default),
    so the flight side must command at its own rate, whatever the rate of the law that decides the
    dipole: run this on its own thread and hand it the dipole with `set_dipole`, or give it
    `dipole_at(t_s)` (seconds since the first command; a scenario's `CanConfig.dipole_at`).
    With `first_command_by_law`, nothing is commanded until the first `set_dipole` (the loop only
    polls until then): the bus carries the law's commands from the first one on, so the first
    command frame, which arms the bus model's faults, is the loop's first step and a fault's
    `start_s` counts from it, not from the moment this process happened to start.
    `health` is a snapshot other threads may read; `on_command(counter, dipole_am2, sent_ns)` and
    `on_events(events)` run on the thread that sent (the loop's, or the caller of `set_dipole` in
    the on-change modes). The driver itself is not thread-safe: every use of it takes `_lock`, and
    the loop waits for frames outside it, so a change goes out without waiting for the loop.
    """

    def __init__(self, driver: MagnetorquerDriver, period_s: float,
                 dipole_at: Callable[[float], list[float]] | None = None,
                 on_command: Callable[[int, list[float], int], None] | None = None,
                 on_events: Callable[[list[FaultEvent]], None] | None = None,
                 transmission: str = "cyclic", first_command_by_law: bool = False):
        if transmission not in ("cyclic", "on_change", "mixed"):
            raise ValueError(f"transmission must be cyclic, on_change or mixed, not {transmission!r}")
        self.driver = driver
        self.period_s = period_s
        self.dipole_at = dipole_at
        self.on_command = on_command
        self.on_events = on_events
        self.transmission = transmission
        self._awaiting_first_dipole = first_command_by_law
        self.health: BoardHealth = driver.health()
        self.started_s: float | None = None
        self._dipole_am2 = [0.0, 0.0, 0.0]
        self._lock = threading.Lock()
        self._running = False
        self._next_command_s = 0.0

    def set_dipole(self, dipole_am2) -> None:
        self._dipole_am2 = [float(x) for x in dipole_am2]   # one reference swap: safe across threads
        if self.transmission == "cyclic" or not self._running:
            self._awaiting_first_dipole = False
        else:
            with self._lock:   # the flag and the frame together: the loop never sends this dipole twice
                self._awaiting_first_dipole = False
                now = self.driver.clock()
                self._command(now)
                self._next_command_s = now + self.period_s   # the keep-alive counts from the change

    def run(self, stop=None, duration_s: float | None = None, commanding: bool = True) -> None:
        """Until `stop` is set or `duration_s` has passed; commanding=False only listens."""
        clock = self.driver.clock
        now = clock()
        end = now + duration_s if duration_s is not None else float("inf")
        cyclic = commanding and self.transmission != "on_change"
        self._next_command_s = now
        self._running = commanding
        wake_by_s = None      # when the last poll should have returned at the latest
        try:
            while now < end and not (stop is not None and stop.is_set()):
                with self._lock:
                    waiting = self._awaiting_first_dipole
                    due = cyclic and not waiting and now >= self._next_command_s
                    late_s = 0.0
                    if due:
                        late_s = now - self._next_command_s
                    elif wake_by_s is not None and self.driver.frames_in_last_poll == 0:
                        # A poll that handled no frame returned this late: the scheduler, not frame work.
                        late_s = now - wake_by_s
                    if late_s > 0.5 * self.period_s and not waiting:
                        self.driver.host_overrun(late_s)   # our thread was late: the host, not the bus
                    if due:
                        self._command(now)
                        self._next_command_s += self.period_s
                        if self._next_command_s < now:   # woke late: skip the missed slots rather than burst
                            self._next_command_s = now + self.period_s
                    if waiting:   # the first cyclic slot is the moment the law's first dipole arrives
                        self._next_command_s = now
                    until = min(self._next_command_s, end) if cyclic and not waiting else end
                    timeout_s = max(0.0, min(until - clock(), 0.01))
                    wake_by_s = clock() + timeout_s
                events = self.driver.poll(timeout_s=timeout_s, lock=self._lock)
                if events and self.on_events is not None:
                    self.on_events(events)
                self.health = self.driver.health()
                now = clock()
        finally:
            self._running = False

    def _command(self, now_s: float) -> None:
        if self.started_s is None:
            self.started_s = now_s
        dipole = self.dipole_at(now_s - self.started_s) if self.dipole_at is not None else self._dipole_am2
        counter = self.driver.command(dipole)
        if self.on_command is not None:
            self.on_command(counter, dipole, self.driver.last_sent_ns)
