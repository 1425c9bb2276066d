"""Mission metrics of a bench run: seed 003's traj_constraints on the SI trajectory the plant
flew, plus the L2 fuel surrogate, under the names metrics.json uses."""
from __future__ import annotations

import numpy as np

from bench.gnc.cwh import RendezvousParams
from bench.studies.metrics import POSITION_TOL_M, THRUST_TOL_N, traj_constraints


def trajectory_metrics(state_m_mps: np.ndarray, thrust_n: np.ndarray, params: RendezvousParams) -> dict:
    """Metrics of X (n+1 x 6, SI) and U (n x 3, N) against the seed's mission requirements."""
    x = np.asarray(state_m_mps, dtype=float)
    u = np.asarray(thrust_n, dtype=float).reshape(-1, 3)
    m = traj_constraints((x * np.asarray(params.scaling)).T, u.T, params)
    return {
        "final_position_error_m": m.final_distance_m,
        "final_velocity_error_mps": m.final_speed_mps,
        "input_cost": m.input_cost_n2,                                 # J_u = sum_k u_k' u_k [N^2]
        "fuel_l2": params.time_step_s * float(np.sqrt(m.input_cost_n2)),   # ||u||_L2(0,T) [N s]
        "max_abs_thrust_N": m.max_abs_thrust_n,
        "max_abs_position_xz_m": m.max_abs_position_xz_m,
        "max_abs_position_y_m": m.max_abs_position_y_m,
        "constraints_satisfied": m.feasible,
        "constraint_checks": {          # which of traj_constraints' conditions held
            "position_xz": m.max_abs_position_xz_m <= params.max_abs_position_xz_m + POSITION_TOL_M,
            "position_y": m.max_abs_position_y_m <= params.max_abs_position_y_m + POSITION_TOL_M,
            "thrust": m.max_abs_thrust_n <= params.max_abs_thrust_n + THRUST_TOL_N,
            "final_position": m.final_distance_m <= params.max_final_position_m,
            "final_velocity": m.final_speed_mps <= params.max_final_velocity_mps,
        },
        # each check with its value and bound (what a "constraints satisfied NO" is about)
        "constraints": [
            {"name": name, "value": float(value), "bound": float(bound), "unit": unit,
             "satisfied": bool(value <= bound + tol)}
            for name, value, bound, tol, unit in (
                ("max |x|, |z| position", m.max_abs_position_xz_m, params.max_abs_position_xz_m, POSITION_TOL_M, "m"),
                ("max |y| position", m.max_abs_position_y_m, params.max_abs_position_y_m, POSITION_TOL_M, "m"),
                ("max |thrust|", m.max_abs_thrust_n, params.max_abs_thrust_n, THRUST_TOL_N, "N"),
                ("final position error", m.final_distance_m, params.max_final_position_m, 0.0, "m"),
                ("final velocity error", m.final_speed_mps, params.max_final_velocity_mps, 0.0, "m/s"))],
        "steps": int(u.shape[0]),
    }
