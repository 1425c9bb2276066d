"""Mission metrics of a rendezvous trajectory (seed 003 task 9 and the L2 fuel surrogate).

Computed on the SI trajectory a run produced; the thresholds come from the scenario's params.
"""
from __future__ import annotations

import numpy as np

from bench.plant.cwh import RendezvousParams


def trajectory_metrics(state_m_mps: np.ndarray, thrust_n: np.ndarray, params: RendezvousParams) -> dict:
    """Metrics of X (n+1 x 6, SI) and U (n x 3, N) against the seed's mission requirements."""
    x = np.asarray(state_m_mps, dtype=float)
    u = np.asarray(thrust_n, dtype=float).reshape(-1, 3)
    input_cost = float(np.sum(u * u))                     # J_u = sum_k u_k' u_k  [N^2]
    max_xz_m = float(np.max(np.abs(x[:, [0, 2]])))
    max_y_m = float(np.max(np.abs(x[:, 1])))
    max_thrust_n = float(np.max(np.abs(u))) if u.size else 0.0
    final_position_error_m = float(np.linalg.norm(x[-1, :3]))
    final_velocity_error_mps = float(np.linalg.norm(x[-1, 3:]))
    checks = {
        "position_xz": max_xz_m <= params.max_abs_position_xz_m,
        "position_y": max_y_m <= params.max_abs_position_y_m,
        "thrust": max_thrust_n <= params.max_abs_thrust_n,
        "final_position": final_position_error_m <= params.max_final_position_m,
        "final_velocity": final_velocity_error_mps <= params.max_final_velocity_mps,
    }
    return {
        "final_position_error_m": final_position_error_m,
        "final_velocity_error_mps": final_velocity_error_mps,
        "input_cost": input_cost,
        "fuel_l2": params.time_step_s * float(np.sqrt(input_cost)),   # ||u||_L2(0,T) [N s]
        "max_abs_thrust_N": max_thrust_n,
        "max_abs_position_xz_m": max_xz_m,
        "max_abs_position_y_m": max_y_m,
        "constraints_satisfied": all(checks.values()),
        "constraint_checks": checks,
        "steps": int(u.shape[0]),
    }
