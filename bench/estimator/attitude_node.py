"""The estimator process of the attitude loop.

reads:  smoother mode: sense/gyro (GyroSample, every plant step), sense/mag (MagnetometerSample, on
        the magnetometer's ticks), sense/star (StarTrackerSample, on the star tracker's ticks; no fix
        in an outage), gathered into ticks by bench.estimator.attitude_sensors.SensorInbox;
        truth mode: truth/attitude (AttitudeTruth)
writes: estimate/attitude (AttitudeEstimate, one per plant step)

A sensor message that does not decode, or decodes to unusable values, is counted per topic and
dropped; a star-tracker outage or a lost star-tracker sample leaves the smoother propagating on the
gyro.
"""
from __future__ import annotations

import time

from bench.bus import keys
from bench.bus.schemas import (
    AttitudeEstimate, AttitudeTruth, GyroSample, MagnetometerSample, StarTrackerSample, header,
)
from bench.estimator.attitude_frontend import AttitudeEstimator
from bench.estimator.attitude_sensors import SensorInbox, SensorSchedule
from bench.runtime.node import STOP_POLL_S, NodeContext

# In real time, how long a sample the schedule promises is awaited once its tick's gyro is in: a
# sliver of the 0.1 s tick. The plant publishes it before the gyro and one subscriber keeps that
# order, so it is normally there already; lock-step waits as for any promised message
# (bench/runtime/time_model.py: a late sample would change the run).
REAL_TIME_SAMPLE_WAIT_S = 0.005


def run(ctx: NodeContext) -> int:
    estimator = AttitudeEstimator(ctx.scenario)
    if estimator.needs_truth:
        return _run_truth(ctx, estimator)
    scenario = ctx.scenario
    inbox = SensorInbox(SensorSchedule.from_sensors(scenario.attitude.sensors), scenario.n_steps, scenario.step_s,
                        ctx.time_model.promised_wait_s(REAL_TIME_SAMPLE_WAIT_S), ctx.malformed, ctx.log)
    # One subscriber for the three: it keeps the plant's publishing order (the gyro last in a tick).
    ctx.subscribe_topics("sense/*", {keys.SENSE_GYRO: GyroSample, keys.SENSE_MAG: MagnetometerSample,
                                     keys.SENSE_STAR: StarTrackerSample}, inbox.add)
    ctx.declare_ready([keys.ESTIMATE_ATTITUDE])
    while (tick := inbox.next_tick(ctx.stop, STOP_POLL_S)) is not None:
        received_ns = time.monotonic_ns()
        hdr = tick.header or header(ctx.run_id, tick.seq, tick.sim_time_s)
        hdr = hdr.stamped("estimator_received", received_ns)
        try:
            estimate = estimator.step(tick.seq, tick.sim_time_s, tick.gyro_radps, tick.magnetometer_t,
                                      tick.field_model_inertial_t, tick.star_tracker_wxyz)
        except ValueError as exc:    # what the smoother still refuses: count, go on
            ctx.malformed[keys.SENSE_GYRO] += 1
            ctx.log.warning("attitude tick %d refused: %s", tick.seq, exc)
            continue
        _publish(ctx, hdr, estimate)
    if estimator.failed_updates:
        ctx.log.warning("attitude smoother updates failed and were re-initialised: %d", estimator.failed_updates)
    if inbox.late or inbox.missing or estimator.gyro_samples_held:
        ctx.log.warning("sensor samples late %s, missing %s; gyro samples held %d", dict(inbox.late),
                        dict(inbox.missing), estimator.gyro_samples_held)
    return 0


def _run_truth(ctx: NodeContext, estimator: AttitudeEstimator) -> int:
    samples = ctx.subscribe_queue(keys.TRUTH_ATTITUDE, AttitudeTruth)
    ctx.declare_ready([keys.ESTIMATE_ATTITUDE])
    for sample in ctx.until_stopped(samples):
        hdr = sample.header.stamped("estimator_received", time.monotonic_ns())
        _publish(ctx, hdr, estimator.truth_step(sample.q_wxyz, sample.omega_radps, sample.gyro_bias_radps,
                                                sample.field_body_t))
    return 0


def _publish(ctx: NodeContext, hdr, estimate) -> None:
    covariance = None if estimate.attitude_covariance_rad2 is None else estimate.attitude_covariance_rad2.ravel().tolist()
    # The magnetometer calibration goes out only when the smoother estimates it (None otherwise):
    # the report compares it with the plant's.
    mag_bias = None if estimate.magnetometer_bias_t is None else [float(v) for v in estimate.magnetometer_bias_t]
    mag_scale = None if estimate.magnetometer_scale is None else float(estimate.magnetometer_scale)
    ctx.publish(keys.ESTIMATE_ATTITUDE, AttitudeEstimate(
        hdr.stamped("estimated", time.monotonic_ns()), estimate.valid, estimate.q_wxyz.tolist(),
        estimate.omega_radps.tolist(), estimate.gyro_bias_radps.tolist(), estimate.field_body_t.tolist(), covariance,
        magnetometer_bias_t=mag_bias, magnetometer_scale=mag_scale))
