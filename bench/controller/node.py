"""The controller process: estimate in, thrust command out, once per plant step, under a deadline.

reads:  estimate/translation (TranslationEstimate; real time: the newest, those queued behind it
        passed over and counted, bench/controller/newest.py)
writes: command/thrust (ThrustCommand), event/deadline (DeadlineEvent, on a miss)

Every cycle runs under the deadline monitor (in real-time mode the law runs in a solver worker
process, bench/runtime/solver_worker.py, so the command leaves by the deadline); a miss applies the configured fallback and is
published as a DeadlineEvent as it happens. The monitor's summary goes to deadline.json.
"""
from __future__ import annotations

import importlib
import json
import time

import numpy as np

from bench.bus import keys
from bench.bus.schemas import ThrustCommand, TranslationEstimate
from bench.controller.cycle import ControlCycle
from bench.controller.mtq_link import MagnetorquerLink
from bench.controller.newest import NewestEstimate
from bench.runtime.node import NodeContext


def run(ctx: NodeContext) -> int:
    if ctx.scenario.kind == "attitude":
        # By name, as NODES finds nodes: the attitude process reuses this module's pieces.
        return importlib.import_module("bench.controller.attitude_node").run(ctx)
    control = ControlCycle(ctx.scenario)
    # The scripted dipole starts with the loop's first step: the bus's faults count from its first
    # command frame, so their start_s is the run's simulated time (bench.bus.can.sim_window.fault_clock_scale).
    mtq = MagnetorquerLink(ctx, ctx.scenario.can, start_with_loop=True) if ctx.scenario.can is not None else None
    if mtq is not None:
        mtq.start()
    estimates = ctx.subscribe_queue(keys.ESTIMATE_TRANSLATION, TranslationEstimate)
    newest = NewestEstimate(ctx.time_model)
    ctx.declare_publisher(keys.EVENT_DEADLINE)
    ctx.declare_ready([keys.COMMAND_THRUST])
    for estimate in ctx.until_stopped(estimates):
        estimate = newest.take(estimates, estimate)
        if mtq is not None:
            mtq.loop_started()
        received_ns = time.monotonic_ns()
        hdr = estimate.header.stamped("controller_received", received_ns)
        state_m_mps = np.array(estimate.state_m_mps) if estimate.valid else None
        outcome = control.run(state_m_mps, estimate.mean_motion_radps, start_ns=received_ns,
                              step=estimate.header.seq)
        hdr = hdr.stamped("commanded", time.monotonic_ns())
        info = outcome.info
        ctx.publish(keys.COMMAND_THRUST, ThrustCommand(
            hdr, outcome.thrust_n.tolist(), bool(info.get("ctrl_feas", False)), str(info.get("status", "")),
            float(info.get("solve_time", 0.0)), int(info.get("iterations", 0)), outcome.fallback,
        ))
        if outcome.has_event:
            ctx.publish(keys.EVENT_DEADLINE, outcome.deadline_event(hdr))
    if mtq is not None:
        mtq.stop()
    control.close()
    summary = control.summary() | {"stale_estimates_skipped": newest.skipped}
    (ctx.run_dir / "deadline_controller.json").write_text(json.dumps(summary, indent=2))
    return 0
