"""Build the controller a scenario's [controller] section asks for.

The controller process calls `build_controller(cfg, params)`; the returned object has
`eval(x_scaled) -> (u_N, info)`: scaled state (Mm, km/s) in, thrust in N out (seed 003 units).
"""
from __future__ import annotations

import numpy as np

from bench.controller.config import ControllerConfig
from bench.controller.lqr import LQR
from bench.plant.cwh import RendezvousParams


def weights_from_config(cfg: ControllerConfig) -> tuple[np.ndarray, np.ndarray]:
    """(Q, R) = (diag(q_diag), diag(r_diag)) on the scaled state."""
    return np.diag(np.asarray(cfg.q_diag, dtype=float)), np.diag(np.asarray(cfg.r_diag, dtype=float))


def build_controller(cfg: ControllerConfig, params: RendezvousParams):
    """A controller object for `cfg` on the scaled CWH model of `params`."""
    q, r = weights_from_config(cfg)
    model = params.scaled
    if cfg.type == "lqr":
        return LQR(q, r, model.A, model.B)
    raise ValueError(f"controller.type: unknown controller type {cfg.type!r}")
