"""The estimator process: turns the plant's sensing into a state estimate for the controller.

truth mode: ground truth passed through. smoother mode: the relative-position fix of step k plus
the thrust the controller commanded at step k-1 (what the flight side knows it asked for).

Reads: sense/relpos (RelativePosition) or sense/range_bearing (RangeBearing), whichever sensor
the smoother uses, and command/thrust (ThrustCommand); truth (TruthState) in truth mode. Writes: estimate/translation (TranslationEstimate, with the measurement's NIS and
whether the innovation gate rejected it). A fix that arrives after a later one (late) is applied
at its sensing step inside the smoother's window and published with the next step's estimate.
"""
from __future__ import annotations

import importlib
import queue
import time

import numpy as np

from bench.bus import keys
from bench.bus.schemas import RangeBearing, RelativePosition, ThrustCommand, TranslationEstimate, TruthState
from bench.estimator.frontend import StateEstimator
from bench.runtime.node import NodeContext


class CommandHistory:
    """Thrust commanded per step, from the controller's published commands."""

    def __init__(self, commands: "queue.Queue[ThrustCommand]"):
        self._queue = commands
        self._by_seq: dict[int, np.ndarray] = {}
        self._last = np.zeros(3)

    def thrust_for(self, seq: int, wait_s: float) -> np.ndarray:
        """Thrust commanded for step `seq` (the last one known if it does not come in time)."""
        deadline = time.monotonic() + wait_s
        while seq not in self._by_seq:
            remaining = deadline - time.monotonic()
            try:
                command = self._queue.get(timeout=remaining) if remaining > 0 else self._queue.get_nowait()
            except queue.Empty:
                break
            self._by_seq[command.header.seq] = np.array(command.thrust_n)
        if seq in self._by_seq:
            self._last = self._by_seq[seq]
        self._by_seq = {k: v for k, v in self._by_seq.items() if k > seq}
        return self._last


def run(ctx: NodeContext) -> int:
    if ctx.scenario.kind == "attitude":
        # By name, as NODES finds nodes: the attitude process reuses this module's pieces.
        return importlib.import_module("bench.estimator.attitude_node").run(ctx)
    scenario = ctx.scenario
    estimator = StateEstimator(scenario)
    if estimator.needs_truth:
        samples = ctx.subscribe_queue(keys.TRUTH, TruthState)
        history = None
    elif estimator.sensor == "range_bearing":
        samples = ctx.subscribe_queue(keys.SENSE_RANGE_BEARING, RangeBearing)
        history = CommandHistory(ctx.subscribe_queue(keys.COMMAND_THRUST, ThrustCommand))
    else:
        samples = ctx.subscribe_queue(keys.SENSE_RELPOS, RelativePosition)
        history = CommandHistory(ctx.subscribe_queue(keys.COMMAND_THRUST, ThrustCommand))
    # How long to wait for command k-1 once fix k is in: in lock-step it was sent before fix k was
    # taken, so it is on its way; in real time one not in yet means the plant held the last one.
    command_wait_s = ctx.time_model.promised_wait_s(real_time_s=0.0)
    ctx.declare_ready([keys.ESTIMATE_TRANSLATION])
    for sample in ctx.until_stopped(samples):
        hdr = sample.header.stamped("estimator_received", time.monotonic_ns())
        k = hdr.seq
        if history is None:
            estimate = estimator.step(k, hdr.sim_time_s, truth_m_mps=sample.state_m_mps)
        else:
            measured = (dict(range_bearing=sample.fix)     # None without a fix: a prediction step
                        if isinstance(sample, RangeBearing) else dict(position_m=sample.position_m))
            if estimator.is_late(k):
                # Applied at its sensing step; the controller gets it in the next step's estimate.
                estimator.step(k, hdr.sim_time_s, **measured)
                continue
            thrust_n = history.thrust_for(k - 1, command_wait_s) if k > 0 else np.zeros(3)
            estimate = estimator.step(k, hdr.sim_time_s, thrust_commanded_n=thrust_n, **measured)
        hdr = hdr.stamped("estimated", time.monotonic_ns())
        if estimate is None:
            # No fix yet: say so every step, so the loop goes on (the controller coasts) instead
            # of waiting for an estimate that cannot come.
            ctx.publish(keys.ESTIMATE_TRANSLATION, TranslationEstimate(hdr, [0.0] * 6, valid=False))
            continue
        covariance = None if estimate.covariance is None else estimate.covariance.ravel().tolist()
        ctx.publish(keys.ESTIMATE_TRANSLATION, TranslationEstimate(
            hdr, estimate.state_m_mps.tolist(), covariance, estimate.mean_motion_radps,
            estimate.nis, estimate.nis_dof, estimate.measurement_rejected))
    if estimator.failed_updates:
        ctx.log.warning("smoother updates failed and were re-initialised: %d", estimator.failed_updates)
    return 0
