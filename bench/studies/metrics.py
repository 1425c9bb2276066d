"""Trajectory metrics of seed 003: constraint satisfaction (task 9) and quadratic cost (task 15).

Trajectories are in scaled units (Mm, km/s; thrust in N) as `simulate` returns them; the metrics
are in SI so they compare directly with the mission limits in `RendezvousParams`.
"""
from __future__ import annotations

from dataclasses import dataclass, asdict

import numpy as np

from bench.gnc.cwh import RendezvousParams


# MPC inputs and states ride their constraints to the QP tolerance (1e-9 in scaled units: 1e-9 N,
# 1 mm); a trajectory is not called infeasible for that.
THRUST_TOL_N = 1e-6
POSITION_TOL_M = 1e-2


@dataclass(frozen=True)
class TrajectoryMetrics:
    max_abs_position_xz_m: float      # s_max^(i)
    max_abs_position_y_m: float       # y_max^(i)
    max_abs_thrust_n: float           # u_max^(i)
    input_cost_n2: float              # J_u = sum u'u
    final_distance_m: float           # d_f
    final_speed_mps: float            # v_f
    feasible: bool                    # traj_feas: all of the above within the mission limits

    def as_dict(self) -> dict:
        return asdict(self)


def traj_constraints(X_scaled: np.ndarray, U_n: np.ndarray, params: RendezvousParams) -> TrajectoryMetrics:
    """The seed's traj_constraints: worst positions and thrust, J_u, final errors, feasibility."""
    X_scaled, U_n = np.atleast_2d(X_scaled), np.atleast_2d(U_n)
    if X_scaled.shape[0] != 6 or U_n.shape[0] != 3 or X_scaled.shape[1] != U_n.shape[1] + 1:
        raise ValueError(f"need X 6 x (N_t+1) and U 3 x N_t, got {X_scaled.shape} and {U_n.shape}")
    X = X_scaled / np.asarray(params.scaling)[:, None]
    s_max = float(np.max(np.abs(X[[0, 2]])))
    y_max = float(np.max(np.abs(X[1])))
    u_max = float(np.max(np.abs(U_n))) if U_n.size else 0.0
    j_u = float(np.sum(U_n * U_n))
    d_f = float(np.linalg.norm(X[0:3, -1]))
    v_f = float(np.linalg.norm(X[3:6, -1]))
    feasible = (s_max <= params.max_abs_position_xz_m + POSITION_TOL_M
                and y_max <= params.max_abs_position_y_m + POSITION_TOL_M
                and u_max <= params.max_abs_thrust_n + THRUST_TOL_N and d_f <= params.max_final_position_m
                and v_f <= params.max_final_velocity_mps)
    return TrajectoryMetrics(s_max, y_max, u_max, j_u, d_f, v_f, bool(feasible))


def traj_cost(X: np.ndarray, U: np.ndarray, Q: np.ndarray, R: np.ndarray) -> float:
    """J_Nt = sum_{k<N_t} x(k)'Q x(k) + u(k)'R u(k) (the terminal state carries no cost)."""
    X, U = np.atleast_2d(X), np.atleast_2d(U)
    if X.shape[1] != U.shape[1] + 1:
        raise ValueError(f"X needs one more column than U, got {X.shape} and {U.shape}")
    Xk = X[:, :-1]
    return float(np.einsum("ik,ij,jk->", Xk, Q, Xk) + np.einsum("ik,ij,jk->", U, R, U))


def fuel_delta_v_mps(U_n: np.ndarray, time_step_s: float, mass_kg: float) -> float:
    """Delta-v spent by per-axis thrusters: sum_k ||u(k)||_1 dt / m."""
    return float(np.sum(np.abs(U_n)) * time_step_s / mass_kg)


def fuel_l2(U_n: np.ndarray, time_step_s: float) -> float:
    """The seed's fuel surrogate ||u||_L2 = dt (sum_k u(k)'u(k))^(1/2) (N s)."""
    return float(time_step_s * np.sqrt(np.sum(U_n * U_n)))
