"""The command line of the launcher: `bench run` (its options, the run id, the scenario's
overrides, where the run is placed) and `bench scenarios`."""
from __future__ import annotations

import secrets
import sys
from datetime import datetime, timezone
from pathlib import Path

import msgspec

from bench.bus import keys
from bench.bus.certs import CertificateError
from bench.bus.deployment import DeploymentError, load_deployment
from bench.bus.session import SessionConfigError
from bench.launcher.endings import EXIT_BAD_INPUT
from bench.launcher.parts import LIVE_DEFAULT_PORT, LIVE_NODE, nodes_for
from bench.launcher.placement import deployment_placement, local_placement, make_local_certs
from bench.launcher.run import run_bench
from bench.runtime import zygote as node_zygote
from bench.scenario import EXTERNAL_PARTS, Scenario, ScenarioError, builtin_names, load_scenario, parse_scenario


# ------------------------------------------------------------------------------------------------
# bench run
# ------------------------------------------------------------------------------------------------
def _new_run_id(scenario: Scenario) -> str:
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S")
    return f"{scenario.name}-{stamp}-{secrets.token_hex(2)}"


def _apply_overrides(scenario: Scenario, args) -> Scenario:
    run = scenario.run
    if args.mode:
        run = msgspec.structs.replace(run, mode=args.mode)
    if getattr(args, "external", None):
        run = msgspec.structs.replace(run, external=sorted(set(run.external) | set(args.external)))
    if args.steps is not None:
        from bench.scenario import MAX_STEPS

        if not 1 <= args.steps <= MAX_STEPS:
            raise ScenarioError(f"--steps must be 1-{MAX_STEPS}, got {args.steps}")
        run = msgspec.structs.replace(run, steps=args.steps)
    return parse_scenario(msgspec.to_builtins(msgspec.structs.replace(scenario, run=run)), "command line")


def cmd_run(args) -> int:
    try:
        scenario = _apply_overrides(load_scenario(args.scenario), args)
        run_id = keys.check_run_id(_new_run_id(scenario) if args.run_id is None else args.run_id)
        if args.port is not None and not 0 < args.port < 65536:
            raise ScenarioError(f"--port must be between 1 and 65535, got {args.port}")
        placement = None
        if args.deployment:
            if args.port is not None:
                raise DeploymentError("--port: the deployment file names the hub's endpoint")
            placement = deployment_placement(load_deployment(args.deployment), Path(args.deployment),
                                             nodes_for(scenario) + ([LIVE_NODE] if args.live is not None else []),
                                             args.zenoh_config)
        elif args.secure:
            # Not in runs/<run_id>: the run claims that directory new (a second run with a live id is refused).
            cert_dir = Path(args.cert_dir) if args.cert_dir else make_local_certs(Path(args.runs_dir) / ".certs" / run_id)
            placement = local_placement(args.port, args.zenoh_config, cert_dir)
        if args.live is not None and not 0 < args.live < 65536:
            raise ScenarioError(f"--live PORT must be between 1 and 65535, got {args.live}")
        code, _ = run_bench(scenario, run_id, Path(args.runs_dir), args.port, not args.no_progress, args.zenoh_config,
                            write_report=not args.no_report, placement=placement, live_port=args.live,
                            allow_live_faults=args.allow_live_faults)
        return code
    except (ScenarioError, SessionConfigError, DeploymentError, CertificateError, ValueError) as exc:
        print(f"bench: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    finally:
        node_zygote.Zygote.close_early()    # started by bench.cli for this run, if run_bench never took it


# ------------------------------------------------------------------------------------------------
# bench scenarios
# ------------------------------------------------------------------------------------------------
def cmd_scenarios(_args) -> int:
    for name in builtin_names():
        print(f"{name:28s} {load_scenario(name).description}")
    return 0


def add_commands(subparsers) -> None:
    run = subparsers.add_parser("run", help="run a scenario: plant, estimator and controller as processes")
    run.add_argument("scenario", nargs="?", help="built-in name or TOML file (default: rendezvous_lqr)")
    run.add_argument("--run-id", help="name of the run (default: scenario name and time)")
    run.add_argument("--runs-dir", default="runs", help="where run directories go (default: runs)")
    run.add_argument("--port", type=int, help="loopback TCP port of the hub session (default: a free one)")
    run.add_argument("--mode", choices=["lock-step", "real-time"], help="override the scenario's run.mode")
    run.add_argument("--steps", type=int, help="override the scenario's run.steps")
    run.add_argument("--zenoh-config", help="JSON5 Zenoh configuration applied under the bench's own settings")
    run.add_argument("--secure", action="store_true",
                     help="mutual TLS and access control on loopback, with certificates made for this run")
    run.add_argument("--cert-dir", help="with --secure: certificates to use (default: new ones in the run directory)")
    run.add_argument("--deployment", help="deployment TOML: which node runs on which host (see docs/security.md)")
    run.add_argument("--external", action="append", choices=list(EXTERNAL_PARTS),
                     help="a part provided from outside: not started, waited for under its name (docs/contract.md)")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    run.add_argument("--no-report", action="store_true", help="skip report.html/report.md (bench report RUN_DIR later)")
    run.add_argument("--live", nargs="?", type=int, const=LIVE_DEFAULT_PORT, metavar="PORT",
                     help=f"watch the run in Foxglove: a WebSocket server on 127.0.0.1:PORT (default {LIVE_DEFAULT_PORT}) "
                          "with the run's topics as they happen (docs/live.md); put it after the scenario")
    run.add_argument("--allow-live-faults", action="store_true",
                     help="take faults injected while the run runs (`bench inject`, the live view's service); "
                          "refused otherwise")
    run.set_defaults(func=cmd_run)

    scenarios = subparsers.add_parser("scenarios", help="list the built-in scenarios")
    scenarios.set_defaults(func=cmd_scenarios)
