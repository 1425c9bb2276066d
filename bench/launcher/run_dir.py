"""The run directory, runs/<run_id>: claimed new for the run and locked while it lasts, so a live
run id or an earlier run's directory is refused before anything is written or started."""
from __future__ import annotations

import fcntl
import os
from pathlib import Path

LOCK_FILE = ".lock"


class RunIdTaken(ValueError):
    """The run id is in use by a live run, or its directory holds an earlier run."""


class RunDirClaim:
    """runs/<run_id>, created for this run and locked while it lasts (flock: released by the kernel
    when the launcher dies, however it dies). A live id, or a directory holding an earlier run, is
    refused before anything is written or started."""

    def __init__(self, run_dir: Path):
        self.run_dir = run_dir
        run_dir.parent.mkdir(parents=True, exist_ok=True)
        try:
            run_dir.mkdir()
        except FileExistsError:
            raise RunIdTaken(self._taken_message()) from None
        self._lock = open(run_dir / LOCK_FILE, "w")
        fcntl.flock(self._lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        self._lock.write(str(os.getpid()))
        self._lock.flush()

    def _taken_message(self) -> str:
        run_id = self.run_dir.name
        try:
            with open(self.run_dir / LOCK_FILE) as f:
                try:
                    fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    return f"run id {run_id!r} is in use by a running bench (pid {f.read().strip() or '?'}); choose another --run-id"
        except OSError:
            pass
        return f"run id {run_id!r}: {self.run_dir} already holds a run; choose another --run-id or remove it"

    def release(self) -> None:
        self._lock.close()
