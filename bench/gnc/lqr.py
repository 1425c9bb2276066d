"""Infinite-horizon discrete LQR (seed 003 task 6): gain from the DARE, computed once."""
from __future__ import annotations

import time

import numpy as np
from scipy.linalg import solve_discrete_are

from bench.gnc.weights import check_weights


def dlqr(a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, P) with u = K x minimising sum x'Qx + u'Ru; P is the cost-to-go x'Px (seed 003 hint 1)."""
    q, r = check_weights(q, r, a.shape[0], b.shape[1])
    p = solve_discrete_are(a, b, q, r)
    k = -np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)
    return k, p


class LQR:
    """u = K x on the scaled model; `eval(x) -> (u, info)` as every bench controller."""

    def __init__(self, q: np.ndarray, r: np.ndarray, a: np.ndarray, b: np.ndarray):
        self.K, self.P = dlqr(a, b, q, r)

    def eval(self, x: np.ndarray) -> tuple[np.ndarray, dict]:
        start = time.perf_counter()
        u = self.K @ np.asarray(x, dtype=float)
        info = {
            "ctrl_feas": True,
            "objective": float(x @ self.P @ x),
            "solve_time": time.perf_counter() - start,
            "iterations": 0,
            "status": "solved",
        }
        return u, info
