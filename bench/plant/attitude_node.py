"""The plant process of the attitude loop: rigid body, environment and sensors at the gyro rate; the
magnetorquer torque from the dipole the board reports as applied.

reads:  command/dipole   (DipoleCommand: step k's dipole and the CAN alive counter that carried it)
        actuator/mtq     (MtqApplied: what the board's coil drivers are set to)
writes: sense/mag        (MagnetometerSample, every magnetometer_period_s, or once per coil-blanking
                         window of the board with magnetometer_sampling = "coil_blanking"),
        sense/star       (StarTrackerSample, every star_tracker_period_s; no fix in an outage),
        sense/gyro       (GyroSample, every step, the gyro rate being the step rate; published after
                         the tick's other sensors: it closes the tick), truth/attitude (AttitudeTruth),
        command/applied  (DipoleCommand as applied, with its stamp chain joined across the bus to the
                         board's report of the frame that carried it: bench/plant/mtq_chain.py), status/step,
        event/deadline   (real-time: step k's command not in before step k+1)

lock-step, bus on simulated time (the default, bench/bus/can/sim_window.py): publish step k, wait
for command k, then for the canbus process's report of step k (MtqApplied with step = k: the coil
drivers' output averaged over the step, the board and the bus having run on simulated time), integrate.
lock-step, bus on the wall clock ([can] lock_step_clock = "wall", or a kernel bus): publish step k,
wait for command k, then for the board's report of a command frame at or after the one that carried it (alive counter c .. c+7 modulo 16: later frames of the driver's
command loop carry the same dipole), integrate. The board and the driver stay on the wall clock:
the driver keeps commanding the current dipole every command period while the plant waits, so the
board never times out, and the plant pairs reports with commands by counter, not by time; that
keeps lock-step deterministic without a simulated clock on the bus (fault windows, which are
wall-clock, therefore belong in real-time runs).
lock-step with an external board ([run] external = ["board"]: on the wall clock): the same, with
the board's command acknowledgement (MTQ_TLM_SETPOINT, bench/plant/board_telemetry.py) as the
report: the echo carrying step k's counter and, bit for bit, the set-point the command asks for.
A board that sends no echo cannot run in lock-step: the run stops at the first step, saying so.
real-time: step k at t0 + k * dt / time_factor on the monotonic clock; the board's latest report
is held over the step (zero-order hold), and is used only if current (DipoleAcceptance).
Without a [can] section the commanded dipole goes through the in-process board model.
"""
from __future__ import annotations

import threading
import time

import numpy as np

from bench.bus import keys
from bench.bus.can.sim_window import bus_on_simulated_time
from bench.bus.spill import StepColumn
from bench.bus.schemas import (
    AttitudeTruth, DipoleCommand, GyroSample, MagnetometerSample, Message, MtqApplied, StarTrackerSample, StepDone,
    header,
)
from bench.runtime.node import NodeContext
from bench.plant.attitude import AttitudeSample
from bench.plant.attitude_plant import AttitudePlant
from bench.plant.mtq_acceptance import DipoleAcceptance, board_dipole_without_bus
from bench.plant.acceptance import ActuatorEnvelope, CommandGate
from bench.plant.mtq_chain import COUNTER_MODULO, COUNTER_WINDOW, CommandChains
from bench.plant.stepping import LoopBroken, RealTimeClock, WaitReport, wait_command_lockstep

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


class CoilBlankingGate:
    """magnetometer_sampling = "coil_blanking": the magnetometer samples once per coil-blanking
    window, at the first tick at which the board's latest report (actuator/mtq, sent whenever its
    coils change) says its coils are held off for the magnetometer."""

    def __init__(self, coils_blanked):
        self._coils_blanked = coils_blanked
        self._sampled_in_this_window = False
        self.windows_sampled = 0

    def __call__(self) -> bool:
        if not self._coils_blanked():
            self._sampled_in_this_window = False
            return False
        if self._sampled_in_this_window:
            return False
        self._sampled_in_this_window = True
        self.windows_sampled += 1
        return True


def _publish_step(ctx: NodeContext, plant: AttitudePlant, k: int, estimator_on_truth: bool) -> None:
    """The sensors of tick k, each on its own topic, the gyro last, as it closes the tick for the
    estimator (one session, one link: Zenoh delivers them in this order); and the truth: first
    when the estimator runs on it, else after the sensors (then only the recorder reads it, and the
    loop's sense -> estimator hop does not wait for its encoding and MAC)."""
    sample = plant.sense()
    hdr = header(ctx.run_id, k, plant.time_s, sensed=time.monotonic_ns())
    if estimator_on_truth:
        _publish_truth(ctx, plant, hdr)
    for topic, message in sensor_messages(hdr, sample):
        ctx.publish(topic, message)
    if not estimator_on_truth:
        _publish_truth(ctx, plant, hdr)


