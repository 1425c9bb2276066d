"""`bench faults`: the faults a scenario's [[can.faults]] can name, with their parameters."""
from __future__ import annotations

from rich.console import Console
from rich.table import Table

from bench.bus.can.faults import FAULTS, Param

COMMON = ("every fault also takes: frames (DBC message names), start_s, duration_s, "
          "count (frames affected, 0 = no limit), every (act on every n-th matching frame)")


def _describe(param: Param) -> str:
    if isinstance(param.default, bool):
        value = f"{param.name} = {str(param.default).lower()}"
    else:
        value = f"{param.name} = {param.default} [{param.low}, {param.high}]{' ' + param.unit if param.unit else ''}"
    return f"{value}: {param.doc}" if param.doc else value


def cmd_faults(_args) -> int:
    table = Table(title="CAN faults (bus model)", show_lines=True)
    table.add_column("name", no_wrap=True)
    for column in ("what it does", "acts", "default frames", "parameters"):
        table.add_column(column, overflow="fold")
    for fault in FAULTS.values():
        table.add_row(fault.name, fault.summary,
                      "per frame" if fault.trigger == "frame" else "time window (needs duration_s)",
                      ", ".join(fault.default_frames) or "-",
                      "\n".join(_describe(p) for p in fault.params) or "-")
    console = Console()
    console.print(table)
    console.print(COMMON)
    return 0


def add_commands(subparsers) -> None:
    faults = subparsers.add_parser("faults", help="list the CAN faults a scenario can inject, with their parameters")
    faults.set_defaults(func=cmd_faults)
