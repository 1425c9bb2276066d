"""A bus fault's effect on the coils, from the real board, driver, bus model and fault injector
run in process on the attitude loop's simulated clock (`bench.sim.simulate_attitude_in_process`'s
coil-fault hook).

Nothing here models a fault: `MagnetorquerBoard` (with its coils and power supply under the
hardware faults, bench.bus.can.coils), `MagnetorquerDriver`, `BusModel` and `FaultInjector`
(bench.bus.can) are the classes the canbus, mtq and controller processes run,
wired as tests/can_sim.py wires them (the bus model delivers each frame after its exact bit time,
arbitration and faults; no transport). The flight side commands the dipole the law gave for the
step at once and then every command period (AUTOSAR COM "mixed", the DBC's default), and the
plant gets, for the step, the time average of the dipole the board's coils produced
(`output_dipole_am2`: zero in safe state and without power). Detection is the driver's own `FaultEvent`s, stamped
with the simulated time at which `poll` returned them: the detection latency is in simulated
seconds, at the co-simulation's resolution (`max_step_s`, 1 ms by default; frames in a burst reach
the nodes at most a quarter of it late).

The bus is co-simulated only over a window: from `warmup_s` before the first fault's onset (the
board booted, started by the driver's NMT, E2E in sync, telemetry flowing) to `tail_s` after the
last fault ends. Outside it the bus is fault-free, which for the coils is the in-process loop's
own board model (DBC scaling, quantisation, saturation): the hook returns the dipole unchanged.
Fault times (`FaultSpec.start_s`) are mission seconds, as in a lock-step run, where commanding
starts with the first step.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np

from bench.bus.can import protocol as p
from bench.bus.can.board import MagnetorquerBoard
from bench.bus.can.busmodel import BOARD, FLIGHT, BusModel
from bench.bus.can.config import CanConfig
from bench.bus.can.driver import MagnetorquerDriver
from bench.bus.can.faults import FaultSpec
from bench.bus.can.injector import FaultInjector
from bench.bus.can.run_key import can_needs_key, can_with_key
from bench.bus.can.simbus import SimBus, SimClock

# Simulated time zero of the bus (ns): the mission's t = 0 s. Far from 0 so that no deadline of
# the driver or board ever looks back before it.
T0_NS = 10**12
# Driver events that say the bus is well again, not that something is wrong.
BENIGN_EVENTS = frozenset({"heartbeat_resumed", "board_error_reset", "error_active", "bus_restarted", "host_overrun"})
# Who detected an event: the board (its E2E/SecOC checks and timeouts, reported by EMCY), the
# flight-side driver (heartbeat, telemetry, plausibility, its own controller), or the FDIR actuator
# monitor (bench.controller.fdir: kinds "fdir_<class>").
BOARD_EVENTS = frozenset({"command_rejected", "command_lost", "board_command_timeout", "board_error_reset"})


def monitor_of(kind: str) -> str:
    """The monitor that raised an event of this kind: "board", "driver" or "FDIR"."""
    if kind.startswith("fdir_"):
        return "FDIR"
    return "board" if kind in BOARD_EVENTS else "driver"
# The board needs a heartbeat and the driver's NMT start before it takes commands (CiA 301).
BOOT_S = 0.05


@dataclass
class DetectedEvent:
    kind: str
    time_s: float            # mission seconds when the driver's poll returned it
    detail: str = ""


def fault_end_s(fault: FaultSpec, command_period_s: float) -> float:
    """When a fault stops acting, in mission seconds: its window, or its count of target frames
    (one per command period on the command frame; an upper bound for `every` > 1)."""
    if fault.duration_s is not None:
        return fault.start_s + fault.duration_s
    if fault.count > 0:
        return fault.start_s + fault.count * fault.every * command_period_s
    raise ValueError(f"fault {fault.name!r}: needs duration_s or count in a campaign (it would never end)")


@dataclass
class BusCoSimulation:
    """The coil-fault hook: `hook(time_s, applied_am2) -> applied_am2` for one attitude step of
    `step_s`, with the real bus, board and driver in the loop around the faults' window."""
    can_config: CanConfig
    faults: list[FaultSpec]
    step_s: float
    seed: int = 1
    warmup_s: float = 1.0
    tail_s: float = 2.0
    max_step_s: float = 1e-3
    events: list[DetectedEvent] = field(default_factory=list)
    # Per co-simulated step: (mission time, fraction of the step the coil drivers were off).
    coils_off_fraction: list[tuple[float, float]] = field(default_factory=list)
    coils_off_in_fault_ns: int = 0      # of it, inside the faults' window [onset, end)

    def __post_init__(self):
        if not self.faults:
            raise ValueError("a bus co-simulation needs at least one fault")
        if can_needs_key(self.can_config):
            # The bus lives inside this process, so the key guards nothing; it is derived from the
            # seed because the MAC's bits change the frames' stuff bits, hence their timing, and a
            # case must give the same row wherever it runs (pool or Ray).
            key_hex = hashlib.sha256(f"bus co-simulation seed {self.seed}".encode()).hexdigest()[:32]
            self.can_config = can_with_key(self.can_config, key_hex)
        period_s = self.can_config.driver.command_period_s
        self.onset_s = min(f.start_s for f in self.faults)
        self.end_s = max(fault_end_s(f, period_s) for f in self.faults)
        self.window = (max(0.0, self.onset_s - self.warmup_s), self.end_s + self.tail_s)
        self._started = False
        self._in_window = False

    # --- the hook ---------------------------------------------------------------------------
    def __call__(self, time_s: float, applied_am2: np.ndarray) -> np.ndarray:
        start_s, stop_s = self.window
        self._in_window = not (time_s + self.step_s <= start_s or time_s >= stop_s)
        if not self._in_window:
            return applied_am2
        if not self._started:
            self._start(time_s)
        self._dipole = np.asarray(applied_am2, float).copy()
        self._command()                                     # on change: at once
        until_ns = T0_NS + round((time_s + self.step_s) * 1e9)
        return self._advance(until_ns)

    # --- the bus ----------------------------------------------------------------------------
    def _start(self, time_s: float) -> None:
        config = self.can_config
        first_command_ns = T0_NS + round(time_s * 1e9)
        self.clock = SimClock(first_command_ns - round(BOOT_S * 1e9))
        outsider = p.Protocol(config.node_id, config.security.profile)     # the injector has no key
        # The bus model arms the injector with the first command frame: fault times count from it.
        shifted = [FaultSpec(name=f.name, frames=list(f.frames), start_s=f.start_s - time_s, duration_s=f.duration_s,
                             count=f.count, every=f.every, params=dict(f.params)) for f in self.faults]
        injector = FaultInjector(shifted, outsider, seed=self.seed, max_dipole_am2=config.board.max_dipole_am2)
        self.model = BusModel(injector, outsider, self.clock.t_ns, to_wall_s=lambda t_ns: t_ns / 1e9)
        self.buses = {FLIGHT: SimBus(self.model, FLIGHT, self.clock), BOARD: SimBus(self.model, BOARD, self.clock)}
        self.board = MagnetorquerBoard(self.buses[BOARD], config.board, config.protocol(), clock=self.clock,
                                       security=config.security, hardware=injector.hardware)
        self.driver = MagnetorquerDriver.from_config(self.buses[FLIGHT], config, clock=self.clock, wall_clock=self.clock)
        self.period_ns = round(config.driver.command_period_s * 1e9)
        self._dipole = np.zeros(3)
        self._next_command_ns = None        # no keep-alive before the first command
        self._advance(first_command_ns)     # boot-up heartbeat, NMT start: operational
        if self.board.nmt_state != p.NMT_OPERATIONAL:
            raise RuntimeError("bus co-simulation: the board did not become operational during boot")
        self.events.clear()
        self.coils_off_fraction.clear()     # the boot is not the mission's
        self.coils_off_in_fault_ns = 0
        self._started = True

    def _command(self) -> None:
        self.driver.command(self._dipole)
        self._next_command_ns = self.clock.t_ns + self.period_ns    # the keep-alive counts from here

    def _advance(self, until_ns: int) -> np.ndarray:
        """Run the bus until until_ns; the time-average of the coil drivers' output over it."""
        begin_ns = self.clock.t_ns
        integral = np.zeros(3)
        off_ns = 0
        max_step_ns = max(1, round(self.max_step_s * 1e9))
        while self.clock.t_ns < until_ns:
            now_ns = self.clock.t_ns
            if self._next_command_ns is not None and now_ns >= self._next_command_ns:
                self._command()
            for delivery in self.model.run_until(now_ns):
                for node in delivery.destinations:
                    if node in self.buses:
                        self.buses[node].inbox.append(delivery.msg)
            self.board.step(self.clock())
            for event in self.driver.poll():
                self.events.append(DetectedEvent(event.kind, (now_ns - T0_NS) / 1e9, event.detail))
            # The coils hold what the board set until the next wake-up (frames change it only then).
            candidates = [now_ns + max_step_ns, until_ns]
            if self._next_command_ns is not None:
                candidates.append(self._next_command_ns)
            bus_next = self.model.next_event_ns()
            if bus_next is not None:
                # Frames are handled when they arrive, but bursts (error frames, a babbler, held
                # frames) are taken a quarter step at a time: the bus model still times every
                # frame exactly, the nodes see them at most max_step_s / 4 late.
                candidates.append(max(bus_next, now_ns + max(1, max_step_ns // 4)))
            next_ns = min(candidates)
            output = self.board.output_dipole_am2
            integral += output * (next_ns - now_ns)
            if self.board.state.safe_state or self.board.state.actuation_paused:
                off_ns += next_ns - now_ns
                fault_start_ns, fault_end_ns = (T0_NS + round(t * 1e9) for t in (self.onset_s, self.end_s))
                self.coils_off_in_fault_ns += max(0, min(next_ns, fault_end_ns) - max(now_ns, fault_start_ns))
            self.clock.t_ns = next_ns
        span_ns = until_ns - begin_ns
        if span_ns <= 0:
            return self._dipole.copy()
        self.coils_off_fraction.append(((begin_ns - T0_NS) / 1e9, off_ns / span_ns))
        return integral / span_ns

    # --- what the flight side saw -----------------------------------------------------------
    def board_ok(self) -> bool:
        """The flight-side driver's word on the board after the last step (BoardHealth.ok); outside
        the co-simulated window the bus is fault-free and the board as commanded."""
        return self.driver.health().ok if self._started and self._in_window else True

    def first_detection(self) -> DetectedEvent | None:
        """The driver's first fault event at or after the onset (benign 'back to normal' events aside)."""
        return next((e for e in self.events if e.time_s >= self.onset_s and e.kind not in BENIGN_EVENTS), None)

    def false_alarms(self) -> int:
        """Fault events before the onset (in the warm-up): a clean bus should give none."""
        return sum(1 for e in self.events if e.time_s < self.onset_s and e.kind not in BENIGN_EVENTS)

    def coils_off_s(self) -> float:
        return float(sum(fraction for _, fraction in self.coils_off_fraction) * self.step_s)

    def power_log(self) -> list[tuple[str, float]]:
        """The board's power losses, boots and NMT starts, (event, mission s)."""
        if not self._started:
            return []
        return [(e["event"], e["t_s"] - T0_NS / 1e9) for e in self.board.power_log]
