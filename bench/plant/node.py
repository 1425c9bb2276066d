"""The plant process: owns simulated time, publishes sensing and truth, applies thrust commands.

Reads: command/thrust (ThrustCommand), actuator/mtq (MtqApplied, recorded). Writes: truth,
sense/relpos, sense/range_bearing, command/applied, event/deadline, status/step; trajectory.npz,
command_acceptance.json and, when it stops on divergence, divergence.json.

Each step: the step clock starts step k (bench/plant/stepping.py; lock-step or real time, the time
model in docs/time-model.md), step k's sample goes out first, then the rest of the step's messages
(the other sensors, the previous step's applied command and step report: the loop's next hop
waits only for the sample), the clock gives step k's command, the plant integrates.

Every command passes the output stage (bench/plant/acceptance.py) first: only a finite command for
the current step inside the thrust envelope is applied, whoever sent it. In lock-step the plant
keeps waiting for an acceptable command k after refusing one (the controller's is on its way);
if only refused ones came by the command timeout, it holds or zeroes as configured.
A state that diverges (non-finite, or beyond [plant.divergence]) ends the run with EXIT_DIVERGED.
"""
from __future__ import annotations

import json
import time

import msgspec
import numpy as np

from bench.bus import keys
from bench.bus.schemas import MtqApplied, RangeBearing, RelativePosition, StepDone, ThrustCommand, TruthState, header
from bench.plant.acceptance import ACCEPTANCE_FILE, ActuatorEnvelope, CommandGate
from bench.plant.divergence import EXIT_DIVERGED, Divergence, check_state
from bench.plant.model import TranslationPlant
from bench.runtime.node import NodeContext
from bench.plant import attitude_node
from bench.plant.stepping import LockStepClock, LoopBroken, RealTimeClock, StampLog, step_clock


def _publish_sample(ctx: NodeContext, plant: TranslationPlant, last_thrust_n: np.ndarray, consumed_topic: str) -> None:
    """Step k's truth and sensors; the one the estimator reads is made and sent first (the loop's
    hot path), then the previous step's applied command and report, then the others."""
    hdr = header(ctx.run_id, plant.step_index, plant.sim_time_s, sensed=time.monotonic_ns())

    def range_bearing() -> RangeBearing:
        fix = plant.measure_range_bearing()
        return RangeBearing(hdr) if fix is None else RangeBearing(hdr, *map(float, fix))

    # Each sensor draws from its own generator (TranslationPlant.from_scenario): any order repeats.
    make = {
        # Truth in the flight side's coordinates: the truth-mode estimator passes it on as the estimate.
        keys.TRUTH: lambda: TruthState(hdr, plant.navigation_state_m_mps.tolist(), last_thrust_n.tolist()),
        keys.SENSE_RELPOS: lambda: RelativePosition(hdr, plant.measure_position_m().tolist(),
                                                    ctx.scenario.plant.relpos_sensor.noise_std_m),
        keys.SENSE_RANGE_BEARING: range_bearing,
    }
    ctx.publish(consumed_topic, make.pop(consumed_topic)())
    ctx.publish_pending()
    for topic, message in make.items():
        ctx.publish(topic, message())