def _publish_truth(ctx: NodeContext, plant: AttitudePlant, hdr) -> None:
    truth = plant.sim.truth()
    ctx.publish(keys.TRUTH_ATTITUDE, AttitudeTruth(
        hdr, truth.q_wxyz.tolist(), truth.omega_body_radps.tolist(), truth.gyro_bias_radps.tolist(),
        plant.sim.field_body_t().tolist(), plant.orbit.position_m(plant.time_s).tolist()))


def sensor_messages(hdr, sample: AttitudeSample) -> list[tuple[str, Message]]:
    """The messages of one sensor tick in publishing order: magnetometer and star tracker on their
    ticks (the star tracker's "no fix" in an outage too), the gyro last."""
    messages: list[tuple[str, Message]] = []
    if sample.magnetometer_t is not None:
        messages.append((keys.SENSE_MAG, MagnetometerSample(
            hdr, np.asarray(sample.magnetometer_t, float).tolist(), np.asarray(sample.field_inertial_t, float).tolist())))
    if sample.star_tracker_tick:
        fix = None if sample.star_tracker_wxyz is None else np.asarray(sample.star_tracker_wxyz, float).tolist()
        messages.append((keys.SENSE_STAR, StarTrackerSample(hdr, fix)))
    messages.append((keys.SENSE_GYRO, GyroSample(hdr, np.asarray(sample.gyro_radps, float).tolist())))
    return messages


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


