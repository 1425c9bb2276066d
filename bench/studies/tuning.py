"""The LQR tuning study of seed 003 (tasks 10 and 11): simulate LQR for many q, pick the cheapest
feasible one.

`lqr_tuning` is the seed's function. `refine_q` runs rounds of it on log-spaced grids that shrink
around the best q so far, using the seed's hint 2: the in-plane (x, y) and out-of-plane (z) loops
are decoupled, so the two halves of q can be gridded separately and every combination of an
in-plane and an out-of-plane candidate evaluated exactly from the two halves' trajectories.
"""
from __future__ import annotations

from dataclasses import dataclass
import itertools
from typing import Callable

import numpy as np

from bench.gnc.cwh import RendezvousParams
from bench.gnc.lqr import LQR
from bench.studies.metrics import TrajectoryMetrics, traj_constraints
from bench.studies.simulate import simulate

IN_PLANE_Q = (0, 1, 3, 4)        # q_x, q_y, q_vx, q_vy
OUT_OF_PLANE_Q = (2, 5)          # q_z, q_vz


@dataclass(frozen=True)
class TuningRow:
    """One entry of the seed's tuning_struct (table 4)."""

    initial_condition: np.ndarray
    q_diag: np.ndarray
    metrics: TrajectoryMetrics


def _check_qs(qs) -> np.ndarray:
    qs = np.atleast_2d(np.asarray(qs, dtype=float))
    if qs.shape[1] != 6:
        raise ValueError(f"each q needs 6 weights [q_x, q_y, q_z, q_vx, q_vy, q_vz], got {qs.shape[1]}")
    if not np.all(np.isfinite(qs)) or np.any(qs <= 0):
        raise ValueError("q weights must be finite and positive (Q = diag(q) positive definite)")
    return qs


def lqr_trajectory(x0_scaled, q_diag, params: RendezvousParams):
    """(X, U) of the LQR closed loop with Q = diag(q), R = I, unsaturated (seed task 7)."""
    model = params.scaled
    ctrl = LQR(np.diag(q_diag), np.eye(model.nu), model.A, model.B)
    X, U, _ = simulate(x0_scaled, ctrl, model, params.n_steps)
    return X, U


def _failed_metrics() -> TrajectoryMetrics:
    """The row of a q whose DARE has no stabilising solution: infeasible, every figure inf."""
    inf = float("inf")
    return TrajectoryMetrics(inf, inf, inf, inf, inf, inf, False)


def lqr_tuning(x0_scaled, qs, params: RendezvousParams,
               progress: Callable[[int], None] | None = None) -> tuple[list[TuningRow], int | None]:
    """The seed's lqr_tuning: one row per q (rows of `qs`, M x 6) and the index of the feasible q
    with the lowest J_u, or None if no q is feasible (the seed's nan)."""
    qs = _check_qs(qs)
    x0_scaled = np.asarray(x0_scaled, dtype=float)
    rows = []
    for q in qs:
        try:
            X, U = lqr_trajectory(x0_scaled, q, params)
            metrics = traj_constraints(X, U, params)
        except (np.linalg.LinAlgError, ValueError):    # the DARE failed at this q: not a candidate
            metrics = _failed_metrics()
        rows.append(TuningRow(x0_scaled.copy(), q.copy(), metrics))
        if progress:
            progress(1)
    return rows, best_feasible(rows)


def best_feasible(rows: list[TuningRow]) -> int | None:
    feasible = [i for i, r in enumerate(rows) if r.metrics.feasible]
    return min(feasible, key=lambda i: rows[i].metrics.input_cost_n2) if feasible else None


def log_grid(centre: np.ndarray, axes: tuple[int, ...], span_decades: float, points: int) -> np.ndarray:
    """q vectors equal to `centre` except on `axes`, where they take `points` log-spaced values
    within +-span_decades of the centre (all combinations)."""
    offsets = np.logspace(-span_decades, span_decades, points)
    qs = []
    for combo in itertools.product(offsets, repeat=len(axes)):
        q = np.array(centre, dtype=float)
        q[list(axes)] *= combo
        qs.append(q)
    return np.array(qs)


