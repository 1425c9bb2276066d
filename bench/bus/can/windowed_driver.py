"""The flight-side driver on simulated time, one plant step at a time (lock-step).

`WindowedDriver` holds the same `MagnetorquerDriver` the real-time command loop runs, on a
simulated clock. For each step it gives the frames the driver sends during the step, at their
simulated times: the law's dipole at the step's start in the on-change and mixed transmission
modes, keep-alives every command period (mixed: counted from the change; cyclic: at the loop's
slots, the first slot carrying a new dipole). `heard` then hands it the frames the bus delivered
during that step, each at its simulated time, with the deadline checks its real-time loop makes
at every command slot in between. A frame it owes in reply (an NMT start for a booting board)
goes out at the next step's start, built then (its SecOC freshness is that time's). No transport here: the controller's LockStepLink carries the
windows over Zenoh; tests run it against the bus in process.
"""
from __future__ import annotations

from bench.bus.can.config import CanConfig
from bench.bus.can.driver import FaultEvent, MagnetorquerDriver
from bench.bus.can.sim_window import BOOT_S, OutboxBus, SimFrame, sim_ns, to_can_message
from bench.bus.can.simbus import SimClock

# The board's boot before step 0: (step, start, end) of the two windows in which it sends its
# boot-up heartbeat and the driver answers with the NMT start.
BOOT_WINDOWS = ((-2, sim_ns(-BOOT_S), sim_ns(-BOOT_S / 2)), (-1, sim_ns(-BOOT_S / 2), sim_ns(0.0)))


class WindowedDriver:
    def __init__(self, config: CanConfig):
        self.clock = SimClock(BOOT_WINDOWS[0][1])
        self.outbox = OutboxBus(self.clock)
        self.driver = MagnetorquerDriver.from_config(self.outbox, config, clock=self.clock, wall_clock=self.clock,
                                                     event_clock_ns=lambda: self.clock.t_ns)
        self.driver.defer_replies = True
        self.transmission = config.driver.transmission
        self.period_ns = round(config.driver.command_period_s * 1e9)
        self._dipole = [0.0, 0.0, 0.0]
        self._next_slot_ns: int | None = None     # none before the law's first dipole
        self._checks_ns: list[int] = []           # when the real-time loop would have polled in the last step

    def window(self, start_ns: int, end_ns: int, dipole_am2=None) -> tuple[list[SimFrame], int, int | None]:
        """The frames of the step [start_ns, end_ns), with (alive counter, monotonic ns sent) of
        the first one carrying `dipole_am2` (-1, None: no dipole given, or no frame in the step)."""
        self.clock.t_ns = start_ns
        self.driver.send_owed()                   # an NMT start for a board that booted, built now
        counter, sent_ns = -1, None
        if dipole_am2 is not None:
            self._dipole = [float(x) for x in dipole_am2]
            if self.transmission != "cyclic" or self._next_slot_ns is None:
                # On change, and the law's first dipole in every mode (nothing is sent before it).
                counter, sent_ns = self.driver.command(self._dipole), self.driver.last_sent_ns
                self._next_slot_ns = start_ns + self.period_ns
        checks = [start_ns]
        if self.transmission != "on_change" and self._next_slot_ns is not None:
            while self._next_slot_ns < end_ns:
                self.clock.t_ns = self._next_slot_ns
                slot_counter = self.driver.command(self._dipole)
                if counter < 0 and dipole_am2 is not None:   # cyclic: the first slot carries the new dipole
                    counter, sent_ns = slot_counter, self.driver.last_sent_ns
                checks.append(self._next_slot_ns)
                self._next_slot_ns += self.period_ns
        self._checks_ns = checks + [end_ns]
        return self.outbox.take(start_ns), counter, sent_ns

    def silence(self) -> None:
        """The flight side stops commanding (a bench run's end, to see the board go safe): no
        keep-alive from the next window on, until a dipole is given again."""
        self._next_slot_ns = None

    def heard(self, frames: list[SimFrame]) -> list[FaultEvent]:
        """The frames the flight side heard during the last window, handled at their times; the
        events the driver detected."""
        timeline = sorted([(f.t_ns, 0, f) for f in frames] + [(t, 1, None) for t in self._checks_ns],
                          key=lambda item: (item[0], item[1]))
        for t_ns, is_check, frame in timeline:
            self.clock.t_ns = t_ns
            if not is_check:
                self.driver.handle(to_can_message(frame))
            self.driver.check_deadlines(self.clock())
        return self.driver.take_events()