def run(ctx: NodeContext) -> int:
    scenario = ctx.scenario
    n_steps = scenario.n_steps
    reports = BoardReports()
    gate = None
    if scenario.attitude.sensors.magnetometer_sampling == "coil_blanking":
        gate = CoilBlankingGate(lambda: reports.latest is not None and reports.latest[1].actuation_paused)
    plant = AttitudePlant(scenario.attitude, n_steps, scenario.run.seed, magnetometer_due=gate)
    acceptance = DipoleAcceptance(scenario.can)
    # Lock-step pairs step k with the controller's command for step k: finite, for this step and
    # inside the board's envelope, or it is refused and counted like a thrust command.
    command_gate = CommandGate(ActuatorEnvelope("dipole", "A m^2", acceptance.envelope_am2),
                               on_reject=scenario.plant.command_acceptance.on_reject)
    commands = ctx.subscribe_queue(keys.COMMAND_DIPOLE, DipoleCommand)
    telemetry = None
    if scenario.can is not None and "board" in scenario.run.external:
        telemetry = _listen_to_external_board(ctx, reports)   # a real board: its frames, not actuator/mtq
    elif scenario.can is not None:
        ctx.subscribe(keys.ACTUATOR_MTQ, MtqApplied, reports.add)
    estimator_truth = scenario.estimator.mode == "truth"
    for topic in (*keys.SENSE_ATTITUDE_TOPICS, keys.TRUTH_ATTITUDE, keys.EVENT_DEADLINE, keys.COMMAND_APPLIED):
        ctx.declare_publisher(topic)
    ctx.declare_ready([keys.TRUTH_ATTITUDE] if estimator_truth else list(keys.SENSE_ATTITUDE_TOPICS))
    ctx.wait_for_ready(ctx.peers, timeout_s=ctx.scenario.run.liveliness.startup_timeout_s)
    ctx.watch_peers(ctx.peers)
    ctx.log.info("peers ready (%s); attitude loop, %d steps of %.3f s in %s mode", ", ".join(ctx.peers), n_steps,
                 plant.dt_s, scenario.run.mode)
    realtime = scenario.run.mode == "real-time"
    simulated_bus = bus_on_simulated_time(scenario)
    clock = RealTimeClock(plant.dt_s / scenario.run.time_factor) if realtime else None
    # a command frame's report can be told from another's until the alive counter wraps
    chains = CommandChains(n_steps, COUNTER_MODULO * scenario.can.driver.command_period_s if scenario.can else 1.0)
    log = AppliedLog(n_steps)
    last_command: DipoleCommand | None = None
    step_started_ns = time.monotonic_ns()
    try:
        for k in range(n_steps):
            if ctx.stop.is_set():
                ctx.log.warning("stopped at step %d of %d", k, n_steps)
                return 1
            # A peer is lost when its token stays away for the hang timeout, not at its first
            # missed lease (a busy host delays a healthy process that long).
            lost = ctx.lost_peer(scenario.run.liveliness.hang_timeout_s)
            if lost:
                raise LoopBroken(f"peer '{lost}' lost at step {k}")
            if realtime:
                clock.sleep_until(clock.tick_s(k))
            _publish_step(ctx, plant, k, estimator_truth)
            ctx.publish_pending()     # the previous step's applied commands and report, behind the tick
            if realtime:
                command = clock.collect_command(ctx, commands, k, command_gate, value=lambda c: c.dipole_am2)
                outcome = clock.deadline.check(k, time.monotonic() - clock.tick_s(k))
                if outcome.has_event:
                    ctx.publish(keys.EVENT_DEADLINE, outcome.deadline_event(header(ctx.run_id, k, plant.time_s), "plant"))
                last_command = command or last_command
                dipole, report = _realtime_dipole(scenario, acceptance, reports, last_command, log, k)
            else:
                command = wait_command_lockstep(ctx, commands, k, scenario.run.command_timeout_s, command_gate,
                                                 value=lambda c: c.dipole_am2)
                if command is None:   # only refused commands came: the controller's step is lost
                    raise LoopBroken(f"step {k}: every dipole command was refused ({dict(command_gate.rejected)})")
                last_command = command
                reports.on_wait = WaitReport(ctx, k, keys.ACTUATOR_MTQ).poll   # the board's report of it, next
                if simulated_bus:
                    dipole, report = _simulated_bus_dipole(scenario, acceptance, reports, command, log, k)
                else:
                    dipole, report = _lockstep_dipole(scenario, acceptance, reports, command, step_started_ns, log, k,
                                                      telemetry)
            if report is not None:
                log.board_applied_ns[k] = report.header.stamps_ns.get("applied", -1)
            applied_ns = time.monotonic_ns()
            completed = []
            if command is not None:
                log.command_received_ns[k] = applied_ns
                if scenario.can is None:
                    completed.append(chains.record_direct(k, command, applied_ns, applied_ns))
                else:
                    chains.open(k, command, board_dipole_without_bus(command.dipole_am2, scenario.can))
            if scenario.can is not None:
                completed += chains.close(reports.received(), applied_ns) + chains.expire(applied_ns)
            for _, applied in completed:     # for the recording: no node waits for them
                ctx.publish_later(keys.COMMAND_APPLIED, applied)
            step_started_ns = time.monotonic_ns()
            plant.apply(dipole)
            # The launcher's progress: behind the next tick (the run's end publishes the last).
            ctx.publish_later(keys.STATUS_STEP, StepDone(header(ctx.run_id, k, plant.time_s), n_steps, k == n_steps - 1))
    except LoopBroken as exc:
        ctx.log.error("%s", exc)
        return 1
    finally:
        ctx.publish_pending()
        ctx.leave_realtime_priority()   # the loop is over; its files must not hold up another run
        for _, applied in chains.expire():
            ctx.publish(keys.COMMAND_APPLIED, applied)
        _write_trajectory(ctx, plant, chains, clock, log, acceptance)
        if telemetry is not None:
            _stop_listening(ctx, telemetry)
    return 0


def _listen_to_external_board(ctx: NodeContext, reports: BoardReports):
    """[run] external = ["board"]: the plant hears the board's telemetry on the driver's bus (with no
    bus model between them, the board's bus: the launcher writes it as [can.driver_bus])."""
    from bench.bus.can.transport import open_bus
    from bench.plant.board_telemetry import BoardTelemetry

    config = ctx.scenario.can
    bus = open_bus(config.bus_spec("driver"), run_id=ctx.run_id, session=ctx.session)
    # Lock-step pairs each step with the board's acknowledgement of its command; real time holds
    # the coils' reported dipole.
    source = "setpoint" if ctx.scenario.run.mode == "lock-step" else "dipole"
    telemetry = BoardTelemetry(bus, config.protocol(), ctx.run_id, reports.add, config.driver.max_delta_counter,
                               source=source)
    telemetry.start()
    return telemetry


def _stop_listening(ctx: NodeContext, telemetry) -> None:
    import json

    from bench.bus.can.nodes import can_dir

    telemetry.stop()
    telemetry.bus.shutdown()
    (can_dir(ctx.run_dir) / "plant_board_telemetry.json").write_text(json.dumps(telemetry.summary(), indent=1))


