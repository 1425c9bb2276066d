"""The estimator's nonlinear motion model: exact two-body relative motion about a circular target orbit.

What the seed 001 nonlinear plant integrates (bench/plant/dynamics.py), written for the flight
side in either of its navigation frames:
- "cartesian": LVLH [x, y, z, vx, vy, vz], the relative acceleration of two-body gravity in the
  rotating frame;
- "curvilinear": [dr, s, w, dr', s', w'] of bench/plant/curvilinear.py, i.e. spherical
  coordinates about the Earth's centre in the rotating frame, r = R + dr, in-plane angle
  theta = s / R, out-of-plane angle phi = w / R. With the inertial longitude rate
  lambda' = theta' + n, the equations of motion are (acceleration in spherical components):
      r''      = r phi'^2 + r lambda'^2 cos^2 phi - mu / r^2 + a_r
      theta''  = (a_theta - 2 r' lambda' cos phi + 2 r lambda' phi' sin phi) / (r cos phi)
      phi''    = (a_phi - 2 r' phi' - r lambda'^2 sin phi cos phi) / r
  Their linearisation about r = R is the CWH model the controllers use; the terms CWH drops are
  what made the smoother with the linear model inconsistent on that plant (docs/estimation.md).

The thrust is held constant in LVLH over the step, as the plant holds it: a curvilinear command
is turned into LVLH along the local (e_r, e_theta, e_phi) at the step's start and projected back
on the moving local axes as the chaser moves.

`propagate` integrates with a fixed-step classical Runge-Kutta (RK4) in complex arithmetic, so
that `linearise` gets the exact Jacobian d x_k / d x_{k-1} by the complex step (six perturbed
trajectories in one vectorised integration, no subtraction error). RK4 at 60 s steps against
scipy's DOP853 at 1e-12: see tests/test_estimator_two_body_model.py.
"""
from __future__ import annotations

from typing import Literal

import numpy as np

NavigationFrame = Literal["cartesian", "curvilinear"]

# RK4 step: the truncation error is ~(n h)^4 / 120 relative per substep, n ~ 1.1e-3 rad/s. At 60 s
# it is ~1.5 mm per 600 s plant step on the 400 km start and less nearer the target (tests):
# far below the 10 m fixes and the ~0.4 m the smoother settles at, while the old CWH model missed
# metres per step there. Each step of the estimator costs one integration (~7 ms at 60 s; the
# numpy calls on six complex trajectories, not the arithmetic, are the cost).
MAX_SUBSTEP_S = 60.0
# Complex-step size (state units: m, m/s): tiny, the derivative is exact to rounding anyway.
_COMPLEX_STEP = 1e-20


