"""The `bench` command. Each part of the bench contributes its own subcommands.

A module listed in COMMAND_MODULES provides `add_commands(subparsers)`; each subcommand sets
`func(args) -> int` with its parser's `set_defaults`. Exit code 2 means bad input.
"""
from __future__ import annotations

import argparse
import importlib
import sys

COMMAND_MODULES = [
    "bench.launcher",          # run, node, scenarios
    "bench.bus.can.vcan",      # vcan up/down
    "bench.report.cli",        # report, compare
    "bench.bus.can.cli",       # faults
    "bench.studies.cli",       # tune-lqr, compare-controllers
    "bench.studies.campaign_cli",   # campaign, campaign-report
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="bench", description="Orbit HIL bench for spacecraft GNC")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).add_commands(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
