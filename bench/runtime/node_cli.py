"""`bench node NAME`: run one bench process (the launcher starts each node this way; so does a
user on another host of a deployment).

Kept apart from the launcher so that a node's start-up imports only what the node needs: every
process of a run pays it, and on a slow host (UML's one CPU) the whole CLI cost tens of seconds.
"""
from __future__ import annotations

import logging
import sys
from pathlib import Path

from bench.bus import keys
from bench.bus.can.board_breaks import BREAKS as BOARD_BREAKS
from bench.bus.certs import CertificateError
from bench.bus.deployment import LAUNCHER, DeploymentError, load_deployment
from bench.bus.session import SessionConfigError
from bench.runtime.node import NODES, node_options, run_node
from bench.scenario import ScenarioError, load_scenario

EXIT_BAD_INPUT = 2


def cmd_node(args) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s", stream=sys.stdout)
    try:
        scenario = load_scenario(args.scenario)
        run_id = keys.check_run_id(args.run_id)
        run_dir = Path(args.run_dir or Path("runs") / run_id)
        run_dir.mkdir(parents=True, exist_ok=True)
        peers = [p for p in (args.wait_for or "").split(",") if p]
        options = node_options(args)
        stop_with, host = None, None
        if args.name in scenario.run.external:
            stop_with = LAUNCHER   # a node from outside (docs/contract.md): no launcher signals it
        if args.deployment:
            host = args.host
            if load_deployment(args.deployment).launcher_host != host:
                stop_with = LAUNCHER   # the launcher cannot signal another host: its leaving ends the run
        breaks = tuple(b for b in (args.breaks or ()) if b != "trust-inputs")
        return run_node(args.name, run_id, scenario, options, run_dir, peers, stop_with=stop_with, host=host,
                        trust_inputs="trust-inputs" in (args.breaks or ()), breaks=breaks,
                        allow_live_faults=args.allow_live_faults, live_port=args.live_port)
    except (ScenarioError, SessionConfigError, DeploymentError, CertificateError, ValueError) as exc:
        print(f"bench node: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT


def add_commands(subparsers) -> None:
    node = subparsers.add_parser("node", help="run one bench process (the launcher uses this; also for other hosts)")
    node.add_argument("name", choices=sorted(NODES), help="which process")
    node.add_argument("--run-id", required=True)
    node.add_argument("--scenario", help="built-in name, TOML or the run directory's scenario.json")
    node.add_argument("--listen", action="append", help="endpoint to listen on (default: an ephemeral loopback port)")
    node.add_argument("--connect", action="append", help="endpoint of the hub, a router or a peer (repeatable)")
    node.add_argument("--run-dir", help="run directory (default: runs/RUN_ID)")
    node.add_argument("--wait-for", help="comma-separated nodes whose ready token to await before starting")
    node.add_argument("--zenoh-config", help="JSON5 Zenoh configuration")
    node.add_argument("--cert-dir", help="certificate directory: mutual TLS as this node, access control on")
    node.add_argument("--deployment", help="deployment TOML (endpoints, certificates) ...")
    node.add_argument("--host", help="... and which of its hosts this is")
    node.add_argument("--break", dest="breaks", action="append", choices=["trust-inputs", *BOARD_BREAKS],
                      help="break this node on purpose, to see `bench contract check` fail it (self-test only, never "
                           "in a run): trust-inputs takes every input without checking its tag or counter; the others "
                           "break the board, node mtq (bench/bus/can/board_breaks.py)")
    node.add_argument("--allow-live-faults", action="store_true",
                      help="take faults injected while the run runs (canbus, the board; `bench run --allow-live-faults`)")
    node.add_argument("--live-port", type=int, help="node live: the Foxglove WebSocket port on loopback (`bench run --live`)")
    node.set_defaults(func=cmd_node)
