"""The controller process: estimate in, thrust command out, once per plant step."""
from __future__ import annotations

import queue
import time

import numpy as np

from bench.bus import keys
from bench.bus.schemas import ThrustCommand, TranslationEstimate
from bench.controller.thrust import ThrustLaw
from bench.node_runtime import NodeContext


def run(ctx: NodeContext) -> int:
    law = ThrustLaw(ctx.scenario)
    estimates = ctx.subscribe_queue(keys.ESTIMATE_TRANSLATION, TranslationEstimate)
    ctx.declare_ready([keys.COMMAND_THRUST])
    while not ctx.stop.is_set():
        try:
            estimate = estimates.get(timeout=0.2)
        except queue.Empty:
            continue
        hdr = estimate.header.stamped("controller_received", time.monotonic_ns())
        thrust_n, info = law.command(np.array(estimate.state_m_mps))
        hdr = hdr.stamped("commanded", time.monotonic_ns())
        ctx.publish(keys.COMMAND_THRUST, ThrustCommand(
            hdr, thrust_n.tolist(), bool(info["ctrl_feas"]), str(info["status"]),
            float(info["solve_time"]), int(info.get("iterations", 0)),
        ))
    return 0
