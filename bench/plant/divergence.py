"""Divergence of the simulated state: a non-finite or physically absurd state ends the run.

A state that left every plausible envelope (a relative position beyond the limit, a NaN) makes
every number computed after it meaningless; going on would only produce a metrics file full of
NaN. The plant stops at the first such step, names the step and the quantity, and exits with
EXIT_DIVERGED so the launcher can tell divergence from a crash.
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

EXIT_DIVERGED = 3
DIVERGENCE_FILE = "divergence.json"


@dataclass(frozen=True)
class Divergence:
    step: int
    quantity: str
    value: float | None      # None where it was not finite (JSON has no NaN)
    limit: float

    def describe(self) -> str:
        shown = "non-finite" if self.value is None else f"{self.value:.6g} (limit {self.limit:g})"
        return f"state diverged at step {self.step}: {self.quantity} = {shown}"

    def write(self, run_dir: Path) -> None:
        (run_dir / DIVERGENCE_FILE).write_text(json.dumps(asdict(self)))


def check_state(step: int, values: Sequence[float], names: Sequence[str], limits: Sequence[float]) -> Divergence | None:
    """The first quantity that is non-finite or beyond its limit (|value| > limit), else None."""
    for value, name, limit in zip(np.asarray(values, dtype=float), names, limits):
        if not math.isfinite(value):
            return Divergence(step, name, None, float(limit))
        if abs(value) > limit:
            return Divergence(step, name, float(value), float(limit))
    return None


def read_divergence(run_dir: Path) -> Divergence | None:
    """What the plant wrote when it stopped on divergence; None if it did not (or it is unreadable)."""
    try:
        data = json.loads((run_dir / DIVERGENCE_FILE).read_text())
        return Divergence(int(data["step"]), str(data["quantity"]),
                          None if data["value"] is None else float(data["value"]), float(data["limit"]))
    except (OSError, ValueError, KeyError, TypeError):
        return None
