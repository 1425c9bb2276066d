"""How a run ends: the launcher's exit codes, the exceptions that end a run early, and the ending
(code and reason) that metrics.json and the terminal are given.

Exit codes: 0 done, 1 a process failed or hung or the run stalled, 2 bad input (nothing started),
3 the plant's state diverged (EXIT_DIVERGED, bench/plant/divergence.py), 130 interrupted (SIGINT),
143 terminated (SIGTERM).
"""
from __future__ import annotations

import signal
from dataclasses import dataclass

EXIT_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143


class NodeFailed(RuntimeError):
    pass


class Diverged(RuntimeError):
    pass


class RunInterrupted(BaseException):
    """SIGINT or SIGTERM to the launcher (a BaseException, like KeyboardInterrupt)."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum

    @property
    def exit_code(self) -> int:
        return EXIT_INTERRUPTED if self.signum == signal.SIGINT else EXIT_TERMINATED


@dataclass
class RunEnding:
    code: int
    reason: str | None      # None: the run finished; else why it ended early (first line)
