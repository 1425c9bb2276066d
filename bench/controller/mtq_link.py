"""The flight side of the magnetorquer bus, inside the controller process.

Two ways to run the driver: `MagnetorquerLink` on the wall clock (real time, a kernel bus, a part
from outside), and `LockStepLink` on simulated time (lock-step with the bench's own bus:
bench/bus/can/sim_window.py).

On the wall clock the board drops to its safe state when commands stop for its command timeout
(0.1 s), far shorter than a plant step, so the driver commands on its own thread at its own
period (CommandLoop),
with the dipole the scenario scripts, or from an attitude law's first dipole on (nothing before
it, so the first command frame, from which the bus faults count, is the loop's first step). A
law's dipole also goes out the moment the law gives it, in the "mixed" and "on_change"
transmission modes ([can.driver] transmission). Every fault the driver detects is logged as it
happens and written, with its detection latency, to can/driver.json.
"""
from __future__ import annotations

import json
import logging
import queue
import threading
import time
from dataclasses import asdict

from bench.bus import keys
from bench.bus.can import protocol as p
from bench.bus.can.bus_events import publish_bus_events
from bench.bus.can.config import CanConfig
from bench.bus.can.driver import BoardHealth, CommandLoop, FaultEvent, MagnetorquerDriver
from bench.bus.can.nodes import can_dir, open_node_bus
from bench.bus.can.sim_window import CanWindow, mission_s, sim_ns
from bench.bus.can.windowed_driver import BOOT_WINDOWS, WindowedDriver
from bench.bus.schemas import header
from bench.runtime.node import NodeContext
from bench.runtime.priority import set_realtime_priority

DRIVER_REPORT_NAME = "driver.json"


class MagnetorquerLink:
    def __init__(self, ctx: NodeContext, config: CanConfig, scripted: bool = True, start_with_loop: bool = False):
        """scripted: command the scenario's dipole profile; False: the dipole a law sets
        (`self.loop.set_dipole`, zero until then). start_with_loop: the profile's first command
        only when the owner calls `loop_started` (at the loop's first step), so that the faults,
        which count from the first command frame, count from the loop's step 0 (simulated time)."""
        self.ctx = ctx
        self.bus = open_node_bus(ctx, config, "driver")
        self.driver = MagnetorquerDriver.from_config(self.bus, config)
        self.loop = CommandLoop(self.driver, config.driver.command_period_s,
                                dipole_at=config.dipole_at if scripted else None, on_events=self._log_events,
                                transmission="cyclic" if scripted else config.driver.transmission,
                                first_command_by_law=not scripted or start_with_loop)
        self._thread = threading.Thread(target=self._command_until_stopped, name="mtq-driver", daemon=True)

    def _log_events(self, events: list[FaultEvent]) -> None:
        _log_events(self.ctx, events)

    def loop_started(self) -> None:
        """The loop's first step: a scripted profile held for it (start_with_loop) starts now."""
        if self.loop._awaiting_first_dipole:
            self.loop.set_dipole([0.0, 0.0, 0.0])    # releases the loop; the profile gives the dipoles

    def start(self) -> None:
        if hasattr(self.bus, "wait_for_peers"):
            self.bus.wait_for_peers(1, 10.0)   # Zenoh delivers only to buses it already knows
        self._thread.start()

    def _command_until_stopped(self) -> None:
        """The command loop until the node stops; then the board is put in pre-operational
        (CiA 301 NMT) at once, on this thread (the driver is not thread-safe). An NMT master that
        stops its PDOs on purpose says so: the board switches its coils off instead of logging a
        command timeout at the end of every run (the launcher stops the flight side first)."""
        # The process's priority, set here too: a thread started by one that took a priority of its
        # own (the controller's cycle thread, SCHED_RESET_ON_FORK) starts at normal priority.
        set_realtime_priority(self.ctx.realtime_priority)
        self.loop.run(self.ctx.stop)
        self.driver.nmt(p.NMT_ENTER_PRE_OPERATIONAL)

    def stop(self, extra_events: list[FaultEvent] = ()) -> None:
        """Join the command thread (ctx.stop is set by now) and write what the driver saw (and
        `extra_events`: the FDIR monitor's, bench.controller.fdir)."""
        self._thread.join(timeout=2.0)
        _write_report(self.ctx, self.health, self.driver, extra_events)
        self.bus.shutdown()

    @property
    def health(self) -> BoardHealth:
        """The driver's word on the board, as its command loop last took it (LockStepLink's too)."""
        return self.loop.health


