"""The flight side of the magnetorquer bus, inside the controller process.

Two ways to run the driver: `MagnetorquerLink` on the wall clock (real time, a kernel bus, a part
from outside), and `LockStepLink` on simulated time (lock-step with the bench's own bus:
bench/bus/can/sim_window.py).

On the wall clock:
The board drops to its safe state when commands stop for its command timeout (0.1 s), far shorter
than a 600 s plant step, so the driver commands on its own thread at its own period (CommandLoop),
with the dipole the scenario scripts, or from an attitude law's first dipole on (nothing before
it, so the first command frame, from which the bus faults count, is the loop's first step). A
law's dipole also goes out the moment the law gives it, in the "mixed" and "on_change"
transmission modes ([can.driver] transmission). Every fault the driver detects is logged as it
happens and written, with its detection latency, to can/driver.json.
"""
from __future__ import annotations

import json
import queue
import threading
import time
from dataclasses import asdict

from bench.bus import keys
from bench.bus.can.config import CanConfig
from bench.bus.can.driver import BoardHealth, CommandLoop, FaultEvent, MagnetorquerDriver
from bench.bus.can.nodes import can_dir, open_node_bus
from bench.bus.can.sim_window import BOOT_S, CanWindow, OutboxBus, mission_s, sim_ns, to_can_message
from bench.bus.can.simbus import SimClock
from bench.bus.schemas import header
from bench.runtime.node import NodeContext

DRIVER_REPORT_NAME = "driver.json"


class MagnetorquerLink:
    def __init__(self, ctx: NodeContext, config: CanConfig, scripted: bool = True):
        """scripted: command the scenario's dipole profile; False: the dipole a law sets
        (`self.loop.set_dipole`, zero until then)."""
        self.ctx = ctx
        self.bus = open_node_bus(ctx, config, config.flight_channel)
        self.driver = MagnetorquerDriver.from_config(self.bus, config)
        self.loop = CommandLoop(self.driver, config.driver.command_period_s,
                                dipole_at=config.dipole_at if scripted else None, on_events=self._log_events,
                                transmission="cyclic" if scripted else config.driver.transmission,
                                first_command_by_law=not scripted)
        self._thread = threading.Thread(target=self.loop.run, args=(ctx.stop,), name="mtq-driver", daemon=True)

    def _log_events(self, events: list[FaultEvent]) -> None:
        _log_events(self.ctx, events)

    def start(self) -> None:
        if hasattr(self.bus, "wait_for_peers"):
            self.bus.wait_for_peers(1, 10.0)   # Zenoh delivers only to buses it already knows
        self._thread.start()

    def stop(self) -> None:
        """Join the command thread (ctx.stop is set by now) and write what the driver saw."""
        self._thread.join(timeout=2.0)
        _write_report(self.ctx, self.loop.health, self.driver)
        self.bus.shutdown()


