"""`bench run`, `bench node` and `bench scenarios`: starting the loop as separate processes.

The launcher opens the hub session every node connects to, starts each node as its own OS process
(`bench node NAME ...`), waits until all are alive, follows the plant's progress, and shuts
everything down on success, on Ctrl-C or SIGTERM, and when a node dies, hangs or the plant's state
diverges, or its steps stop advancing (bench/runtime/progress_watchdog.py: the stage that stopped is
named). Then it writes metrics.json and the report, marked partial with the reason when the run
did not finish. The nodes die with it even when it is killed (bench/runtime/ownership.py); a second
Ctrl-C kills them at once and exits within a bounded time.

Exit codes: 0 done, 1 a process failed or hung or the run stalled, 2 bad input (nothing started),
3 the plant's state diverged, 130 interrupted (SIGINT), 143 terminated (SIGTERM).

One concern a module:
- commands.py: the command line (`bench run`'s options and overrides, `bench scenarios`)
- run.py: run_bench, one run from the hub session to what it leaves
- parts.py: which processes a scenario needs, and the parts provided from outside
- placement.py: where the sessions are (this host's loopback, or a deployment's hosts)
- run_dir.py: the run directory, claimed and locked for the run
- children.py: the node processes on this host: started, stopped in stages, their exits judged
- liveliness.py: the nodes' presence answers: alive at start, hung or stopped later, gone at the end
- follow.py: following the run until the plant finishes, and every look that ends it early
- stats.py: the processes' reports (stats, the plant's steps), taken only when genuine
- signals.py: SIGINT and SIGTERM during a run
- endings.py: exit codes, the exceptions that end a run, the ending metrics.json is given
- finish.py: metrics.json, the report and the summary, however the run ended
- campaign.py: one campaign case as a multi-process run

This module is what the rest of the bench imports: `bench.cli` finds add_commands here, the
campaign its runner ("bench.launcher:campaign_case"), the contract's check run_bench.
"""
from __future__ import annotations

from bench.launcher.campaign import campaign_case
from bench.launcher.children import Child, ProcessGroup, _check_children, stop_stages
from bench.launcher.commands import add_commands, cmd_run, cmd_scenarios
from bench.launcher.endings import (EXIT_BAD_INPUT, EXIT_FAILED, EXIT_INTERRUPTED, EXIT_TERMINATED, Diverged,
                                    NodeFailed, RunEnding, RunInterrupted)
from bench.launcher.liveliness import TokenLoss, _check_liveliness, _wait_alive
from bench.launcher.parts import (BOARD_SIDE_NODES, EXTERNAL_HOST, LIVE_DEFAULT_PORT, LIVE_NODE, WATCHERS,
                                  board_is_external, external_parts, nodes_for, with_driver_on_the_board_bus)
from bench.launcher.placement import Placement, deployment_placement, local_placement, make_local_certs
from bench.launcher.run import run_bench
from bench.launcher.run_dir import RunDirClaim, RunIdTaken
from bench.launcher.signals import SignalGuard
from bench.launcher.stats import StatsCollector, unauthentic_drops

__all__ = [
    "BOARD_SIDE_NODES", "EXIT_BAD_INPUT", "EXIT_FAILED", "EXIT_INTERRUPTED", "EXIT_TERMINATED", "EXTERNAL_HOST",
    "LIVE_DEFAULT_PORT", "LIVE_NODE", "WATCHERS", "Child", "Diverged", "NodeFailed", "Placement", "ProcessGroup",
    "RunDirClaim", "RunEnding", "RunIdTaken", "RunInterrupted", "SignalGuard", "StatsCollector", "TokenLoss",
    "add_commands", "board_is_external", "campaign_case", "cmd_run", "cmd_scenarios", "deployment_placement",
    "external_parts", "local_placement", "make_local_certs", "nodes_for", "run_bench", "stop_stages",
    "unauthentic_drops", "with_driver_on_the_board_bus",
    # The tests drive these checks directly (tests/test_scenario_strict.py, tests/test_hang_detection.py).
    "_check_children", "_check_liveliness", "_wait_alive",
]
