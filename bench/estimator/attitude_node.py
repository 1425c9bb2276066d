"""The estimator process of the attitude loop.

reads:  sense/attitude (AttitudeSensors; smoother mode) or truth/attitude (AttitudeTruth; truth mode)
writes: estimate/attitude (AttitudeEstimate, one per plant step)
"""
from __future__ import annotations

import time

from bench.bus import keys
from bench.bus.schemas import AttitudeEstimate, AttitudeSensors, AttitudeTruth
from bench.estimator.attitude_frontend import AttitudeEstimator
from bench.runtime.node import NodeContext


def run(ctx: NodeContext) -> int:
    estimator = AttitudeEstimator(ctx.scenario)
    if estimator.needs_truth:
        samples = ctx.subscribe_queue(keys.TRUTH_ATTITUDE, AttitudeTruth)
    else:
        samples = ctx.subscribe_queue(keys.SENSE_ATTITUDE, AttitudeSensors)
    ctx.declare_ready([keys.ESTIMATE_ATTITUDE])
    for sample in ctx.until_stopped(samples):
        hdr = sample.header.stamped("estimator_received", time.monotonic_ns())
        if estimator.needs_truth:
            estimate = estimator.truth_step(sample.q_wxyz, sample.omega_radps, sample.gyro_bias_radps, sample.field_body_t)
        else:
            try:
                estimate = estimator.step(hdr.seq, hdr.sim_time_s, sample.gyro_radps, sample.field_model_inertial_t,
                                          sample.magnetometer_t, sample.star_tracker_wxyz)
            except ValueError as exc:    # a sample the smoother refuses (non-finite, not unit): count, go on
                ctx.malformed[keys.SENSE_ATTITUDE] += 1
                ctx.log.warning("attitude sample %d refused: %s", hdr.seq, exc)
                continue
        covariance = None if estimate.attitude_covariance_rad2 is None else estimate.attitude_covariance_rad2.ravel().tolist()
        ctx.publish(keys.ESTIMATE_ATTITUDE, AttitudeEstimate(
            hdr.stamped("estimated", time.monotonic_ns()), estimate.valid, estimate.q_wxyz.tolist(),
            estimate.omega_radps.tolist(), estimate.gyro_bias_radps.tolist(), estimate.field_body_t.tolist(), covariance))
    if estimator.failed_updates:
        ctx.log.warning("attitude smoother updates failed and were re-initialised: %d", estimator.failed_updates)
    return 0