class LockStepLink:
    """The driver on simulated time, one step at a time: no command thread, no wall-clock period.

    `send(k, dipole)` first hands the driver the frames the bus says it heard during the last
    step, each at its simulated time, checking its deadlines at every command slot between them
    as its real-time loop does; then it sends the step's frames (the dipole at the step's start in
    the on-change and mixed modes, keep-alives at their slots) in one CanWindow to the canbus
    process. What the driver detects is stamped on the bus's simulated time (sim_window: ns, with
    the mission's t = 0 at SIM_ZERO_NS). A frame it owes in reply to one it heard (an NMT start)
    goes out at the next step's start, at most a step later than on the wall clock.
    """

    def __init__(self, ctx: NodeContext, config: CanConfig, step_s: float, reply_timeout_s: float):
        self.ctx = ctx
        self.step_s = step_s
        self.reply_timeout_s = reply_timeout_s
        self.clock = SimClock(sim_ns(-BOOT_S))
        self.bus = OutboxBus(self.clock)
        self.driver = MagnetorquerDriver.from_config(self.bus, config, clock=self.clock, wall_clock=self.clock,
                                                     event_clock_ns=lambda: self.clock.t_ns)
        self.transmission = config.driver.transmission
        self.period_ns = round(config.driver.command_period_s * 1e9)
        self.health: BoardHealth = self.driver.health()
        self._replies = ctx.subscribe_queue(keys.CAN_STEP_BUS, CanWindow)
        self._publisher = ctx.declare_publisher(keys.CAN_STEP_FLIGHT)
        self._dipole = [0.0, 0.0, 0.0]
        self._next_slot_ns: int | None = None     # none before the law's first dipole
        self._awaiting: CanWindow | None = None   # the last window sent, until the bus answers it
        self._windows = 0

    def start(self) -> None:
        """Wait for the bus, then boot the board: its boot-up heartbeat comes back in the first
        window and the driver's NMT start goes out in the second, before step 0."""
        deadline = time.monotonic() + self.ctx.scenario.run.liveliness.startup_timeout_s
        while not self._publisher.matching_status.matching:
            if time.monotonic() > deadline or self.ctx.stop.is_set():
                raise TimeoutError("no canbus process on the lock-step CAN topic")
            time.sleep(0.005)
        self._exchange(-2, sim_ns(-BOOT_S), sim_ns(-BOOT_S / 2), None)
        self._catch_up(timeout_s=max(0.0, deadline - time.monotonic()))   # the boot-up heartbeat
        self._exchange(-1, sim_ns(-BOOT_S / 2), sim_ns(0.0), None)           # the NMT start
        self._catch_up(timeout_s=max(0.0, deadline - time.monotonic()))

    def send(self, step: int, dipole_am2, timeout_s: float | None = None) -> tuple[int, int | None]:
        """(alive counter, can_sent ns) of the first frame carrying the step's dipole."""
        return self._exchange(step, sim_ns(step * self.step_s), sim_ns((step + 1) * self.step_s),
                              [float(x) for x in dipole_am2])

    def _exchange(self, step: int, start_ns: int, end_ns: int, dipole) -> tuple[int, int | None]:
        self._catch_up()
        self.clock.t_ns = start_ns
        counter, sent_ns = -1, None
        if dipole is not None:
            self._dipole = dipole
            if self.transmission != "cyclic" or self._next_slot_ns is None:
                # On change, and the law's first dipole in every mode (nothing is sent before it).
                counter, sent_ns = self.driver.command(dipole), self.driver.last_sent_ns
                self._next_slot_ns = start_ns + self.period_ns
        slots = [start_ns]
        if self.transmission != "on_change" and self._next_slot_ns is not None:
            while self._next_slot_ns < end_ns:
                self.clock.t_ns = self._next_slot_ns
                slot_counter = self.driver.command(self._dipole)
                if counter < 0 and dipole is not None:   # cyclic: the first slot carries the new dipole
                    counter, sent_ns = slot_counter, self.driver.last_sent_ns
                slots.append(self._next_slot_ns)
                self._next_slot_ns += self.period_ns
        window = CanWindow(header(self.ctx.run_id, self._windows, mission_s(start_ns)), step, start_ns, end_ns,
                           self.bus.take(start_ns))
        self._windows += 1
        self._slots_ns = slots + [end_ns]
        self.ctx.publish(keys.CAN_STEP_FLIGHT, window)
        self._awaiting = window
        return counter, sent_ns

    def _catch_up(self, stop_aware: bool = True, timeout_s: float | None = None) -> None:
        """The bus's answer to the last window: its frames handled at their times, with the
        deadline checks the real-time loop makes at every command slot."""
        sent = self._awaiting
        if sent is None:
            return
        reply = self._reply_to(sent, stop_aware, timeout_s)
        timeline = sorted([(f.t_ns, 0, f) for f in reply.frames] + [(t, 1, None) for t in self._slots_ns],
                          key=lambda item: (item[0], item[1]))
        for t_ns, is_check, frame in timeline:
            self.clock.t_ns = t_ns
            if not is_check:
                self.driver.handle(to_can_message(frame))
            self.driver.check_deadlines(self.clock())
        events = self.driver.take_events()
        if events:
            _log_events(self.ctx, events)
        self.health = self.driver.health()
        self._awaiting = None

    def _reply_to(self, sent: CanWindow, stop_aware: bool = True, timeout_s: float | None = None) -> CanWindow:
        if timeout_s is None:
            timeout_s = self.reply_timeout_s if stop_aware else 1.0
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or (stop_aware and self.ctx.stop.is_set()):
                raise TimeoutError(f"no answer from the CAN bus to step {sent.step} within {timeout_s:g} s")
            try:
                reply = self._replies.get(timeout=min(remaining, 0.2))
            except queue.Empty:
                continue
            if reply.step == sent.step and reply.start_ns == sent.start_ns:
                return reply
            self.ctx.log.warning("lock-step CAN: answer to step %d while waiting for step %d: ignored", reply.step,
                                 sent.step)

    def stop(self) -> None:
        try:
            self._catch_up(stop_aware=False)   # the last step's frames count too (the bus may be gone)
        except TimeoutError:
            pass
        _write_report(self.ctx, self.health, self.driver)


def _log_events(ctx: NodeContext, events: list[FaultEvent]) -> None:
    for event in events:
        ctx.log.warning("magnetorquer bus: %s after %.1f ms (%s %s)", event.kind, event.latency_s * 1e3,
                        event.frame, event.detail)


def _write_report(ctx: NodeContext, health: BoardHealth, driver: MagnetorquerDriver) -> None:
    report = {
        "health": asdict(health) | {"ok": health.ok},
        "events": [asdict(e) for e in driver.events],
    }
    (can_dir(ctx.run_dir) / DRIVER_REPORT_NAME).write_text(json.dumps(report, indent=1))