def _lockstep_dipole(scenario, acceptance, reports, command, since_ns, log, k, external_board=None):
    """external_board: the BoardTelemetry of an external board (its echoes are the reports)."""
    log.commanded[k] = command.dipole_am2
    log.counter[k] = command.alive_counter
    if scenario.can is None:
        dipole, reason = acceptance.accept(board_dipole_without_bus(command.dipole_am2, None), None)
        log.reported[k] = dipole
        log.refused[k] = reason is not None
        return dipole, None
    report = None
    if command.alive_counter >= 0:
        expected = board_dipole_without_bus(command.dipole_am2, scenario.can)
        exact_wait_s = EXACT_REPORT_WAIT_S if scenario.can.faults else scenario.run.command_timeout_s
        if external_board is not None:
            from bench.plant.board_telemetry import as_echoed

            expected = as_echoed(external_board.protocol, expected)
        report = reports.wait_for_report(command.alive_counter, expected, since_ns, exact_wait_s,
                                         acknowledgements_only=external_board is not None)
        if report is None and external_board is not None and not external_board.reports:
            raise LoopBroken(_no_echo_message(external_board, k, exact_wait_s + REPORT_WAIT_S))
    if report is None:
        # No report of this command (never sent, or every frame lost for 2 s): coils as last
        # reported if that is current, else off. Counted as a refusal of the command.
        latest = reports.latest
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


def _no_echo_message(telemetry, k: int, waited_s: float) -> str:
    import bench.bus.can.protocol as p

    heard = telemetry.frames[p.TLM_DIPOLE] + telemetry.frames[p.TLM_COIL]
    return (f"step {k}: no {p.TLM_SETPOINT} from the external board within {waited_s:g} s ({heard} of its telemetry "
            f"frames heard, {sum(telemetry.refused.values())} refused): lock-step with an external board needs the "
            f"board's command acknowledgement; a board without it runs in real time only (docs/can-bus.md)")


def _simulated_bus_dipole(scenario, acceptance, reports, command, log, k):
    log.commanded[k] = command.dipole_am2
    log.counter[k] = command.alive_counter
    report = reports.wait_for_step(k, scenario.run.command_timeout_s)
    if report is None:
        raise LoopBroken(f"step {k}: no report of the coils from the CAN bus within {scenario.run.command_timeout_s:g} s")
    dipole, reason = acceptance.accept(report.dipole_am2, None)
    # The step's command not applied (lost, rejected, the board in safe state): what the coils did
    # is still what the plant gets, and the step counts as refused.
    log.refused[k] = reason is not None or not report.command_applied
    log.safe_state[k] = report.safe_state
    log.reported[k] = dipole
    return dipole, report


def _realtime_dipole(scenario, acceptance, reports, command, log, k):
    if command is not None:
        log.commanded[k] = command.dipole_am2
        log.counter[k] = command.alive_counter
    if scenario.can is None:
        requested = command.dipole_am2 if command is not None else np.zeros(3)
        dipole, reason = acceptance.accept(board_dipole_without_bus(requested, None), None)
        log.reported[k] = dipole
        log.refused[k] = reason is not None
        return dipole, None
    latest = reports.latest
    if latest is None:
        log.reported[k] = 0.0
        return np.zeros(3), None
    report = latest[1]
    dipole, reason = acceptance.accept(report.dipole_am2, report.header.stamps_ns.get("applied", latest[0]))
    log.refused[k] = reason is not None
    log.safe_state[k] = report.safe_state
    log.reported[k] = dipole
    return dipole, report


def _write_trajectory(ctx, plant, chains: CommandChains, clock, log: AppliedLog, acceptance: DipoleAcceptance) -> None:
    n = len(plant.log.time_s)
    arrays = plant.trajectory()
    arrays.update({
        "att_dipole_commanded_am2": log.commanded[:n], "att_board_report_am2": log.reported[:n],
        "att_alive_counter": log.counter[:n], "att_refused": log.refused[:n], "att_safe_state": log.safe_state[:n],
        "att_board_applied_ns": log.board_applied_ns[:n], "att_command_received_ns": log.command_received_ns[:n],
        "att_board_report_counter": chains.board_counter[:n],
    })
    arrays.update({f"stamp_{stage}_ns": v[:n] for stage, v in chains.stamps.stamps.items()})
    arrays["plant_late_commands"] = np.array(clock.late_commands if clock else 0)
    arrays["plant_missed_steps"] = np.array(clock.deadline.counter.misses if clock else 0)
    arrays["plant_refused_reports"] = np.array(sum(acceptance.rejected.values()))
    np.savez(ctx.run_dir / "trajectory.npz", **arrays)
