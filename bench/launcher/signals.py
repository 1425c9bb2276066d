"""SIGINT and SIGTERM during a run: the first ends the run in order at the launcher's next look,
a second kills every node at once and exits within a bounded time."""
from __future__ import annotations

import os
import signal
import threading

from bench.launcher.children import ProcessGroup
from bench.launcher.endings import RunInterrupted

# After a second Ctrl-C (or SIGTERM) the launcher kills every node and exits within this, even if
# a Zenoh call it is in never returns.
HARD_EXIT_S = 2.5


class SignalGuard:
    """SIGINT and SIGTERM during a run. The first is noted, and the launcher's next look (`check`,
    at most a few tenths of a second away in its waits) raises RunInterrupted there; it stops the
    nodes in order and writes what the run left. A second one kills every node at once and arms a
    hard exit HARD_EXIT_S later.

    The handler itself never raises: Python runs it between any two bytecodes of the main thread,
    and an exception raised there can land inside an import's module-lock bookkeeping (dropped as
    "Exception ignored", CI105) or leave that lock half taken, after which the report's import
    waited forever (CI2 of issue 44: "stopping all processes", "building the report", then no
    exit for 120 s)."""

    def __init__(self, group: ProcessGroup):
        self.group = group
        self.first: int | None = None
        self.delivered = False      # the first signal's RunInterrupted reached the launcher's handler
        self.hurry = False
        self._saved: dict = {}

    def __enter__(self) -> "SignalGuard":
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, signal.SIGTERM):
                self._saved[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for signum, handler in self._saved.items():
            signal.signal(signum, handler)

    def check(self) -> None:
        """Raise the first signal's RunInterrupted, once (the launcher's waits call this at every
        look; the cleanup that follows is not interrupted again)."""
        if self.first is not None and not self.delivered:
            self.delivered = True
            raise RunInterrupted(self.first)

    def _handle(self, signum, _frame) -> None:
        if self.first is None:
            self.first = signum       # raised at the next look (check), never from here
            return
        if not self.hurry:
            self.hurry = True
            self.group.kill()
            code = RunInterrupted(self.first).exit_code
            timer = threading.Timer(HARD_EXIT_S, os._exit, (code,))
            timer.daemon = True
            timer.start()
