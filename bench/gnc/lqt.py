"""Finite-horizon linear-quadratic tracking (LQT, seed 001 section 3), by the backward recursion.

Problem: minimise over u_0 .. u_{N-1}

    sum_{k<N} 1/2 [(x_k - r_k)' Q (x_k - r_k) + u_k' R u_k] + 1/2 (x_N - r_N)' Q_f (x_N - r_N)
    s.t. x_{k+1} = A_k x_k + B_k u_k.

Seed 001 derives the regulator (r = 0): the cost-to-go is 1/2 x' P_k x. With a reference it gains
an affine term, V_k(x) = 1/2 x' P_k x + s_k' x + const, and the same one-step minimisation gives

    H_k   = R + B_k' P_{k+1} B_k
    K_k   = -H_k^-1 B_k' P_{k+1} A_k                  (feedback, the seed's K)
    d_k   = -H_k^-1 B_k' s_{k+1}                      (feed-forward from the reference)
    P_k   = Q + A_k' P_{k+1} (A_k + B_k K_k)          (the seed's Riccati step; P symmetric)
    s_k   = (A_k + B_k K_k)' s_{k+1} - Q r_k
    u_k   = K_k x_k + d_k,       P_N = Q_f,  s_N = -Q_f r_N.

With r = 0 every s_k is zero and this is the seed's finite-horizon LQR; with Q_f the DARE solution
it is the infinite-horizon LQR at every step (the DARE is the recursion's fixed point).

Pure numerics: no units of its own (the bench calls it on the scaled state, Mm and km/s).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TrackingGains:
    """u_k = K[k] x_k + d[k] for k = 0 .. N-1; P[k], s[k] the cost-to-go terms (k = 0 .. N)."""

    K: np.ndarray      # (N, n_u, n_x)
    d: np.ndarray      # (N, n_u)
    P: np.ndarray      # (N+1, n_x, n_x)
    s: np.ndarray      # (N+1, n_x)

    @property
    def horizon(self) -> int:
        return self.K.shape[0]


def _per_step(matrices, n_steps: int, name: str, shape: tuple[int, int]) -> np.ndarray:
    """A constant matrix repeated, or a sequence of n_steps matrices, as an (n_steps, *shape) array."""
    m = np.asarray(matrices, dtype=float)
    if m.ndim == 2:
        m = np.broadcast_to(m, (n_steps, *m.shape))
    if m.shape != (n_steps, *shape):
        raise ValueError(f"{name} must be {shape} or {n_steps} x {shape}, got shape {m.shape}")
    return m


def lqt_gains(A, B, Q, R, Q_f, reference) -> TrackingGains:
    """Backward recursion for the tracking problem above.

    A, B: one matrix each (time-invariant) or one per step (N of them); reference: (N+1, n_x), the
    states r_0 .. r_N to track.
    """
    reference = np.atleast_2d(np.asarray(reference, dtype=float))
    n_steps = reference.shape[0] - 1
    if n_steps < 1:
        raise ValueError(f"reference needs at least 2 states (r_0 .. r_N), got {reference.shape[0]}")
    n_x = reference.shape[1]
    n_u = np.asarray(B[0] if np.ndim(B) == 3 else B).shape[1]
    A = _per_step(A, n_steps, "A", (n_x, n_x))
    B = _per_step(B, n_steps, "B", (n_x, n_u))
    Q, R, Q_f = (np.asarray(m, dtype=float) for m in (Q, R, Q_f))
    for name, m, n in (("Q", Q, n_x), ("R", R, n_u), ("Q_f", Q_f, n_x)):
        if m.shape != (n, n):
            raise ValueError(f"{name} must be {n}x{n}, got shape {m.shape}")
    if not np.all(np.isfinite(reference)):
        raise ValueError("reference has non-finite entries")
    K = np.empty((n_steps, n_u, n_x))
    d = np.empty((n_steps, n_u))
    P = np.empty((n_steps + 1, n_x, n_x))
    s = np.empty((n_steps + 1, n_x))
    P[n_steps] = Q_f
    s[n_steps] = -Q_f @ reference[n_steps]
    for k in range(n_steps - 1, -1, -1):
        a, b, p_next, s_next = A[k], B[k], P[k + 1], s[k + 1]
        h = R + b.T @ p_next @ b
        K[k] = -np.linalg.solve(h, b.T @ p_next @ a)
        d[k] = -np.linalg.solve(h, b.T @ s_next)
        closed = a + b @ K[k]
        p = Q + a.T @ p_next @ closed
        P[k] = 0.5 * (p + p.T)          # symmetric in exact arithmetic; keep it so in floating point
        s[k] = closed.T @ s_next - Q @ reference[k]
    return TrackingGains(K, d, P, s)


def glide_slope_reference(x0: np.ndarray, n_steps: int, glide_steps: int) -> np.ndarray:
    """States r_0 .. r_N approaching the origin along the straight line from x0's position.

    Position p0 (1 - k/G)^2 for k <= G, zero after: the range closes at a speed proportional to
    the square root of the range left, slowing down to arrive (a glide slope); the reference
    velocity is that profile's derivative (per step length 1; callers pass `step_scale`d units).
    The state is [position (n), velocity (n)] with n = len(x0) // 2.
    """
    x0 = np.asarray(x0, dtype=float)
    if x0.ndim != 1 or x0.size % 2:
        raise ValueError(f"x0 must be a [position, velocity] vector, got shape {x0.shape}")
    if not 1 <= glide_steps <= n_steps:
        raise ValueError(f"glide_steps must be in 1 .. n_steps ({n_steps}), got {glide_steps}")
    k = np.arange(n_steps + 1, dtype=float)
    fraction_left = np.clip(1.0 - k / glide_steps, 0.0, None)
    position = np.outer(fraction_left**2, x0[: x0.size // 2])
    rate = np.outer(-2.0 * fraction_left / glide_steps, x0[: x0.size // 2])   # d/dk
    return np.hstack([position, rate])


class TrackingLQT:
    """LQT on a discrete model, `eval(x) -> (u, info)` like every bench controller.

    The reference is the glide slope from the first state it is asked about (`glide_fraction` of
    the horizon long), velocities converted from per-step to per-`time_step` units by
    `velocity_per_step` (for the bench's scaled model: 1e3 / dt, Mm per step -> km/s). Q_f is the
    infinite-horizon LQR cost (P of the DARE), so the end of the run is the LQR's.
    Time-varying models: `continue_from(previous)` keeps the previous law's step and reference
    and recomputes the gains for the rest of the horizon on this law's A, B.
    """

    def __init__(self, Q, R, Q_f, A, B, horizon: int, glide_fraction: float, velocity_per_step: float):
        if not 0 < glide_fraction <= 1:
            raise ValueError(f"glide_fraction must be in (0, 1], got {glide_fraction}")
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        self.Q, self.R, self.Q_f = (np.asarray(m, dtype=float) for m in (Q, R, Q_f))
        self.A, self.B = np.asarray(A, dtype=float), np.asarray(B, dtype=float)
        self.horizon = int(horizon)
        self.glide_steps = max(1, int(round(glide_fraction * horizon)))
        self.velocity_per_step = float(velocity_per_step)
        self.step = 0
        self.reference: np.ndarray | None = None
        self.gains: TrackingGains | None = None

    def _plan(self, x0: np.ndarray) -> None:
        reference = glide_slope_reference(x0, self.horizon, self.glide_steps)
        n = x0.size // 2
        reference[:, n:] *= self.velocity_per_step
        self.reference = reference
        self._recompute()

    def _recompute(self) -> None:
        self.gains = lqt_gains(self.A, self.B, self.Q, self.R, self.Q_f, self.reference[self.step:])

    def continue_from(self, previous: "TrackingLQT") -> None:
        self.step, self.reference = previous.step, previous.reference
        if self.reference is not None and self.step < self.horizon:
            self._recompute()

    def eval(self, x) -> tuple[np.ndarray, dict]:
        start = time.perf_counter()
        x = np.asarray(x, dtype=float)
        if self.reference is None:
            self._plan(x)
        i = self.step - (self.horizon - self.gains.horizon)        # index into the current gains
        if i < self.gains.horizon:
            u = self.gains.K[i] @ x + self.gains.d[i]
        else:
            # Past the horizon: the terminal law is the infinite-horizon LQR (Q_f = its P).
            u = self.gains.K[-1] @ x
        self.step += 1
        return u, {"ctrl_feas": True, "objective": float("nan"), "solve_time": time.perf_counter() - start,
                   "iterations": 0, "status": "solved"}
