"""The controller process of the attitude loop: estimate in, dipole out through the magnetorquer
link, once per plant step, under the deadline monitor.

reads:  estimate/attitude (AttitudeEstimate; real time: the newest, those queued behind it passed
                           over and counted, bench/controller/newest.py)
        plan/attitude     (AttitudePlanMessage from `bench node planner`; law "tvlqr_plan" only,
                           bench.controller.plan_tracking: lock-step waits for a plan that is due)
        canstep/bus       (CanWindow: lock-step, bus on simulated time: the frames the driver heard)
writes: command/dipole (DipoleCommand: the law's dipole and the alive counter of the first CAN
        frame that carried it), event/deadline; CAN command frames through the driver
        (canstep/flight, one CanWindow per step, when the bus is on simulated time)
On the wall clock the driver's command loop (its own thread) sends the newest dipole every command
period, so the board never times out between plant steps; in the "mixed" transmission mode (the
default) the law's dipole also goes out the moment the law gives it. In lock-step with the bus on
simulated time (bench/bus/can/sim_window.py) the same frames go out at their simulated times, a
step's worth at once (mtq_link.LockStepLink).
The FDIR actuator monitor ([attitude_control.fdir], bench.controller.fdir) runs once each command
is out; what it detects is logged, and written with the driver's events to can/driver.json (kind
"fdir_<class>", frame "FDIR"; lock-step on simulated bus time: stamped with it) and, with the
monitor's whole account on simulated time, to fdir.json.
Summary: deadline_controller.json; the driver's view of the bus: can/driver.json.
"""
from __future__ import annotations

import json
import threading
import time

import numpy as np

from bench.bus import keys
from bench.bus.can.bus_events import publish_bus_events
from bench.bus.can.sim_window import bus_on_simulated_time, sim_ns
from bench.bus.schemas import AttitudeEstimate, DipoleCommand
from bench.controller.attitude_cycle import AttitudeCycle
from bench.config.controller import PLANNED_LAWS
from bench.controller import fdir
from bench.controller.mtq_link import LockStepLink, MagnetorquerLink
from bench.controller.newest import NewestEstimate
from bench.runtime.node import NodeContext
from bench.runtime.time_model import TimeModel


class DipoleSender:
    """Hands the law's dipole to the driver's command loop and learns which frame carried it."""

    def __init__(self, link: MagnetorquerLink):
        self.link = link
        self._lock = threading.Lock()
        self._pending: tuple[list[float], threading.Event, list, int] | None = None
        link.loop.on_command = self._on_command

    def send(self, step: int, dipole_am2: np.ndarray, timeout_s: float) -> tuple[int, int | None]:
        """(alive counter, can_sent ns) of the first frame with this dipole; (-1, None) on timeout."""
        dipole = [float(x) for x in dipole_am2]
        done, result = threading.Event(), []
        with self._lock:   # before the dipole is set: in the on-change modes it goes out within set_dipole
            self._pending = (dipole, done, result, time.monotonic_ns())
        self.link.loop.set_dipole(dipole)
        if not done.wait(timeout_s):
            with self._lock:
                self._pending = None
            return -1, None
        return result[0], result[1]

    def _on_command(self, counter: int, dipole: list[float], sent_ns: int) -> None:
        with self._lock:
            # A frame built from the previous dipole can be on its way when the new one is set:
            # only a frame with the new values, sent after the law asked for them, answers (an
            # unchanged dipole is on every frame: one sent before the request carries the old
            # command, and its stamp would put can_sent before commanded).
            if self._pending is not None and list(dipole) == self._pending[0] and sent_ns >= self._pending[3]:
                _, done, result, _ = self._pending
                result.extend([counter, sent_ns])
                self._pending = None
                done.set()


