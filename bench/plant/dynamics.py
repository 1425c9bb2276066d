"""Translational relative motion of the chaser over one zero-order-hold step.

Two models, chosen per scenario (seed 001 compares controllers on both):
- "cwh": the linear CWH equations, propagated with their exact discretisation.
- "nonlinear": the exact relative motion about a circular target orbit (two-body gravity of
  chaser and target, expressed in the rotating LVLH frame), integrated with scipy's DOP853.
Thrust is held constant in the LVLH frame over the step, as a thruster slaved to the attitude
that keeps the LVLH pointing would apply it.
"""
from __future__ import annotations

from functools import lru_cache
from typing import Literal

import numpy as np

from bench.gnc.cwh import RendezvousParams

DynamicsModel = Literal["cwh", "nonlinear"]

# Tolerances for the nonlinear model: at 1e5 m offsets, 1e-12 relative keeps the integration error
# (micrometres over a 600 s step) far below any sensor noise the bench models.
RTOL = 1e-12
ATOL_M = 1e-9


@lru_cache(maxsize=8)
def _discrete_si(params: RendezvousParams) -> tuple[np.ndarray, np.ndarray]:
    return params.discrete_si()


def relative_acceleration_mps2(state_m_mps: np.ndarray, thrust_n: np.ndarray, params: RendezvousParams) -> np.ndarray:
    """Nonlinear relative acceleration in LVLH about a circular target orbit of radius R."""
    x, y, z, vx, vy, vz = state_m_mps
    n = params.mean_motion
    mu = params.gravitational_parameter_m3ps2
    radius = params.target_radius_m
    r_chaser = np.sqrt((radius + x) ** 2 + y**2 + z**2)
    gravity = mu / r_chaser**3
    a_thrust = np.asarray(thrust_n) / params.mass_kg
    return np.array([
        2 * n * vy + n**2 * (radius + x) - gravity * (radius + x) + a_thrust[0],
        -2 * n * vx + n**2 * y - gravity * y + a_thrust[1],
        -gravity * z + a_thrust[2],
    ])


def propagate(state_m_mps: np.ndarray, thrust_n: np.ndarray, dt_s: float, params: RendezvousParams,
              model: DynamicsModel = "cwh") -> np.ndarray:
    """State after dt_s with thrust held constant (ZOH)."""
    state = np.asarray(state_m_mps, dtype=float)
    thrust = np.asarray(thrust_n, dtype=float)
    if model == "cwh":
        if dt_s != params.time_step_s:
            raise ValueError(f"cwh propagation is discretised for {params.time_step_s} s steps, got {dt_s}")
        a_d, b_d = _discrete_si(params)
        return a_d @ state + b_d @ thrust
    if model == "nonlinear":
        from scipy.integrate import solve_ivp   # here: only this model integrates (0.2 s of a plant's start)

        def rhs(_t, s):
            return np.concatenate([s[3:], relative_acceleration_mps2(s, thrust, params)])

        sol = solve_ivp(rhs, (0.0, dt_s), state, method="DOP853", rtol=RTOL, atol=ATOL_M)
        if not sol.success:
            raise RuntimeError(f"nonlinear propagation failed: {sol.message}")
        return sol.y[:, -1]
    raise ValueError(f"unknown dynamics model {model!r} (use 'cwh' or 'nonlinear')")
