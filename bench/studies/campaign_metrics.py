"""Per-run metrics of a seed 001 campaign: compute cost, fuel, stability, time to rendezvous, success.

Inputs are what a run leaves behind: the true state (Cartesian LVLH, SI) at every step, the
thrust the plant applied (N, LVLH), and per controller cycle the solver's time and iterations.

Fuel, three ways (all over the applied thrust u_k held for dt):
- `delta_v_mps`: sum_k ||u_k||_1 dt / m, what per-axis thrusters burn;
- `fuel_l2_n_sqrt_s`: the L2 norm of the piecewise-constant thrust, ||u||_L2 = sqrt(dt sum_k u_k'u_k);
- `fuel_l2_seed003`: seed 003's printed surrogate dt sqrt(sum_k u_k'u_k), which is not that norm
  (it is sqrt(dt) times it); kept under its own name so results compare with the seed's numbers.
`input_cost_n2` is the seed's J_u = sum_k u_k'u_k.
"""
from __future__ import annotations

import numpy as np

from bench.gnc.cwh import RendezvousParams
from bench.studies.metrics import fuel_delta_v_mps, traj_constraints

# A run has diverged when the chaser ends farther than it started or ever gets this many times
# farther than its initial distance (a controller that lost the target on the nonlinear plant ends
# thousands of km away; noise alone moves a converging run by metres).
DIVERGENCE_FACTOR = 10.0


def time_to_rendezvous_s(state_m_mps: np.ndarray, time_step_s: float, max_position_m: float,
                         max_velocity_mps: float) -> float:
    """First time inside the terminal position and velocity bounds and staying there to the end;
    NaN if the run does not end inside them."""
    state = np.asarray(state_m_mps, dtype=float)
    inside = (np.linalg.norm(state[:, :3], axis=1) <= max_position_m) & (np.linalg.norm(state[:, 3:], axis=1) <= max_velocity_mps)
    if not inside.size or not inside[-1]:
        return float("nan")
    outside = np.flatnonzero(~inside)
    first_k = 0 if outside.size == 0 else int(outside[-1]) + 1
    return first_k * time_step_s


def _percentile(values: np.ndarray, q: float) -> float:
    values = values[np.isfinite(values)]
    return float(np.percentile(values, q)) if values.size else float("nan")


def estimate_consistency(estimate_m_mps, estimate_covariance, navigation_truth_m_mps) -> dict:
    """NEES of the estimate against the truth (both in the flight side's coordinates), per step
    e' P^-1 e with e = truth - estimate, averaged over the steps that have a covariance (a
    consistent 6-state estimator averages 6); and the estimate's position error at the last step.
    NaN without a covariance (full state knowledge)."""
    nan = float("nan")
    if estimate_m_mps is None or estimate_covariance is None or navigation_truth_m_mps is None:
        return {"nees_mean": nan, "nees_steps": 0, "estimate_position_error_final_m": nan}
    error = np.asarray(navigation_truth_m_mps, dtype=float) - np.asarray(estimate_m_mps, dtype=float)
    covariance = np.asarray(estimate_covariance, dtype=float).reshape(-1, 6, 6)
    usable = np.all(np.isfinite(covariance), axis=(1, 2)) & np.all(np.isfinite(error), axis=1)
    if not usable.any():
        return {"nees_mean": nan, "nees_steps": 0, "estimate_position_error_final_m": nan}
    nees = np.einsum("ki,ki->k", error[usable], np.linalg.solve(covariance[usable], error[usable][..., None])[..., 0])
    return {"nees_mean": float(nees.mean()), "nees_steps": int(usable.sum()),
            "estimate_position_error_final_m": float(np.linalg.norm(error[-1, :3]))}


def run_metrics(state_m_mps: np.ndarray, thrust_n: np.ndarray, params: RendezvousParams,
                solve_time_s: np.ndarray | None = None, solver_iterations: np.ndarray | None = None,
                ctrl_feasible: np.ndarray | None = None, *, estimate_m_mps: np.ndarray | None = None,
                estimate_covariance: np.ndarray | None = None,
                navigation_truth_m_mps: np.ndarray | None = None) -> dict:
    """One campaign row's metrics (flat: numbers and booleans only). With the estimate, its
    covariance and the truth in the flight side's coordinates, also the estimate's NEES."""
    x = np.asarray(state_m_mps, dtype=float)
    u = np.asarray(thrust_n, dtype=float).reshape(-1, 3)
    finite = bool(np.all(np.isfinite(x)) and np.all(np.isfinite(u)))
    seed = traj_constraints((x * np.asarray(params.scaling)).T, u.T, params) if finite else None
    dt = params.time_step_s
    j_u = float(np.sum(u * u))
    distance_m = np.linalg.norm(x[:, :3], axis=1)
    diverged = (not finite) or bool(distance_m[-1] > distance_m[0]
                                    or distance_m.max() > DIVERGENCE_FACTOR * max(distance_m[0], params.max_final_position_m))
    t_rdv = time_to_rendezvous_s(x, dt, params.max_final_position_m, params.max_final_velocity_mps) if finite else float("nan")
    settle_from = int(0.9 * (x.shape[0] - 1))
    solve = np.asarray(solve_time_s if solve_time_s is not None else [], dtype=float)
    iters = np.asarray(solver_iterations if solver_iterations is not None else [], dtype=float)
    feas = np.asarray(ctrl_feasible if ctrl_feasible is not None else [], dtype=bool)
    nan = float("nan")
    return {
        "final_position_error_m": seed.final_distance_m if seed else nan,
        "final_velocity_error_mps": seed.final_speed_mps if seed else nan,
        "constraints_satisfied": bool(seed.feasible) if seed else False,
        "max_abs_thrust_n": seed.max_abs_thrust_n if seed else nan,
        "input_cost_n2": j_u,                                           # seed J_u
        "delta_v_mps": fuel_delta_v_mps(u.T, dt, params.mass_kg),
        "fuel_l2_n_sqrt_s": float(np.sqrt(dt * j_u)),                  # ||u||_L2(0,T)
        "fuel_l2_seed003": float(dt * np.sqrt(j_u)),                    # seed 003's expression
        "time_to_rendezvous_s": t_rdv,
        "rendezvous": bool(np.isfinite(t_rdv)),
        # Stability: the worst distance over the last 10 % of the run (bounded after convergence),
        # and whether the run diverged.
        "settled_max_position_m": float(distance_m[settle_from:].max()) if finite else nan,
        "diverged": diverged,
        "success": bool(seed is not None and seed.feasible and not diverged),
        # Compute cost per controller cycle (the solver's own time; LQR's is a matrix product).
        "solve_time_p50_ms": _percentile(solve, 50) * 1e3,
        "solve_time_p90_ms": _percentile(solve, 90) * 1e3,
        "solve_time_p99_ms": _percentile(solve, 99) * 1e3,
        "solve_time_max_ms": _percentile(solve, 100) * 1e3,
        "solver_iterations_median": _percentile(iters, 50),
        "solver_iterations_max": float(iters.max()) if iters.size else nan,
        "infeasible_cycles": int(np.sum(~feas)),
        "steps": int(u.shape[0]),
        **estimate_consistency(estimate_m_mps, estimate_covariance, navigation_truth_m_mps),
    }

# Columns that depend on the machine and its load, not on the scenario: two runs of the same case
# agree on every other column exactly.
TIMING_COLUMNS = ("solve_time_p50_ms", "solve_time_p90_ms", "solve_time_p99_ms", "solve_time_max_ms")
