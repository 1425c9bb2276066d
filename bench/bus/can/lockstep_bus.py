"""The bus and the board on simulated time, one plant step at a time (lock-step attitude runs).

The canbus process runs this in lock-step when the bus is on simulated time
(bench/bus/can/sim_window.py). It holds the same `BusModel`, `FaultInjector` and
`MagnetorquerBoard` the real-time processes run, on one simulated clock: for each step it takes
the flight side's frames at their simulated times, wakes at every event (a frame's last bit, a
board timer), and gives back the frames the flight side heard and what the coils did. The board
shares the process with the bus so that its frames are arbitrated with the flight side's at
their exact times, which a board in another process could only match by trading messages for
every frame.

What the plant integrates over step k is the time average of the coil drivers' output
(`output_dipole_am2`: zero in safe state and magnetometer windows) over the step as the board
sees it: from the moment the step's first command frame reached the board, for one step length
(the last stretch, which falls in the next step, held at the output at the step's end). A
fault-free step gives exactly the commanded dipole after quantisation and saturation, as the
in-process loop does; a step with coils off for part of it gives the average. When that frame
never reaches the board unchanged (lost, delayed, altered), the average is over the step itself.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.bus.can import protocol as p
from bench.bus.can.board import AppliedCommand, MagnetorquerBoard, applied_record
from bench.bus.can.busmodel import BOARD, FLIGHT, BusModel
from bench.bus.can.config import CanConfig
from bench.bus.can.injector import FaultInjector
from bench.bus.can.sim_window import SimFrame, to_can_message, to_sim_frame
from bench.bus.can.simbus import SimBus, SimClock
from bench.bus.spill import SpilledJson


@dataclass
class StepCoils:
    """What the board's coils did during one step."""
    dipole_am2: np.ndarray          # time average of the coil drivers' output over the step (see module)
    safe_state: bool                # coils in safe state at the step's end
    actuation_paused: bool          # in a magnetometer window at the step's end
    coil_current_a: np.ndarray      # at the step's end
    applied_counter: int | None     # alive counter of the first command the board applied in the step
    off_fraction: float             # part of the step with the coil drivers off


class StepAverage:
    """The coil drivers' output over one step, as the plant integrates it (module docstring)."""

    def __init__(self, start_ns: int, end_ns: int):
        self.start_ns, self.step_ns = start_ns, max(1, end_ns - start_ns)
        self.command_ns: int | None = None    # the step's command frame reached the board unchanged
        self.whole = np.zeros(3)              # integral over the step (A m^2 ns)
        self.after = np.zeros(3)              # the same from command_ns on
        self.outputs_after: list[np.ndarray] = []   # the distinct outputs from command_ns on

    def hold(self, output_am2: np.ndarray, duration_ns: int) -> None:
        self.whole += output_am2 * duration_ns
        if self.command_ns is not None:
            self.after += output_am2 * duration_ns
            if not self.outputs_after or not np.array_equal(self.outputs_after[-1], output_am2):
                self.outputs_after.append(output_am2)

    def dipole_am2(self, output_at_end_am2: np.ndarray) -> np.ndarray:
        if self.command_ns is None:        # no command reached the board: the coils over the step itself
            return self.whole / self.step_ns
        if all(np.array_equal(o, output_at_end_am2) for o in self.outputs_after):
            return output_at_end_am2.copy()   # held from the command on: exactly it (a sum of parts may round)
        # From the command on for one step length; the stretch past the step's end at its end's output.
        return (self.after + output_at_end_am2 * (self.command_ns - self.start_ns)) / self.step_ns


