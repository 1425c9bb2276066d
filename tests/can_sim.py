"""Driver, bus model (with its fault injector) and board in one process on a simulated clock.

The same classes as the canbus, mtq and controller processes, wired through BusModel instead of a
transport: every frame takes its exact bit time, queues, arbitration and faults act as in a run,
and a test is deterministic and independent of host load. Times are in ns from T0.
"""
from __future__ import annotations

import random
from dataclasses import dataclass


from bench.bus.can import protocol as p
from bench.bus.can.board import AppliedCommand, MagnetorquerBoard
from bench.bus.can.busmodel import BOARD, FLIGHT, BusModel
from bench.bus.can.config import BoardConfig, DriverConfig, SecurityConfig
from bench.bus.can.driver import MagnetorquerDriver
from bench.bus.can.faults import FaultSpec
from bench.bus.can.injector import FaultInjector
from bench.bus.can.simbus import SimBus, SimClock

T0_NS = 10**12
STEP_NS = 250_000


@dataclass
class Sent:
    counter: int
    dipole_am2: tuple
    sent_s: float


class SimBench:
    """Commands a distinct dipole every command period, so that each applied dipole names the
    command it came from (and when that command was sent)."""

    def __init__(self, *faults: FaultSpec, profile: str = "secoc", board_config: BoardConfig | None = None,
                 security: SecurityConfig | None = None, seed: int = 1, driver_config: DriverConfig | None = None):
        self.clock = SimClock(T0_NS)
        self.security = security or SecurityConfig(profile=profile)
        profile = self.security.profile
        # The run's key: the scenario's, else drawn per bench as the launcher draws one per run
        # (seeded here: deterministic).
        self.key = key = self.security.key or random.Random(seed).randbytes(16)
        outsider = p.Protocol(profile=profile)                      # the injector has no key
        self.model = BusModel(FaultInjector(list(faults), outsider, seed=seed), outsider, T0_NS,
                              to_wall_s=lambda t_ns: t_ns / 1e9)
        self.buses = {FLIGHT: SimBus(self.model, FLIGHT, self.clock), BOARD: SimBus(self.model, BOARD, self.clock)}
        self.board_config = board_config or BoardConfig()
        self.driver_config = driver_config or DriverConfig()
        self.applied: list[tuple[float, AppliedCommand]] = []
        self.coils_off_s: list[float] = []   # when the board entered its safe state (timeout or NMT)
        self.board = MagnetorquerBoard(self.buses[BOARD], self.board_config, p.Protocol(profile=profile, key=key),
                                       clock=self.clock, security=self.security,
                                       on_applied=lambda a: self.applied.append((self.clock(), a)),
                                       on_coils_changed=lambda s: self.coils_off_s.extend([self.clock()] * s.safe_state),
                                       hardware=self.model.injector.hardware)   # its coils under the hardware faults
        self.driver = MagnetorquerDriver(self.buses[FLIGHT], self.driver_config, self.board_config,
                                         p.Protocol(profile=profile, key=key), clock=self.clock, wall_clock=self.clock)
        self.sent: list[Sent] = []
        self.events = []
        self._next_command_ns = T0_NS
        self.run(0.005, commanding=False)   # boot-up heartbeat, NMT start from the driver: operational
        assert self.board.nmt_state == p.NMT_OPERATIONAL

    def dipole(self, k: int) -> tuple:
        x = round(0.001 * (1 + k % 150), 3)
        return (x, -x, 0.05)

    def run(self, duration_s: float, commanding: bool = True) -> None:
        end_ns = self.clock.t_ns + round(duration_s * 1e9)
        period_ns = round(self.driver_config.command_period_s * 1e9)
        while self.clock.t_ns < end_ns:
            if commanding and self.clock.t_ns >= self._next_command_ns:
                dipole = self.dipole(len(self.sent))
                counter = self.driver.command(dipole)
                self.sent.append(Sent(counter, dipole, self.clock()))
                self._next_command_ns += period_ns
            for delivery in self.model.run_until(self.clock.t_ns):
                for node in delivery.destinations:
                    self.buses[node].inbox.append(delivery.msg)
            self.board.step(self.clock())
            self.events += self.driver.poll()
            self.clock.t_ns += STEP_NS
        if not commanding:
            self._next_command_ns = self.clock.t_ns

    def kinds(self) -> list[str]:
        return [e.kind for e in self.events]

    def applied_ages_s(self) -> list[float]:
        """For each applied command: time from the driver sending it to the board applying it,
        found from the dipole (each command's is distinct within 150 periods)."""
        ages = []
        for applied_s, command in self.applied:
            key = tuple(round(float(x), 3) for x in command.dipole_am2)
            matches = [s for s in self.sent if tuple(round(x, 3) for x in s.dipole_am2) == key and s.sent_s <= applied_s]
            assert matches, f"applied {key} at {applied_s} was never commanded"
            ages.append(applied_s - matches[-1].sent_s)
        return ages

    @property
    def max_age_s(self) -> float:
        return self.driver_config.command_period_s + self.security.freshness_margin_s
