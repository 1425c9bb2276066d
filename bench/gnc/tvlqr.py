"""Time-varying LQR by dynamic programming and tracking of a nominal trajectory (seed 000).

For dx_{k+1} = A_k dx_k + B_k du_k and cost sum_k dx_k' Q_k dx_k + du_k' R_k du_k + dx_N' Q_N dx_N,
the backward recursion from S_N = Q_N is

    K_k = (R_k + B_k' S_{k+1} B_k)^-1 B_k' S_{k+1} A_k
    S_k = Q_k + K_k' R_k K_k + (A_k - B_k K_k)' S_{k+1} (A_k - B_k K_k)     (Joseph form, stays symmetric PSD)

and the tracking law is u_k = u_bar_k - K_k dx_k, dx_k the deviation from the nominal state (for an
attitude, a 3-vector from the error quaternion; see `bench.gnc.quaternion.error_state`). Nothing
here knows about attitude: the same functions track a planned rendezvous trajectory.

Seed 000 errata: its zero-order-hold input matrix reads (e^{A dt} - I) B A^-1; the right one is
A^-1 (e^{A dt} - I) B, and `zero_order_hold` computes it without inverting A (the exponential of the
augmented matrix [[A, B], [0, 0]] dt), so it also holds for the singular A of a rigid body. Its
attitude kinematics write q_dot = 1/2 q (x) [v, 0]; it is 1/2 q (x) [0, omega].
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from bench.gnc.cwh import discretise_zoh


def zero_order_hold(a_continuous: np.ndarray, b_continuous: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(A_d, B_d) = (e^{A dt}, integral_0^dt e^{A s} ds B) from one matrix exponential; A may be singular.
    The same discretisation as seed 003's CWH model, so one implementation serves both."""
    return discretise_zoh(a_continuous, b_continuous, dt_s)


def bryson_weights(max_state_deviation, max_control) -> tuple[np.ndarray, np.ndarray]:
    """Bryson's rule: Q = diag(1/max_dev^2), R = diag(1/max_u^2) from the largest acceptable values."""
    dev = np.asarray(max_state_deviation, dtype=float)
    umax = np.asarray(max_control, dtype=float)
    for name, v in (("max_state_deviation", dev), ("max_control", umax)):
        if v.ndim != 1 or not np.all(np.isfinite(v)) or not np.all(v > 0):
            raise ValueError(f"{name} must be a vector of positive finite values, got {v}")
    return np.diag(1.0 / dev**2), np.diag(1.0 / umax**2)


def _per_step(matrix_or_sequence: np.ndarray, steps: int, name: str) -> np.ndarray:
    arr = np.asarray(matrix_or_sequence, dtype=float)
    if arr.ndim == 2:
        return np.broadcast_to(arr, (steps,) + arr.shape)
    if arr.ndim == 3 and arr.shape[0] == steps:
        return arr
    raise ValueError(f"{name} must be one matrix or one per step ({steps}), got shape {arr.shape}")


def tvlqr_gains(A: np.ndarray, B: np.ndarray, Q, R, Q_final) -> tuple[np.ndarray, np.ndarray]:
    """Gains K (N, m, n) for u = -K x and cost-to-go matrices S (N+1, n, n) by the backward recursion.

    A: (N, n, n), B: (N, n, m); Q and R one matrix or one per step (Q_k weights x_k, k < N).
    """
    A = np.asarray(A, dtype=float)
    B = np.asarray(B, dtype=float)
    if A.ndim != 3 or B.ndim != 3 or A.shape[0] != B.shape[0] or A.shape[1] != A.shape[2] or B.shape[1] != A.shape[1]:
        raise ValueError(f"A must be (N, n, n) and B (N, n, m), got {A.shape} and {B.shape}")
    steps, n, m = B.shape
    Qs, Rs = _per_step(Q, steps, "Q"), _per_step(R, steps, "R")
    S = np.empty((steps + 1, n, n))
    K = np.empty((steps, m, n))
    S[steps] = Q_final
    for k in range(steps - 1, -1, -1):
        Sn, Ak, Bk = S[k + 1], A[k], B[k]
        # R > 0 makes R + B'SB positive definite: Cholesky, not an explicit inverse.
        K[k] = cho_solve(cho_factor(Rs[k] + Bk.T @ Sn @ Bk), Bk.T @ Sn @ Ak)
        closed = Ak - Bk @ K[k]
        Sk = Qs[k] + K[k].T @ Rs[k] @ K[k] + closed.T @ Sn @ closed
        S[k] = 0.5 * (Sk + Sk.T)
    return K, S


def tracking_control(u_nominal: np.ndarray, gain: np.ndarray, state_deviation: np.ndarray) -> np.ndarray:
    """u = u_bar - K dx (seed 000's online law)."""
    return np.asarray(u_nominal) - gain @ np.asarray(state_deviation)