class LockStepBus:
    """`advance(start_ns, end_ns, frames)`: one step of the flight side's frames through the bus
    model and the board; returns the frames the flight side heard and the step's `StepCoils`."""

    def __init__(self, config: CanConfig, seed: int, capture=None):
        self.config = config
        self.seed = seed
        self.capture = capture
        self.clock: SimClock | None = None
        # Every command the board applied, as can/board.json lists it (`applied_record`): on disk as
        # they come (bench/bus/spill.py), so a lock-step run of any length keeps a flat memory.
        self.applied = SpilledJson()
        self._applied_in_step: list[AppliedCommand] = []
        self._command_id = config.protocol().frame_ids[config.protocol().command_name]

    def _boot(self, t_ns: int) -> None:
        config = self.config
        self.clock = SimClock(t_ns)
        outsider = p.Protocol(config.node_id, config.security.profile)     # the injector has no key
        self.injector = FaultInjector(config.faults, outsider, seed=self.seed, max_dipole_am2=config.board.max_dipole_am2)
        self.model = BusModel(self.injector, outsider, t_ns, bitrate_bps=config.bitrate_bps,
                              tx_queue_frames=config.tx_queue_frames, capture=self.capture,
                              to_wall_s=lambda ns: ns / 1e9)
        self.buses = {FLIGHT: SimBus(self.model, FLIGHT, self.clock), BOARD: SimBus(self.model, BOARD, self.clock)}
        self.board = MagnetorquerBoard(self.buses[BOARD], config.board, config.protocol(), clock=self.clock,
                                       on_applied=self._on_applied, security=config.security,
                                       hardware=self.injector.hardware)
        self.board.start(self.clock())

    def advance(self, start_ns: int, end_ns: int, frames: list[SimFrame]) -> tuple[list[SimFrame], StepCoils]:
        if self.clock is None:
            self._boot(start_ns)
        if start_ns < self.clock.t_ns or end_ns < start_ns:
            raise ValueError(f"step [{start_ns}, {end_ns}) ns is not after the bus's time {self.clock.t_ns} ns")
        self.clock.t_ns = start_ns
        pending = sorted(frames, key=lambda f: f.t_ns)
        if pending and not (start_ns <= pending[0].t_ns and pending[-1].t_ns < max(end_ns, start_ns + 1)):
            raise ValueError("a flight frame's time is outside its step")
        step_command = next(((f.arbitration_id, f.data) for f in pending if f.arbitration_id == self._command_id), None)
        heard: list[SimFrame] = []
        self._applied_in_step = []
        average = StepAverage(start_ns, end_ns)
        off_ns = 0
        i = 0
        board = self.board
        while True:
            now_ns = self.clock.t_ns
            while i < len(pending) and pending[i].t_ns <= now_ns:
                self.buses[FLIGHT].send(to_can_message(pending[i]))
                i += 1
            for delivery in self.model.run_until(now_ns):
                for node in delivery.destinations:
                    if node == BOARD:
                        if average.command_ns is None and \
                                (delivery.msg.arbitration_id, bytes(delivery.msg.data)) == step_command:
                            average.command_ns = now_ns
                        self.buses[BOARD].inbox.append(delivery.msg)
                    elif node == FLIGHT:
                        heard.append(to_sim_frame(delivery.msg, now_ns))
            board.step(self.clock())
            if now_ns >= end_ns:
                break
            # The next event: a flight frame's time, a frame's last bit, a board timer, the step's end.
            candidates = [end_ns, round(board.next_due_s(self.clock()) * 1e9)]
            if i < len(pending):
                candidates.append(pending[i].t_ns)
            bus_next = self.model.next_event_ns()
            if bus_next is not None:
                candidates.append(bus_next)
            next_ns = min(max(now_ns + 1, min(candidates)), end_ns)   # a timer due now was handled: move on
            average.hold(board.output_dipole_am2, next_ns - now_ns)
            if board.state.safe_state or board.state.actuation_paused:
                off_ns += next_ns - now_ns
            self.clock.t_ns = next_ns
        new = self._applied_in_step
        coils = StepCoils(average.dipole_am2(board.output_dipole_am2), bool(board.state.safe_state),
                          bool(board.state.actuation_paused), board.state.coil_current_a.copy(),
                          new[0].alive_counter if new else None, off_ns / average.step_ns)
        return heard, coils

    def _on_applied(self, command: AppliedCommand) -> None:
        self._applied_in_step.append(command)
        self.applied.append(applied_record(command))

    @property
    def t_ns(self) -> int | None:
        return None if self.clock is None else self.clock.t_ns

    def report(self) -> dict:
        return self.model.report() if self.clock is not None else {}
