"""The estimator process: turns the plant's sensing into a state estimate for the controller.

mode "truth" passes ground truth through (seed 001's full state knowledge).
"""
from __future__ import annotations

import queue
import time

from bench.bus import keys
from bench.bus.schemas import TranslationEstimate, TruthState
from bench.estimator.truth import TruthEstimator
from bench.node_runtime import NodeContext


def run(ctx: NodeContext) -> int:
    estimator = TruthEstimator()
    truths = ctx.subscribe_queue(keys.TRUTH, TruthState)
    ctx.declare_ready([keys.ESTIMATE_TRANSLATION])
    while not ctx.stop.is_set():
        try:
            truth = truths.get(timeout=0.2)
        except queue.Empty:
            continue
        hdr = truth.header.stamped("estimator_received", time.monotonic_ns())
        state_m_mps, covariance, mean_motion = estimator.estimate(truth.state_m_mps)
        hdr = hdr.stamped("estimated", time.monotonic_ns())
        ctx.publish(keys.ESTIMATE_TRANSLATION, TranslationEstimate(
            hdr, state_m_mps.tolist(),
            None if covariance is None else covariance.ravel().tolist(),
            mean_motion,
        ))
    return 0
