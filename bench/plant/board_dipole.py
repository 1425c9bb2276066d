"""How the attitude plant learns the dipole the coils produced over step k, and the board's
reports it learns it from. One source for the run, chosen once by `board_dipole_source` from the
time model (docs/time-model.md):

- `ReportOfCommand` (lock-step, the bus and board on the wall clock, or no [can] at all): the
  board's report of the frame that carried step k's command (alive counter c, or a later frame
  c+1 .. c+7 carrying the same dipole if that one was lost); an external board's command
  acknowledgement (MTQ_TLM_SETPOINT, bench/plant/board_telemetry.py) is its report. Without
  [can] the command goes through the in-process board model.
- `ReportOfStep` (lock-step, the bus and board on simulated time, bench/bus/can/sim_window.py):
  the canbus process's report of step k (the coil drivers' output averaged over the step).
- `HeldReport` (real time): the board's latest report, held over the step (zero-order hold) and
  used only if current (DipoleAcceptance); a late command leaves the last one in force.

Every dipole passes DipoleAcceptance (bench/plant/mtq_acceptance.py) and is written to the
AppliedLog with the reason it was refused, if it was.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from bench.bus import keys
from bench.bus.can.sim_window import bus_on_simulated_time
from bench.bus.schemas import DipoleCommand, MtqApplied
from bench.bus.spill import StepColumn
from bench.plant.acceptance import CommandGate
from bench.plant.mtq_acceptance import DipoleAcceptance, board_dipole_without_bus
from bench.plant.mtq_chain import COUNTER_MODULO, COUNTER_WINDOW
from bench.plant.stepping import LoopBroken, WaitReport
from bench.runtime.node import NodeContext

# Lock-step on the wall-clock bus: how long the plant waits for the board's report of the frame
# that carried step k's command. On a bus with faults the frame may be lost: 0.5 s (far longer
# than a fault-free round trip, ~5 ms), then up to REPORT_WAIT_S for a later frame with the same
# dipole. On a fault-free bus the report always comes: the plant waits up to the run's command
# timeout, so that a starved host (user-mode Linux on a busy machine) slows the run instead of
# changing it.
EXACT_REPORT_WAIT_S = 0.5
REPORT_WAIT_S = 1.0


class BoardReports:
    """The board's applied-dipole reports as they arrive (Zenoh thread), for the plant's loop."""

    def __init__(self):
        self._cond = threading.Condition()
        self._reports: list[tuple[int, MtqApplied]] = []   # (received_ns, message)
        self.latest: tuple[int, MtqApplied] | None = None
        self.on_wait = None      # called while a wait goes on (a WaitReport's poll: the launcher hears of a long one)

    def add(self, message: MtqApplied) -> None:
        with self._cond:
            self.latest = (time.monotonic_ns(), message)
            self._reports.append(self.latest)
            del self._reports[:-64]
            self._cond.notify_all()

    def received(self) -> list[tuple[int, MtqApplied]]:
        """The last reports as (plant received ns, report), oldest first."""
        with self._cond:
            return list(self._reports)

    def wait_for_report(self, counter: int, expected_am2: np.ndarray, since_ns: int,
                        exact_wait_s: float = EXACT_REPORT_WAIT_S,
                        acknowledgements_only: bool = False) -> MtqApplied | None:
        """The board's report of the frame with alive counter `counter` carrying the expected
        dipole; if that frame was lost (faults), of a later frame (c+1 .. c+7) carrying it.
        acknowledgements_only: only reports of an applied command (an external board's echo with
        CommandApplied), not those of a set-point change without a command."""
        def answers(m: MtqApplied) -> bool:
            return np.array_equal(m.dipole_am2, expected_am2) and (not acknowledgements_only or bool(m.command_applied))

        exact = self._wait(lambda m: m.alive_counter == counter and answers(m), since_ns, exact_wait_s)
        if exact is not None:
            return exact
        return self._wait(lambda m: (m.alive_counter - counter) % COUNTER_MODULO < COUNTER_WINDOW and answers(m),
                          since_ns, REPORT_WAIT_S)

    def wait_for_step(self, step: int, timeout_s: float) -> MtqApplied | None:
        """Lock-step on simulated time: the report of the coils over plant step `step`."""
        return self._wait(lambda m: m.step == step, 0, timeout_s)

    def _wait(self, matches, since_ns: int, timeout_s: float) -> MtqApplied | None:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                for received_ns, message in self._reports:
                    if received_ns >= since_ns and matches(message):
                        return message
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                if self.on_wait is not None:
                    self.on_wait()
                self._cond.wait(min(remaining, 0.2))


class AppliedLog:
    """Per step: the dipole commanded, the board's report used, what was applied and why not.
    Columns of the recent steps in memory, the rest on disk (bench/bus/spill.py StepColumn): the
    plant's memory stays flat in a run of any length; `column[:n]` reads one back whole."""

    def __init__(self, n_steps: int):
        self.commanded = StepColumn(n_steps, (3,), np.float64, np.nan)
        self.reported = StepColumn(n_steps, (3,), np.float64, np.nan)
        self.counter = StepColumn(n_steps, (), np.int64, -1)
        self.refused = StepColumn(n_steps, (), bool, False)
        self.safe_state = StepColumn(n_steps, (), bool, False)
        self.board_applied_ns = StepColumn(n_steps, (), np.int64, -1)   # board set its coils (sense-to-torque)
        self.command_received_ns = StepColumn(n_steps, (), np.int64, -1)  # step k's command in (on time in real time)

