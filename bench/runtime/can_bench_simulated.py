"""The actuator bus without the rest of the loop, on simulated time in one process.

The simulated-time twin of `CanBench` (bench/runtime/can_bench.py): the same scenario, the same
scripted dipole profile commanded every command period, the same `CanRunResult` at the end. Here
the flight-side driver is the lock-step attitude loop's `WindowedDriver` and the bus model, the
fault injector and the board are its `LockStepBus`, the classes the controller and canbus
processes run when a lock-step run puts the bus on simulated time. A command period is one
window: the driver's frames at their simulated times through the bus, then the frames it heard.

Every time is bus time (integer ns, `bench.bus.can.sim_window`): the driver's events, the
injector's records and the capture's stamps share it. No host is in the run: what a fault's
detection takes is the bus's and the nodes' own doing, the same on a loaded machine, and a run is
repeatable bit for bit. The board and the bus model write the files their processes write
(bench.bus.can.nodes), so the result is read the same way and the capture opens in any CAN tool.
"""
from __future__ import annotations

from pathlib import Path

from bench.bus.can import run_key
from bench.bus.can.config import CanConfig
from bench.bus.can.lockstep_bus import LockStepBus
from bench.bus.can.nodes import ACCOUNTING_NAME, CAPTURE_NAME, Capture, can_dir, step_applied, \
    write_board_summary, write_bus_results
from bench.bus.can.sim_window import SIM_ZERO_NS, mission_s
from bench.bus.can.windowed_driver import BOOT_WINDOWS, WindowedDriver
from bench.bus.schemas import MtqApplied, header
from bench.runtime.can_bench import CanRunResult, first_event, read_run
from bench.scenario import load_scenario

# After the run's silence has lasted the board's command timeout and a little more, how much more
# simulated time to listen for the board's report of its safe state: a bound on a board that never
# reports it, which the run's checks then name.
SAFE_STATE_WAIT_S = 1.0


class SimulatedCanBench:
    """`start()`, `drive(duration_s, commanding)`, `stop() -> CanRunResult`, as `CanBench`."""

    def __init__(self, scenario_path: Path, run_dir: Path, run_id: str):
        scenario = load_scenario(scenario_path)
        if run_key.needs_key(scenario):
            scenario = run_key.with_run_key(scenario)   # as the launcher does: a key for this run
        self.scenario = scenario
        self.config: CanConfig = scenario.can
        self.run_dir = Path(run_dir)
        self.run_id = run_id
        self.period_ns = round(self.config.driver.command_period_s * 1e9)
        protocol = self.config.protocol()
        self.command_id = protocol.frame_ids[protocol.command_name]
        self.capture = Capture(self.run_dir / CAPTURE_NAME, can_dir(self.run_dir) / ACCOUNTING_NAME) \
            if self.config.capture else None
        self.driver = WindowedDriver(self.config)
        self.bus = LockStepBus(self.config, seed=scenario.run.seed, capture=self.capture)
        self.events: list = []
        self.commanded: list[list[float]] = []
        self.sent: list[tuple[int, int]] = []           # (alive counter, bus ns sent) per command
        self.mtq_applied: list[MtqApplied] = []         # what the plant would integrate, per window
        self.command_start_ns = self.last_command_ns = 0
        self.t_ns = BOOT_WINDOWS[0][1]

    def start(self) -> "SimulatedCanBench":
        """The board's boot-up and the driver's NMT start, before the first command."""
        for _, start_ns, end_ns in BOOT_WINDOWS:
            self._window(start_ns, end_ns, None)
        if not self.driver.driver.health().alive:
            raise RuntimeError("the board sent no heartbeat in its boot windows")
        self.events.clear()
        self.t_ns = BOOT_WINDOWS[-1][2]
        return self

    def drive(self, duration_s: float, commanding: bool = True) -> None:
        """Command the scripted profile every command period (or stay silent), one window each."""
        if not commanding:
            self.driver.silence()
        end_ns = self.t_ns + round(duration_s * 1e9)
        while self.t_ns < end_ns:
            dipole = None
            if commanding:
                first_ns = self.sent[0][1] if self.sent else self.t_ns
                dipole = self.config.dipole_at((self.t_ns - first_ns) / 1e9)
            counter, sent_ns = self._window(self.t_ns, self.t_ns + self.period_ns, dipole)
            if commanding and sent_ns is not None:
                self.command_start_ns = self.command_start_ns or sent_ns
                self.last_command_ns = sent_ns
                self.commanded.append(dipole)
                self.sent.append((counter, sent_ns))
            self.t_ns += self.period_ns

    def _window(self, start_ns: int, end_ns: int, dipole) -> tuple[int, int | None]:
        """One window through the bus; the alive counter and bus time of the window's command."""
        frames, counter, _ = self.driver.window(start_ns, end_ns, dipole)
        sent_ns = next((f.t_ns for f in frames if f.arbitration_id == self.command_id), None)
        heard, coils = self.bus.advance(start_ns, end_ns, frames)
        self.events += self.driver.heard(heard)
        if start_ns >= SIM_ZERO_NS:   # after the boot: what the canbus process publishes for the plant
            step = len(self.mtq_applied)
            self.mtq_applied.append(step_applied(self.bus, coils, header(self.run_id, step, mission_s(start_ns)), step))
        return counter, sent_ns

    def stop(self) -> CanRunResult:
        """Silence until the board reported its safe state (its command timeout after the last
        command), then the files the nodes write, read back."""
        board = self.config.board
        self.drive(board.command_timeout_s + 3 * board.telemetry_period_s + 0.2, commanding=False)
        waited_s = 0.0
        while first_event(self.events, "board_command_timeout", self.last_command_ns) is None \
                and waited_s < SAFE_STATE_WAIT_S:
            self.drive(board.telemetry_period_s, commanding=False)
            waited_s += board.telemetry_period_s
        report = self.bus.report() | {"clock": "simulated", "sim_zero_ns": SIM_ZERO_NS, "wall_offset_s": 0.0,
                                      "t0_ns": BOOT_WINDOWS[0][1]}
        write_bus_results(self.run_dir, self.capture, report, self.bus.injector)   # closes the capture
        self.capture = None
        write_board_summary(self.run_dir, self.bus.board, self.bus.applied)
        return read_run(self.run_dir, self.config, self.driver.driver, events=list(self.events),
                        commanded=list(self.commanded), sent=list(self.sent), mtq_applied=list(self.mtq_applied),
                        command_start_ns=self.command_start_ns, last_command_ns=self.last_command_ns,
                        board_drain_s=0.0)

    def close(self) -> None:
        if self.capture is not None:
            self.capture.stop()
