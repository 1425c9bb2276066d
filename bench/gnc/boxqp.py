"""Box-constrained QP by projected Newton (seed 004 section 4; Tassa, Mansard, Todorov 2014).

    minimise  f(x) = 1/2 x' H x + g' x     subject to  lower <= x <= upper

Seed 004 writes f = q'x + x'Qx with gradient q + Qx; that gradient needs the 1/2 written here.

Each iteration: x on the box; a variable is clamped when it sits on a bound and the gradient pushes
it outward; a Newton step on the free variables (Cholesky of H_ff), projected back onto the box,
with an Armijo backtracking line search. For a QP the Newton step is exact once the clamped set is
right, so the iteration ends in a handful of steps. Used per time step inside MILQR's backward
pass, warm-started from the neighbouring step's solution.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class BoxQPResult:
    x: np.ndarray
    clamped: np.ndarray                 # bool mask: variables held on a bound at the solution
    free_hessian: np.ndarray | None     # H_ff, positive definite (None when nothing is free)
    status: str                  # "converged" | "all_clamped" | "not_positive_definite" | "max_iterations" | "no_descent"
    iterations: int

    @property
    def ok(self) -> bool:
        return self.status in ("converged", "all_clamped")

    def solve_free(self, rhs: np.ndarray) -> np.ndarray:
        """H_ff^-1 rhs (MILQR's feedback rows of the free controls)."""
        return np.linalg.solve(self.free_hessian, rhs)


def objective(H: np.ndarray, g: np.ndarray, x: np.ndarray) -> float:
    return float(0.5 * x @ H @ x + g @ x)


def solve_box_qp(H: np.ndarray, g: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                 x0: np.ndarray | None = None, *, max_iterations: int = 100, gradient_tol: float = 1e-12,
                 armijo: float = 0.1, step_shrink: float = 0.5, min_step: float = 1e-20) -> BoxQPResult:
    """Projected-Newton solution of the box QP; `x0` warm-starts (it is clamped onto the box first)."""
    H = np.asarray(H, dtype=float)
    g = np.asarray(g, dtype=float)
    lower = np.asarray(lower, dtype=float)
    upper = np.asarray(upper, dtype=float)
    n = g.shape[0]
    if H.shape != (n, n) or lower.shape != (n,) or upper.shape != (n,):
        raise ValueError(f"box QP shapes: H {H.shape}, g {g.shape}, lower {lower.shape}, upper {upper.shape}")
    if np.any(lower > upper):
        raise ValueError(f"box QP has lower > upper at indices {np.flatnonzero(lower > upper)}")
    x = np.clip(np.zeros(n) if x0 is None else np.asarray(x0, dtype=float), lower, upper)
    value = objective(H, g, x)
    H_ff = None
    clamped = np.zeros(n, dtype=bool)
    scale = 1.0 + np.linalg.norm(g) + np.linalg.norm(H, ord=np.inf) * np.linalg.norm(x)
    for iteration in range(1, max_iterations + 1):
        grad = g + H @ x
        clamped = ((x <= lower) & (grad > 0)) | ((x >= upper) & (grad < 0))
        free = ~clamped
        if not free.any():
            return BoxQPResult(x, clamped, None, "all_clamped", iteration)
        H_ff = H[np.ix_(free, free)]
        try:
            # numpy's Cholesky, not scipy's: on 3x3 blocks scipy's input checks cost more than the
            # factorisation (MILQR solves one box QP per step per iteration)
            L = np.linalg.cholesky(H_ff)
        except np.linalg.LinAlgError:
            return BoxQPResult(x, clamped, None, "not_positive_definite", iteration)
        grad_free = grad[free]
        if np.linalg.norm(grad_free) <= gradient_tol * scale:
            return BoxQPResult(x, clamped, H_ff, "converged", iteration)
        step = np.zeros(n)
        step[free] = -np.linalg.solve(L.T, np.linalg.solve(L, grad_free))
        slope = grad @ step                   # < 0: a descent direction on the free subspace
        if slope >= 0:
            return BoxQPResult(x, clamped, H_ff, "no_descent", iteration)
        alpha = 1.0
        while True:
            candidate = np.clip(x + alpha * step, lower, upper)
            candidate_value = objective(H, g, candidate)
            # Armijo on the projected step: actual decrease against the one predicted by the slope
            if (value - candidate_value) >= armijo * alpha * (-slope):
                break
            alpha *= step_shrink
            if alpha < min_step:
                return BoxQPResult(x, clamped, H_ff, "converged", iteration)
        x, value = candidate, candidate_value
    grad = g + H @ x
    clamped = ((x <= lower) & (grad > 0)) | ((x >= upper) & (grad < 0))
    return BoxQPResult(x, clamped, H_ff if (~clamped).any() else None, "max_iterations", max_iterations)
