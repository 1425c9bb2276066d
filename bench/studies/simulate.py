"""Closed-loop simulation on the discrete model (seed 003 tasks 7 and 26), scaled units.

Inputs are applied as the controller returns them: no saturation (seed task 7), so a controller
that asks for more than u_max shows it in the metrics instead of being silently clipped.
"""
from __future__ import annotations

import numpy as np


def simulate(x0, ctrl, model, n_steps: int) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """(X, U, infos): X = [x(0) .. x(N_t)] (nx x N_t+1), U = [u(0) .. u(N_t-1)] (nu x N_t)."""
    return simulate_uncertain(x0, ctrl, np.zeros((model.nx, _check_steps(n_steps))), model)


def simulate_uncertain(x0, ctrl, disturbances: np.ndarray, model) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """As `simulate`, with x(k+1) = A x(k) + B u(k) + w(k), w(k) the columns of `disturbances`."""
    x0 = np.asarray(x0, dtype=float).reshape(-1)
    disturbances = np.asarray(disturbances, dtype=float)
    if x0.shape != (model.nx,):
        raise ValueError(f"x0 must have {model.nx} entries, got {x0.size}")
    if disturbances.ndim != 2 or disturbances.shape[0] != model.nx:
        raise ValueError(f"disturbances must be {model.nx} x N_t, got shape {disturbances.shape}")
    n_steps = disturbances.shape[1]
    X = np.empty((model.nx, n_steps + 1))
    U = np.empty((model.nu, n_steps))
    infos = []
    X[:, 0] = x0
    for k in range(n_steps):
        u, info = ctrl.eval(X[:, k])
        U[:, k] = u
        infos.append(info)
        X[:, k + 1] = model.A @ X[:, k] + model.B @ u + disturbances[:, k]
    return X, U, infos


def _check_steps(n_steps) -> int:
    if isinstance(n_steps, bool) or int(n_steps) != n_steps or n_steps < 1:
        raise ValueError(f"n_steps must be an integer >= 1, got {n_steps!r}")
    return int(n_steps)
