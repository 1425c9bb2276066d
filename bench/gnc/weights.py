"""Checks on cost weights, so a bad Q or R is named here and not deep inside a solver."""
from __future__ import annotations

import numpy as np


def _check_one(name: str, m: np.ndarray, n: int, strict: bool) -> np.ndarray:
    m = np.atleast_2d(np.asarray(m, dtype=float))
    if m.shape != (n, n):
        raise ValueError(f"{name} must be {n}x{n}, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"{name} has non-finite entries")
    if not np.allclose(m, m.T, rtol=1e-10, atol=1e-12):
        raise ValueError(f"{name} must be symmetric")
    smallest = np.linalg.eigvalsh(m).min()
    if strict and smallest <= 0:
        raise ValueError(f"{name} must be positive definite (smallest eigenvalue {smallest:.3g})")
    if not strict and smallest < -1e-12:
        raise ValueError(f"{name} must be positive semidefinite (smallest eigenvalue {smallest:.3g})")
    return m


def check_weights(q, r, n_x: int, n_u: int) -> tuple[np.ndarray, np.ndarray]:
    """Q must be n_x x n_x symmetric positive definite, R n_u x n_u symmetric positive definite."""
    return _check_one("Q", q, n_x, strict=True), _check_one("R", r, n_u, strict=True)
