"""The flight side of the magnetorquer bus, inside the controller process.

The board drops to its safe state when commands stop for its command timeout (0.1 s), far shorter
than a 600 s plant step, so the driver commands on its own thread at its own period (CommandLoop),
with the dipole the scenario scripts, or from an attitude law's first dipole on (nothing before
it, so the first command frame, from which the bus faults count, is the loop's first step). A
law's dipole also goes out the moment the law gives it, in the "mixed" and "on_change"
transmission modes ([can.driver] transmission). Every fault the driver detects is logged as it
happens and written, with its detection latency, to can/driver.json.
"""
from __future__ import annotations

import json
import threading
from dataclasses import asdict

from bench.bus.can.config import CanConfig
from bench.bus.can.driver import CommandLoop, FaultEvent, MagnetorquerDriver
from bench.bus.can.nodes import can_dir, open_node_bus
from bench.runtime.node import NodeContext

DRIVER_REPORT_NAME = "driver.json"


class MagnetorquerLink:
    def __init__(self, ctx: NodeContext, config: CanConfig, scripted: bool = True):
        """scripted: command the scenario's dipole profile; False: the dipole a law sets
        (`self.loop.set_dipole`, zero until then)."""
        self.ctx = ctx
        self.bus = open_node_bus(ctx, config, "driver")
        self.driver = MagnetorquerDriver.from_config(self.bus, config)
        self.loop = CommandLoop(self.driver, config.driver.command_period_s,
                                dipole_at=config.dipole_at if scripted else None, on_events=self._log_events,
                                transmission="cyclic" if scripted else config.driver.transmission,
                                first_command_by_law=not scripted)
        self._thread = threading.Thread(target=self.loop.run, args=(ctx.stop,), name="mtq-driver", daemon=True)

    def _log_events(self, events: list[FaultEvent]) -> None:
        for event in events:
            self.ctx.log.warning("magnetorquer bus: %s after %.1f ms (%s %s)", event.kind, event.latency_s * 1e3,
                                 event.frame, event.detail)

    def start(self) -> None:
        if hasattr(self.bus, "wait_for_peers"):
            self.bus.wait_for_peers(1, 10.0)   # Zenoh delivers only to buses it already knows
        self._thread.start()

    def stop(self) -> None:
        """Join the command thread (ctx.stop is set by now) and write what the driver saw."""
        self._thread.join(timeout=2.0)
        health = self.loop.health
        report = {
            "health": asdict(health) | {"ok": health.ok},
            "events": [asdict(e) for e in self.driver.events],
        }
        (can_dir(self.ctx.run_dir) / DRIVER_REPORT_NAME).write_text(json.dumps(report, indent=1))
        self.bus.shutdown()