class TwoBodyRelativeModel:
    """x_k = f(x_{k-1}, u) over a whole number of plant steps, and its Jacobian in x_{k-1}.

    gravitational_parameter_m3ps2 and target_radius_m are what the flight side believes; the
    rotating frame turns at n = sqrt(mu / R^3).
    """

    def __init__(self, gravitational_parameter_m3ps2: float, target_radius_m: float, mass_kg: float,
                 time_step_s: float, frame: NavigationFrame):
        if not all(np.isfinite(v) and v > 0 for v in (gravitational_parameter_m3ps2, target_radius_m, mass_kg, time_step_s)):
            raise ValueError(
                "TwoBodyRelativeModel needs positive finite gravitational_parameter_m3ps2, target_radius_m, mass_kg "
                f"and time_step_s, got {gravitational_parameter_m3ps2}, {target_radius_m}, {mass_kg}, {time_step_s}")
        if frame not in ("cartesian", "curvilinear"):
            raise ValueError(f"unknown navigation frame {frame!r} (use 'cartesian' or 'curvilinear')")
        self.mu = float(gravitational_parameter_m3ps2)
        self.radius_m = float(target_radius_m)
        self.mean_motion_radps = float(np.sqrt(self.mu / self.radius_m**3))
        self.mass_kg = float(mass_kg)
        self.time_step_s = float(time_step_s)
        self.frame = frame
        self._last_key = None
        self._last_value = None

    # ---- the equations -----------------------------------------------------------------------

    def _lvlh_thrust(self, state: np.ndarray, thrust_n: np.ndarray) -> tuple:
        """The command as the LVLH vector the plant holds over the step: three components, each
        one number per trajectory (rows of `state`)."""
        if self.frame == "cartesian":
            return tuple(thrust_n[i] + 0.0 * state[..., 0] for i in range(3))
        theta, phi = state[..., 1] / self.radius_m, state[..., 2] / self.radius_m
        ct, st, cp, sp = np.cos(theta), np.sin(theta), np.cos(phi), np.sin(phi)
        u_r, u_t, u_p = thrust_n
        # u_r e_r + u_t e_theta + u_p e_phi, with the axes of bench/plant/curvilinear.py
        return (u_r * cp * ct - u_t * st - u_p * sp * ct, u_r * cp * st + u_t * ct - u_p * sp * st, u_r * sp + u_p * cp)

    def derivative(self, state: np.ndarray, thrust_lvlh_n: tuple) -> np.ndarray:
        """d state / dt for rows of states (real or complex), the thrust as the held LVLH components."""
        mu, radius, n = self.mu, self.radius_m, self.mean_motion_radps
        ux, uy, uz = (u / self.mass_kg for u in thrust_lvlh_n)
        out = np.empty_like(state)
        out[..., :3] = state[..., 3:]
        if self.frame == "cartesian":
            x, y, z, vx, vy, vz = (state[..., i] for i in range(6))
            px = radius + x
            gravity = mu / (px * px + y * y + z * z) ** 1.5
            out[..., 3] = 2 * n * vy + n * n * px - gravity * px + ux
            out[..., 4] = -2 * n * vx + n * n * y - gravity * y + uy
            out[..., 5] = -gravity * z + uz
            return out
        dr, s, w, dr_dot, s_dot, w_dot = (state[..., i] for i in range(6))
        r = radius + dr
        theta, phi = s / radius, w / radius
        phi_dot = w_dot / radius
        lam_dot = s_dot / radius + n
        ct, st, cp, sp = np.cos(theta), np.sin(theta), np.cos(phi), np.sin(phi)
        # The held LVLH thrust on the local axes (e_r, e_theta, e_phi) where the chaser is now.
        horizontal = ux * ct + uy * st
        a_r = cp * horizontal + sp * uz
        a_t = -ux * st + uy * ct
        a_p = -sp * horizontal + cp * uz
        out[..., 3] = r * phi_dot**2 + r * lam_dot**2 * cp**2 - mu / r**2 + a_r
        out[..., 4] = radius * (a_t - 2 * dr_dot * lam_dot * cp + 2 * r * lam_dot * phi_dot * sp) / (r * cp)
        out[..., 5] = radius * (a_p - 2 * dr_dot * phi_dot - r * lam_dot**2 * sp * cp) / r
        return out

    def _integrate(self, state: np.ndarray, thrust_n: np.ndarray, interval_s: float) -> np.ndarray:
        substeps = max(1, int(np.ceil(interval_s / MAX_SUBSTEP_S - 1e-9)))
        h = interval_s / substeps
        thrust_lvlh = self._lvlh_thrust(state, thrust_n)
        x = state
        for _ in range(substeps):
            k1 = self.derivative(x, thrust_lvlh)
            k2 = self.derivative(x + 0.5 * h * k1, thrust_lvlh)
            k3 = self.derivative(x + 0.5 * h * k2, thrust_lvlh)
            k4 = self.derivative(x + h * k3, thrust_lvlh)
            x = x + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
        return x

    # ---- what the smoother uses ---------------------------------------------------------------

    def propagate(self, state_m_mps: np.ndarray, thrust_n: np.ndarray, n_steps: int = 1) -> np.ndarray:
        """The state n_steps plant steps later, the thrust held (in LVLH) over the whole interval."""
        state, thrust = _checked(state_m_mps, thrust_n, n_steps)
        return self._integrate(state, thrust, n_steps * self.time_step_s)

    def linearise(self, state_m_mps: np.ndarray, thrust_n: np.ndarray, n_steps: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """(f(x, u), d f / d x) at x: the propagated state and its exact Jacobian (complex step).

        The last call is cached: the smoother's prediction and motion factor linearise at the same
        point.
        """
        state, thrust = _checked(state_m_mps, thrust_n, n_steps)
        key = (state.tobytes(), thrust.tobytes(), n_steps)
        if key == self._last_key:
            return self._last_value
        h = _COMPLEX_STEP
        perturbed = np.tile(state.astype(complex), (6, 1)) + 1j * h * np.eye(6)
        ends = self._integrate(perturbed, thrust, n_steps * self.time_step_s)
        value = (ends[0].real.copy(), (ends.imag / h).T.copy())
        self._last_key, self._last_value = key, value
        return value


def _checked(state_m_mps, thrust_n, n_steps) -> tuple[np.ndarray, np.ndarray]:
    state = np.asarray(state_m_mps, dtype=float)
    thrust = np.asarray(thrust_n, dtype=float)
    if state.shape != (6,) or not np.all(np.isfinite(state)):
        raise ValueError(f"state_m_mps must be 6 finite numbers, got {state_m_mps!r}")
    if thrust.shape != (3,) or not np.all(np.isfinite(thrust)):
        raise ValueError(f"thrust_n must be 3 finite numbers, got {thrust_n!r}")
    if int(n_steps) != n_steps or n_steps < 1:
        raise ValueError(f"n_steps must be a positive whole number, got {n_steps}")
    return state, thrust
