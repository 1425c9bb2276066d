"""The `bench` command. Each part of the bench contributes its own subcommands.

A module listed in COMMAND_MODULES provides `add_commands(subparsers)`; each subcommand sets
`func(args) -> int` with its parser's `set_defaults`. Exit code 2 means bad input.

Only the module that owns the requested command is imported: every bench process starts through
`bench node`, and importing every command (studies, reports, campaigns, deployment) cost each
process seconds on a loaded host and tens of seconds on UML's one CPU. `bench --help` and an
unknown command import them all, so the help lists everything.
"""
from __future__ import annotations

import argparse
import importlib
import sys

# Command name -> the module that adds it.
COMMAND_MODULES: dict[str, str] = {
    "run": "bench.launcher",
    "scenarios": "bench.launcher",
    "node": "bench.runtime.node_cli",
    "certs": "bench.bus.deploy_cli",
    "router": "bench.bus.deploy_cli",
    "vcan": "bench.bus.can.vcan",
    "report": "bench.report.cli",
    "compare": "bench.report.cli",
    "faults": "bench.bus.can.cli",
    "tune-lqr": "bench.studies.cli",
    "compare-controllers": "bench.studies.cli",
    "mpc-studies": "bench.studies.cli",
    "compare-attitude": "bench.studies.attitude_comparison",
    "campaign": "bench.studies.campaign_cli",
    "campaign-report": "bench.studies.campaign_cli",
    "contract": "bench.contract_check.cli",
    "inject": "bench.live.inject_cli",
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser for `command` alone, or for every command when it is None or unknown."""
    parser = argparse.ArgumentParser(prog="bench", description="Orbit HIL bench for spacecraft GNC")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    if command in COMMAND_MODULES:
        modules = [COMMAND_MODULES[command]]
    else:
        modules = list(dict.fromkeys(COMMAND_MODULES.values()))
    for name in modules:
        importlib.import_module(name).add_commands(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    if command == "run" and not {"-h", "--help"} & set(argv):
        # The nodes' imports (about a second) start now, beside the launcher's (bench/runtime/zygote.py).
        from bench.runtime.zygote import Zygote
        Zygote.start_early()
    args = build_parser(command).parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