@dataclass
class ReportOfCommand:
    """Lock-step on the wall clock: the board's report of the frame that carried step k's command.
    external_board: the BoardTelemetry of an external board (its echoes are the reports)."""

    ctx: NodeContext
    command_gate: CommandGate
    acceptance: DipoleAcceptance
    reports: BoardReports
    log: AppliedLog
    external_board: object | None = None

    def for_step(self, k: int, command: DipoleCommand | None, since_ns: int) -> tuple[np.ndarray, MtqApplied | None]:
        """since_ns: reports received from then on (the previous step's integration) can be this step's."""
        command = _every_step_commanded(command, k, self.command_gate)
        self.reports.on_wait = WaitReport(self.ctx, k, keys.ACTUATOR_MTQ).poll   # the launcher hears of a long wait
        scenario, acceptance, log, external_board = self.ctx.scenario, self.acceptance, self.log, self.external_board
        _log_command(log, k, command)
        if scenario.can is None:
            return _through_board_model(acceptance, log, k, command.dipole_am2)
        report = None
        if command.alive_counter >= 0:
            expected = board_dipole_without_bus(command.dipole_am2, scenario.can)
            exact_wait_s = EXACT_REPORT_WAIT_S if scenario.can.faults else scenario.run.command_timeout_s
            if external_board is not None:
                from bench.plant.board_telemetry import as_echoed

                expected = as_echoed(external_board.protocol, expected)
            report = self.reports.wait_for_report(command.alive_counter, expected, since_ns, exact_wait_s,
                                                  acknowledgements_only=external_board is not None)
            if report is None and external_board is not None and not external_board.reports:
                raise LoopBroken(_no_echo_message(external_board, k, exact_wait_s + REPORT_WAIT_S))
        if report is None:
            # No report of this command (never sent, or every frame lost for 2 s): coils as last
            # reported if that is current, else off. Counted as a refusal of the command.
            latest = self.reports.latest
            report = latest[1] if latest else None
            dipole, _ = acceptance.accept(report.dipole_am2, report.header.stamps_ns.get("applied")) if report else (np.zeros(3), None)
            acceptance.rejected["no_report"] += 1
            log.refused[k] = True
        else:
            dipole, reason = acceptance.accept(report.dipole_am2, None)
            log.refused[k] = reason is not None
            log.safe_state[k] = report.safe_state
        log.reported[k] = dipole
        return dipole, report