def run(ctx: NodeContext) -> int:
    if ctx.scenario.kind == "attitude":
        # By name, as NODES finds nodes: the attitude process reuses this module's pieces.
        return attitude_node.run(ctx)
    scenario = ctx.scenario
    plant = TranslationPlant.from_scenario(scenario)
    n_steps = scenario.n_steps
    commands = ctx.subscribe_queue(keys.COMMAND_THRUST, ThrustCommand)
    dipoles = MagnetorquerRecord(dipole_gate(scenario))
    if scenario.can is not None:
        # No attitude dynamics yet: the plant records the dipole the board applies (m x B later),
        # through the same output stage the attitude plant will apply it with.
        ctx.subscribe(keys.ACTUATOR_MTQ, MtqApplied, dipoles.add)
    sense_topic = keys.TRUTH if scenario.estimator.mode == "truth" else keys.SENSE_RELPOS
    if scenario.estimator.mode != "truth" and scenario.estimator.translation.sensor == "range_bearing":
        sense_topic = keys.SENSE_RANGE_BEARING
    ctx.declare_publisher(keys.SENSE_RELPOS)
    ctx.declare_publisher(keys.SENSE_RANGE_BEARING)
    ctx.declare_publisher(keys.EVENT_DEADLINE)
    ctx.declare_ready([sense_topic])
    ctx.wait_for_ready(ctx.peers, timeout_s=scenario.run.liveliness.startup_timeout_s)
    ctx.watch_peers(ctx.peers)
    ctx.log.info("peers ready (%s); running %d steps in %s mode", ", ".join(ctx.peers), n_steps, scenario.run.mode)

    stamps = StampLog(n_steps)
    gate = thrust_gate(scenario)
    clock = step_clock(scenario)
    divergence = None
    try:
        for k in range(n_steps):
            if ctx.stop.is_set():
                ctx.log.warning("stopped at step %d of %d", k, n_steps)
                return 1
            if ctx.lost_peer(scenario.run.liveliness.hang_timeout_s):
                raise LoopBroken(f"peer '{ctx.lost_peer(0.0)}' lost at step {k}")
            clock.start_step(k)
            _publish_sample(ctx, plant, gate.output, sense_topic)
            command = clock.command_for_step(ctx, commands, k, gate, plant.sim_time_s)
            if command is not None:
                received = command.header.stamped("plant_received", time.monotonic_ns())
                applied = msgspec.structs.replace(command, header=received.stamped("applied", time.monotonic_ns()))
                stamps.record(k, applied.header.stamps_ns)
                # Published so the recording holds every stage's stamp, actuation included; no
                # node waits for it, so it leaves behind the next step's sample.
                ctx.publish_later(keys.COMMAND_APPLIED, applied)
            plant.apply(gate.output)
            divergence = state_divergence(plant, scenario)
            if divergence is not None:
                ctx.log.error("%s; stopping the run", divergence.describe())
                divergence.write(ctx.run_dir)
                return EXIT_DIVERGED
            # The launcher's progress: behind the next step's sample (the run's end publishes the last).
            ctx.publish_later(keys.STATUS_STEP, StepDone(header(ctx.run_id, k, plant.sim_time_s), n_steps, k == n_steps - 1))
    except LoopBroken as exc:
        ctx.log.error("%s", exc)
        return 1
    finally:
        ctx.publish_pending()
        ctx.leave_realtime_priority()   # the loop is over; its files must not hold up another run
        _write_trajectory(ctx, plant, stamps, clock, dipoles)
        _write_acceptance(ctx, {"thrust": gate.counts(), "dipole": dipoles.gate.counts() if dipoles.gate else None})
    return 0


def thrust_gate(scenario) -> CommandGate:
    """The output stage of the thruster: the reference's u_max per axis."""
    envelope = ActuatorEnvelope("thrust", "N", scenario.params().max_abs_thrust_n)
    return CommandGate(envelope, on_reject=scenario.plant.command_acceptance.on_reject)


STATE_NAMES = ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")


def state_divergence(plant: TranslationPlant, scenario) -> Divergence | None:
    limits = scenario.plant.divergence
    bounds = [limits.max_abs_position_m] * 3 + [limits.max_abs_velocity_mps] * 3
    return check_state(plant.step_index, plant.state_m_mps, STATE_NAMES, bounds)


def _write_acceptance(ctx: NodeContext, counts: dict) -> None:
    (ctx.run_dir / ACCEPTANCE_FILE).write_text(json.dumps(counts, indent=2))


def dipole_gate(scenario) -> CommandGate | None:
    """The output stage of the magnetorquer: the board's saturation per axis. Its messages carry
    the board's alive counter, not a step, so only size, finiteness and envelope apply here."""
    if scenario.can is None:
        return None
    envelope = ActuatorEnvelope("dipole", "A m^2", scenario.can.board.max_dipole_am2)
    return CommandGate(envelope, on_reject=scenario.plant.command_acceptance.on_reject)


class MagnetorquerRecord:
    """Every accepted applied-dipole report of the board, with the plant's receive time (monotonic ns)."""

    def __init__(self, gate: CommandGate | None = None):
        self.gate = gate
        self.rows: list[tuple] = []

    def add(self, message: MtqApplied) -> None:
        if self.gate is not None and not self.gate.check(message.dipole_am2).accepted:
            return
        self.rows.append((time.monotonic_ns(), *message.dipole_am2, message.safe_state))

    def arrays(self) -> dict[str, np.ndarray]:
        rows = np.array(self.rows, dtype=float).reshape(-1, 5)
        return {"mtq_received_ns": rows[:, 0].astype(np.int64), "mtq_dipole_am2": rows[:, 1:4],
                "mtq_safe_state": rows[:, 4].astype(bool)}


def _write_trajectory(ctx: NodeContext, plant: TranslationPlant, stamps: StampLog, clock: LockStepClock | RealTimeClock,
                      dipoles: MagnetorquerRecord) -> None:
    arrays = plant.trajectory() | dipoles.arrays()
    arrays.update({f"stamp_{stage}_ns": v for stage, v in stamps.stamps.items()})
    arrays["plant_late_commands"] = np.array(clock.late_commands)
    arrays["plant_missed_steps"] = np.array(clock.missed_steps)
    np.savez(ctx.run_dir / "trajectory.npz", **arrays)
