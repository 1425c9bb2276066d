"""`bench faults`: the faults a scenario's [[can.faults]] can name, with their parameters."""
from __future__ import annotations

from rich.console import Console
from rich.table import Table

from bench.bus.can.faults import FAULTS, Param

COMMON = ("every fault also takes start_s and duration_s (the run's simulated seconds from the first command frame); "
          "a frame fault also frames (DBC message names), count (frames affected, 0 = no limit) and every (act on "
          "every n-th matching frame). Retired: board_death (use board_power_loss), stuck_actuator (use "
          "telemetry_freeze or coil_stuck)")
ACTS = {"frame": "per frame", "window": "time window (needs duration_s)",
        "hardware": "the board's hardware, from start_s (for duration_s, or to the end)"}


def _describe(param: Param) -> str:
    if isinstance(param.default, bool):
        value = f"{param.name} = {str(param.default).lower()}"
    else:
        value = f"{param.name} = {param.default} [{param.low}, {param.high}]{' ' + param.unit if param.unit else ''}"
    return f"{value}: {param.doc}" if param.doc else value


def cmd_faults(_args) -> int:
    table = Table(title="CAN faults (bus model and the board's hardware)", show_lines=True)
    table.add_column("name", no_wrap=True)
    for column in ("what it does", "acts", "default frames", "parameters"):
        table.add_column(column, overflow="fold")
    for fault in FAULTS.values():
        table.add_row(fault.name, fault.summary,
                      ACTS[fault.trigger] + (" (needs duration_s)" if fault.needs_duration else ""),
                      ", ".join(fault.default_frames) or "-",
                      "\n".join(_describe(p) for p in fault.params) or "-")
    console = Console()
    console.print(table)
    console.print(COMMON)
    return 0


def add_commands(subparsers) -> None:
    faults = subparsers.add_parser("faults", help="list the CAN faults a scenario can inject, with their parameters")
    faults.set_defaults(func=cmd_faults)
