"""Scenario section [controller]."""
from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from bench.controller.deadline import DeadlineConfig

PositiveWeights = Annotated[list[Annotated[float, msgspec.Meta(gt=0)]], msgspec.Meta(min_length=1)]


class ControllerConfig(msgspec.Struct, forbid_unknown_fields=True):
    type: Literal["lqr"] = "lqr"
    # Q = diag(q_diag), R = diag(r_diag), on the scaled state (seed 003); defaults are Q*, R*.
    q_diag: PositiveWeights = msgspec.field(default_factory=lambda: [94.0, 0.1579, 300.0, 0.01, 0.10, 0.10])
    r_diag: PositiveWeights = msgspec.field(default_factory=lambda: [1.0, 1.0, 1.0])
    # Wall-clock budget per cycle, fallback on a miss, optional stress (bench/controller/deadline.py).
    deadline: DeadlineConfig = msgspec.field(default_factory=DeadlineConfig)
