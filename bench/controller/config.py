"""Scenario section [controller]: which controller and its weights (seed 003)."""
from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from bench.controller.deadline import DeadlineConfig

PositiveWeights = Annotated[list[Annotated[float, msgspec.Meta(gt=0, le=1e12)]], msgspec.Meta(min_length=1, max_length=64)]
# The QP grows with N (3N inputs, 6N states); 1000 steps is already a 9000-variable QP per cycle.
Horizon = Annotated[int, msgspec.Meta(ge=1, le=1000)]


class ControllerConfig(msgspec.Struct, forbid_unknown_fields=True):
    # lqr: u = K x (task 6). mpc: LQR terminal cost (17). mpc_te: terminal equality (18).
    # mpc_ts: terminal set X_LQR (19). mpc_ts_sc: mpc_ts with soft state constraints (20).
    # mpc_tube: tube MPC (23) on the out-of-plane axis [z, vz], mpc with LQR terminal cost in plane.
    type: Literal["lqr", "mpc", "mpc_te", "mpc_ts", "mpc_ts_sc", "mpc_tube"] = "lqr"
    # Q = diag(q_diag), R = diag(r_diag), on the scaled state (seed 003); defaults are Q*, R*.
    q_diag: PositiveWeights = msgspec.field(default_factory=lambda: [94.0, 0.1579, 300.0, 0.01, 0.10, 0.10])
    r_diag: PositiveWeights = msgspec.field(default_factory=lambda: [1.0, 1.0, 1.0])
    horizon: Horizon = 30                               # N, prediction steps (seed: 30; tube 50)
    # mpc_ts_sc: slack penalty eps'S eps + v ||eps||_inf with S = soft_quadratic_weight * I (task 23).
    soft_quadratic_weight: Annotated[float, msgspec.Meta(gt=0, le=1e12)] = 1.0e3
    soft_linf_weight: Annotated[float, msgspec.Meta(ge=0, le=1e12)] = 1.0e5
    # mpc_tube: poles of A + B K_tube (task 31) and the out-of-plane horizon.
    tube_poles: Annotated[list[Annotated[float, msgspec.Meta(gt=-1, lt=1)]], msgspec.Meta(min_length=2, max_length=2)] = \
        msgspec.field(default_factory=lambda: [0.05, 0.1])
    tube_horizon: Horizon = 50
    # Wall-clock budget per cycle, fallback on a miss, optional stress (bench/controller/deadline.py).
    deadline: DeadlineConfig = msgspec.field(default_factory=DeadlineConfig)