@dataclass(frozen=True)
class _HalfMetrics:
    """The parts of the trajectory metrics one decoupled half of the loop determines."""

    pos_xz_max: np.ndarray   # max |x| (in-plane) or max |z| (out-of-plane), m
    y_max: np.ndarray        # m (0 for out-of-plane)
    u_max: np.ndarray        # N
    j_u: np.ndarray          # N^2
    d2: np.ndarray           # squared final distance, m^2
    v2: np.ndarray           # squared final speed, (m/s)^2


def _half_metrics(x0_scaled, qs, params, states, inputs, progress) -> _HalfMetrics:
    scaling = np.asarray(params.scaling)
    cols = {k: [] for k in _HalfMetrics.__dataclass_fields__}
    pos_axes = [s for s in states if s in (0, 2)]
    for q in qs:
        try:
            X, U = lqr_trajectory(x0_scaled, q, params)
        except (np.linalg.LinAlgError, ValueError):    # the DARE failed at this q: never feasible
            for k in cols:
                cols[k].append(np.inf)
            if progress:
                progress(1)
            continue
        X = X / scaling[:, None]
        cols["pos_xz_max"].append(np.max(np.abs(X[pos_axes])))
        cols["y_max"].append(np.max(np.abs(X[1])) if 1 in states else 0.0)
        cols["u_max"].append(np.max(np.abs(U[list(inputs)])))
        cols["j_u"].append(np.sum(U[list(inputs)] ** 2))
        cols["d2"].append(np.sum(X[[s for s in states if s < 3], -1] ** 2))
        cols["v2"].append(np.sum(X[[s for s in states if s >= 3], -1] ** 2))
        if progress:
            progress(1)
    return _HalfMetrics(**{k: np.array(v) for k, v in cols.items()})


def refine_q(x0_scaled, q_start, params: RendezvousParams, rounds: int = 4, points_in_plane: int = 5,
             points_out_of_plane: int = 9, span_decades: float = 1.0,
             progress: Callable[[int], None] | None = None) -> tuple[np.ndarray, float]:
    """Best feasible q (lowest J_u) found by shrinking log grids around q_start; (q, J_u).

    Each round grids the in-plane weights (others fixed) and the out-of-plane weights (others
    fixed), combines every pair exactly, moves the centre to the best feasible combination and
    halves the span. Raises ValueError if no combination in any round is feasible.
    """
    centre = _check_qs(q_start)[0].copy()
    x0_scaled = np.asarray(x0_scaled, dtype=float)
    best_q, best_j = None, np.inf
    for _ in range(rounds):
        q_in = log_grid(centre, IN_PLANE_Q, span_decades, points_in_plane)
        q_out = log_grid(centre, OUT_OF_PLANE_Q, span_decades, points_out_of_plane)
        m_in = _half_metrics(x0_scaled, q_in, params, (0, 1, 3, 4), (0, 1), progress)
        m_out = _half_metrics(x0_scaled, q_out, params, (2, 5), (2,), progress)
        feasible = (
            (np.maximum.outer(m_in.pos_xz_max, m_out.pos_xz_max) <= params.max_abs_position_xz_m)
            & (m_in.y_max[:, None] <= params.max_abs_position_y_m)
            & (np.maximum.outer(m_in.u_max, m_out.u_max) <= params.max_abs_thrust_n)
            & (np.sqrt(np.add.outer(m_in.d2, m_out.d2)) <= params.max_final_position_m)
            & (np.sqrt(np.add.outer(m_in.v2, m_out.v2)) <= params.max_final_velocity_mps)
        )
        j_u = np.where(feasible, np.add.outer(m_in.j_u, m_out.j_u), np.inf)
        i, j = np.unravel_index(np.argmin(j_u), j_u.shape)
        if np.isfinite(j_u[i, j]) and j_u[i, j] < best_j:
            best_j = float(j_u[i, j])
            best_q = q_in[i].copy()
            best_q[list(OUT_OF_PLANE_Q)] = q_out[j][list(OUT_OF_PLANE_Q)]
        if best_q is not None:
            centre = best_q
        span_decades /= 2.0
    if best_q is None:
        raise ValueError("no feasible q found; widen the span or start from another q")
    return best_q, best_j
