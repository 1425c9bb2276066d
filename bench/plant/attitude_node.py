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

Each step: the step clock starts step k (bench/plant/stepping.py), the tick's sensors and truth go
out, then the previous step's applied commands and report; the clock gives step k's command, the
run's board dipole source (bench/plant/board_dipole.py) the dipole the coils produced over the step,
and the plant integrates. Lock-step, real time and the bus's clock: docs/time-model.md.
"""
from __future__ import annotations

import time

import numpy as np

from bench.bus import keys
from bench.bus.schemas import (
    AttitudeTruth, DipoleCommand, GyroSample, MagnetometerSample, Message, MtqApplied, StarTrackerSample, StepDone,
    header,
)
from bench.runtime.node import NodeContext
from bench.plant.attitude import AttitudeSample
from bench.plant.attitude_plant import AttitudePlant
from bench.plant.mtq_acceptance import DipoleAcceptance, board_dipole_without_bus
from bench.plant.acceptance import ActuatorEnvelope, CommandGate
from bench.plant.mtq_chain import COUNTER_MODULO, CommandChains
from bench.plant.board_dipole import AppliedLog, BoardReports, board_dipole_source
from bench.plant.stepping import LoopBroken, step_clock

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
    clock = step_clock(scenario)
    # a command frame's report can be told from another's until the alive counter wraps
    chains = CommandChains(n_steps, COUNTER_MODULO * scenario.can.driver.command_period_s if scenario.can else 1.0)
    log = AppliedLog(n_steps)
    board = board_dipole_source(ctx, command_gate, acceptance, reports, log, telemetry)
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
            clock.start_step(k)
            _publish_step(ctx, plant, k, estimator_truth)
            ctx.publish_pending()     # the previous step's applied commands and report, behind the tick
            command = clock.command_for_step(ctx, commands, k, command_gate, plant.time_s, value=lambda c: c.dipole_am2)
            dipole, report = board.for_step(k, command, since_ns=step_started_ns)
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
    source = "setpoint" if ctx.time_model.lock_step else "dipole"
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
    arrays["plant_late_commands"] = np.array(clock.late_commands)
    arrays["plant_missed_steps"] = np.array(clock.missed_steps)
    arrays["plant_refused_reports"] = np.array(sum(acceptance.rejected.values()))
    np.savez(ctx.run_dir / "trajectory.npz", **arrays)