class LockStepLink:
    """The driver on simulated time (bench/bus/can/windowed_driver.py), its windows carried over
    Zenoh to the canbus process: one CanWindow out per step, the bus's answer back before the next.
    What the driver detects is stamped on the bus's simulated time (sim_window: ns, the mission's
    t = 0 at SIM_ZERO_NS)."""

    def __init__(self, ctx: NodeContext, config: CanConfig, step_s: float, reply_timeout_s: float):
        self.ctx = ctx
        self.step_s = step_s
        self.reply_timeout_s = reply_timeout_s
        self.windowed = WindowedDriver(config)
        self.driver = self.windowed.driver
        self.health: BoardHealth = self.driver.health()
        self._replies = ctx.subscribe_queue(keys.CAN_STEP_BUS, CanWindow)
        self._publisher = ctx.declare_publisher(keys.CAN_STEP_FLIGHT)
        self._awaiting: CanWindow | None = None   # the last window sent, until the bus answers it
        self._windows = 0

    def start(self) -> None:
        """Wait for the bus, then boot the board: its boot-up heartbeat comes back in the first
        window and the driver's NMT start goes out in the second, before step 0."""
        timeout_s = self.ctx.scenario.run.liveliness.startup_timeout_s
        deadline = time.monotonic() + timeout_s
        # canbus's ready token, not a matching subscriber: the recorder (bench/<run_id>/**) matches
        # too, and a window it alone hears is never answered (a controller from outside, started
        # before the launcher's canbus is up, sent its boot window to the recorder only).
        self.ctx.wait_for_ready(["canbus"], timeout_s=timeout_s)
        for step, start_ns, end_ns in BOOT_WINDOWS:
            self._send_window(step, start_ns, end_ns, None)
            self._catch_up(timeout_s=max(0.0, deadline - time.monotonic()))

    def send(self, step: int, dipole_am2, timeout_s: float | None = None) -> tuple[int, int | None]:
        """(alive counter, can_sent ns) of the first frame carrying the step's dipole."""
        self._catch_up()
        return self._send_window(step, sim_ns(step * self.step_s), sim_ns((step + 1) * self.step_s), dipole_am2)

    def _send_window(self, step: int, start_ns: int, end_ns: int, dipole) -> tuple[int, int | None]:
        frames, counter, sent_ns = self.windowed.window(start_ns, end_ns, dipole)
        window = CanWindow(header(self.ctx.run_id, self._windows, mission_s(start_ns)), step, start_ns, end_ns, frames)
        self._windows += 1
        self.ctx.publish(keys.CAN_STEP_FLIGHT, window)
        self._awaiting = window
        return counter, sent_ns

    def _catch_up(self, stop_aware: bool = True, timeout_s: float | None = None) -> None:
        sent = self._awaiting
        if sent is None:
            return
        events = self.windowed.heard(self._reply_to(sent, stop_aware, timeout_s).frames)
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

    def stop(self, extra_events: list[FaultEvent] = ()) -> None:
        try:
            self._catch_up(stop_aware=False)   # the last step's frames count too (the bus may be gone)
        except TimeoutError:
            pass
        _write_report(self.ctx, self.health, self.driver, extra_events)


def _log_events(ctx: NodeContext, events: list[FaultEvent]) -> None:
    for event in events:
        # A late wake-up of our own command thread is the host's, not the bus's: counted and
        # reported (driver.json, the summary) like the faults, but not a warning on a busy host.
        level = logging.INFO if event.kind == "host_overrun" else logging.WARNING
        ctx.log.log(level, "magnetorquer bus: %s after %.1f ms (%s %s)", event.kind, event.latency_s * 1e3,
                    event.frame, event.detail)
    publish_bus_events(ctx, events)    # event/can, as they come (recorder, live view)


def _write_report(ctx: NodeContext, health: BoardHealth, driver: MagnetorquerDriver,
                  extra_events: list[FaultEvent] = ()) -> None:
    """can/driver.json; `extra_events` after the driver's own (the FDIR monitor's: frame "FDIR")."""
    report = {
        "health": asdict(health) | {"ok": health.ok},
        "events": [asdict(e) for e in driver.events] + [asdict(e) for e in extra_events],
        "realtime_priority": ctx.realtime_priority,
    }
    (can_dir(ctx.run_dir) / DRIVER_REPORT_NAME).write_text(json.dumps(report, indent=1))