@dataclass
class ReportOfStep:
    """Lock-step on simulated time: the canbus process's report of the coils over step k."""

    ctx: NodeContext
    command_gate: CommandGate
    acceptance: DipoleAcceptance
    reports: BoardReports
    log: AppliedLog

    def for_step(self, k: int, command: DipoleCommand | None, since_ns: int) -> tuple[np.ndarray, MtqApplied | None]:
        command = _every_step_commanded(command, k, self.command_gate)
        self.reports.on_wait = WaitReport(self.ctx, k, keys.ACTUATOR_MTQ).poll
        timeout_s, log = self.ctx.scenario.run.command_timeout_s, self.log
        _log_command(log, k, command)
        report = self.reports.wait_for_step(k, timeout_s)
        if report is None:
            raise LoopBroken(f"step {k}: no report of the coils from the CAN bus within {timeout_s:g} s")
        dipole, reason = self.acceptance.accept(report.dipole_am2, None)
        # The step's command not applied (lost, rejected, the board in safe state): what the coils did
        # is still what the plant gets, and the step counts as refused.
        log.refused[k] = reason is not None or not report.command_applied
        log.safe_state[k] = report.safe_state
        log.reported[k] = dipole
        return dipole, report


@dataclass
class HeldReport:
    """Real time: the board's latest report, held over the step; a late command (None) leaves the
    last one in force."""

    ctx: NodeContext
    acceptance: DipoleAcceptance
    reports: BoardReports
    log: AppliedLog
    last_command: DipoleCommand | None = None

    def for_step(self, k: int, command: DipoleCommand | None, since_ns: int) -> tuple[np.ndarray, MtqApplied | None]:
        self.last_command = command = command or self.last_command
        log = self.log
        if command is not None:
            _log_command(log, k, command)
        if self.ctx.scenario.can is None:
            return _through_board_model(self.acceptance, log, k, command.dipole_am2 if command is not None else np.zeros(3))
        latest = self.reports.latest
        if latest is None:
            log.reported[k] = 0.0
            return np.zeros(3), None
        report = latest[1]
        dipole, reason = self.acceptance.accept(report.dipole_am2, report.header.stamps_ns.get("applied", latest[0]))
        log.refused[k] = reason is not None
        log.safe_state[k] = report.safe_state
        log.reported[k] = dipole
        return dipole, report


def _log_command(log: AppliedLog, k: int, command: DipoleCommand) -> None:
    log.commanded[k] = command.dipole_am2
    log.counter[k] = command.alive_counter


def _through_board_model(acceptance: DipoleAcceptance, log: AppliedLog, k: int, requested_am2) -> tuple[np.ndarray, None]:
    """No [can] section: the requested dipole through the in-process board model."""
    dipole, reason = acceptance.accept(board_dipole_without_bus(requested_am2, None), None)
    log.reported[k] = dipole
    log.refused[k] = reason is not None
    return dipole, None


def _every_step_commanded(command: DipoleCommand | None, k: int, command_gate: CommandGate) -> DipoleCommand:
    """Lock-step pairs every step with its command: none (only refused ones came) ends the run."""
    if command is None:
        raise LoopBroken(f"step {k}: every dipole command was refused ({dict(command_gate.rejected)})")
    return command


def board_dipole_source(ctx: NodeContext, command_gate: CommandGate, acceptance: DipoleAcceptance,
                        reports: BoardReports, log: AppliedLog,
                        external_board=None) -> ReportOfCommand | ReportOfStep | HeldReport:
    """The run's source of the applied dipole (the module docstring); command_gate: the plant's
    output stage of dipole commands (a lock-step run ends when it refused every one of a step's)."""
    if not ctx.time_model.lock_step:
        return HeldReport(ctx, acceptance, reports, log)
    if bus_on_simulated_time(ctx.scenario):
        return ReportOfStep(ctx, command_gate, acceptance, reports, log)
    return ReportOfCommand(ctx, command_gate, acceptance, reports, log, external_board)


def _no_echo_message(telemetry, k: int, waited_s: float) -> str:
    import bench.bus.can.protocol as p

    heard = telemetry.frames[p.TLM_DIPOLE] + telemetry.frames[p.TLM_COIL]
    return (f"step {k}: no {p.TLM_SETPOINT} from the external board within {waited_s:g} s ({heard} of its telemetry "
            f"frames heard, {sum(telemetry.refused.values())} refused): lock-step with an external board needs the "
            f"board's command acknowledgement; a board without it runs in real time only (docs/can-bus.md)")