def command_send_timeout_s(scenario) -> float:
    """How long the controller waits for the driver's first CAN frame carrying a new dipole.

    Real-time: 5 command periods, then the step goes without a counter (the plant holds the board's
    latest report). Lock-step: as long as the plant waits for the command, because lock-step results
    must not depend on the host's load: the driver's command loop sends the new dipole within a
    command period on an idle host, but at load 10 it once took more than 5 periods (issue 12,
    attitude_slew_milqr step 140): the step went without a counter, the plant applied the previous
    dipole and the run left the in-process loop."""
    if scenario.can is None:
        return 0.0
    if TimeModel.of(scenario).lock_step:
        return scenario.run.command_timeout_s
    return 5 * scenario.can.driver.command_period_s


def run(ctx: NodeContext) -> int:
    scenario = ctx.scenario
    cycle = AttitudeCycle(scenario)
    link = sender = None
    if bus_on_simulated_time(scenario):
        link = sender = LockStepLink(ctx, scenario.can, scenario.step_s, scenario.run.command_timeout_s)
    elif scenario.can is not None:
        link = MagnetorquerLink(ctx, scenario.can, scripted=False)
        sender = DipoleSender(link)
    send_timeout_s = command_send_timeout_s(scenario)
    estimates = ctx.subscribe_queue(keys.ESTIMATE_ATTITUDE, AttitudeEstimate)
    newest = NewestEstimate(ctx.time_model)
    follower = None
    if scenario.attitude_control.law in PLANNED_LAWS:
        from bench.controller.plan_tracking import PlanFollower

        follower = PlanFollower(ctx, cycle.law)
    ctx.declare_publisher(keys.EVENT_DEADLINE)
    if link is not None:
        link.start()
    ctx.declare_ready([keys.COMMAND_DIPOLE])
    fdir_events = []     # as the driver's FaultEvents, for can/driver.json
    for estimate in ctx.until_stopped(estimates):
        estimate = newest.take(estimates, estimate)
        if follower is not None:   # before the deadline clock starts: a lock-step wait is not the law's time
            follower.before_cycle(estimate.header.seq, estimate.header.sim_time_s, estimate.valid, estimate.q_wxyz)
        received_ns = time.monotonic_ns()
        hdr = estimate.header.stamped("controller_received", received_ns)
        outcome = cycle.run(hdr.sim_time_s, estimate.valid, estimate.q_wxyz, estimate.omega_radps,
                            estimate.field_body_t, start_ns=received_ns, gyro_bias_radps=estimate.gyro_bias_radps)
        hdr = hdr.stamped("commanded", time.monotonic_ns())
        counter = -1
        if sender is not None:
            counter, sent_ns = sender.send(estimate.header.seq, outcome.dipole_am2, send_timeout_s)
            if sent_ns is not None:
                hdr = hdr.stamped("can_sent", sent_ns)
        monitored = outcome.monitored
        ctx.publish(keys.COMMAND_DIPOLE, DipoleCommand(
            hdr, outcome.dipole_am2.tolist(), counter, cycle.law_name, outcome.saturated, outcome.weak_field,
            monitored.fallback if monitored is not None else None))
        if monitored is not None and monitored.has_event:
            ctx.publish(keys.EVENT_DEADLINE, monitored.deadline_event(hdr))
        board_ok = True if link is None else link.health.ok
        for event in cycle.monitor_actuators(board_ok):     # after the command: the fit must not delay it
            ctx.log.warning("FDIR: %s", event.describe())
            detected_ns = sim_ns(event.time_s) if isinstance(link, LockStepLink) else time.monotonic_ns()
            fdir_events.append(fdir.fault_event(event, detected_ns))
            publish_bus_events(ctx, fdir_events[-1:])    # event/can, as it comes (recorder, live view)
    if link is not None:
        link.stop(extra_events=fdir_events)
    fdir.write_report(ctx.run_dir, cycle.fdir, cycle.envelope)
    summary = (cycle.summary() | (follower.summary() if follower is not None else {})
               | {"stale_estimates_skipped": newest.skipped})
    (ctx.run_dir / "deadline_controller.json").write_text(json.dumps(summary, indent=2))
    return 0
