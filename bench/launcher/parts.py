"""Which processes a scenario needs: the nodes the launcher starts, in start order, the parts
provided from outside ([run] external, `--external`), and the nodes' roles that decide the order
they stop in (the board side, the watchers)."""
from __future__ import annotations

import msgspec

from bench.bus.can.sim_window import bus_on_simulated_time
from bench.config.controller import PLANNED_LAWS
from bench.runtime.node import NODES
from bench.scenario import Scenario, ScenarioError


def nodes_for(scenario: Scenario) -> list[str]:
    """In start order (they stop in stop_stages' order). The recorder first and last, so it sees
    everything; the CAN bus and board before the flight side and after it, so the driver never sees
    the board vanish at shutdown."""
    names = ["recorder"] if "recorder" in NODES else []
    if scenario.can is not None:
        # On simulated time the board runs with the bus model, in canbus (bench/bus/can/lockstep_bus.py).
        if not board_is_external(scenario):     # else the driver and the plant are on the board's bus
            names += ["canbus"] if bus_on_simulated_time(scenario) else ["canbus", "mtq"]
    names += ["plant", "estimator", "controller"]
    if scenario.kind == "attitude" and scenario.attitude_control.law in PLANNED_LAWS:
        names.append("planner")    # MILQR plans for the controller's tracker (issue 12)
    return names


EXTERNAL_HOST = "external"   # the "host" of a part provided from outside (docs/contract.md)


def external_parts(scenario: Scenario) -> dict[str, str]:
    """[run] external's Zenoh nodes: node -> EXTERNAL_HOST. They join as nodes on other hosts do
    (not spawned, waited for and watched by their liveliness token), so they reuse the `remote`
    placement. An external board is no Zenoh node (it is on the CAN bus only): not in here, but
    nodes_for starts neither the simulated board nor the bus model for it."""
    external = scenario.run.external
    if len(set(external)) != len(external):
        raise ScenarioError(f"run.external: a part named twice ({', '.join(external)})")
    if "board" in external:
        if scenario.kind != "attitude" or scenario.can is None:
            raise ScenarioError("run.external: \"board\" is the magnetorquer board on the CAN bus: the attitude "
                                "loop with [can] only")
        if scenario.run.mode == "lock-step" and scenario.can.lock_step_clock == "simulated":
            raise ScenarioError("run.external: an external \"board\" runs on its own (wall) clock: in lock-step "
                                "[can] lock_step_clock must be \"auto\" or \"wall\", not \"simulated\" "
                                "(and the board must acknowledge its commands with MTQ_TLM_SETPOINT; a board "
                                "without it runs in real time only: docs/can-bus.md)")
    return {name: EXTERNAL_HOST for name in external if name != "board"}


def board_is_external(scenario: Scenario) -> bool:
    return "board" in scenario.run.external


BOARD_SIDE_NODES = ("mtq", "canbus")    # what an external board replaces: the simulated board and the bus model
WATCHERS = ("recorder", "live")          # they stop last: every other node's last messages are theirs too
LIVE_NODE = "live"                       # `--live`: the Foxglove WebSocket server (bench/live/node.py, docs/live.md)
LIVE_DEFAULT_PORT = 8765                 # Foxglove's default WebSocket port


def with_driver_on_the_board_bus(scenario: Scenario) -> Scenario:
    """An external board has no bus model between it and the driver: unless [can.driver_bus] names
    the driver's own bus, the driver (and the plant, which hears the board's telemetry) open the
    board's bus ([can.board_bus], else the transport on board_channel). Written into the run's
    scenario.json, so an external controller started from it opens the same bus."""
    if not board_is_external(scenario) or scenario.can.driver_bus is not None:
        return scenario
    can_config = msgspec.structs.replace(scenario.can, driver_bus=scenario.can.bus_spec("board"))
    return msgspec.structs.replace(scenario, can=can_config)
