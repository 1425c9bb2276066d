"""Discrete attitude dynamics for magnetorquer planning, with Jacobians in reduced coordinates (seed 004).

State x = [q (4, scalar first, body to inertial), omega (3, body, rad/s)]; control u = magnetic dipole
m in the body frame (A m^2). The inertial field B_N is given per planning step (a sequence sampled
along the orbit) and held over the step; at every Runge-Kutta stage it is rotated into the body
with the stage attitude, so the torque tau = m x (R(q)^T B_N) follows the rotation within a step:

    q_dot     = 1/2 q (x) [0, omega]
    omega_dot = J^-1 (m x R(q)^T B_N - omega x J omega)

One step is classical RK4 followed by normalisation of q (the same integrator as the truth model
`bench.plant.attitude.rk4_attitude_step`, which however holds the torque, not the dipole, over its
0.1 s step). The Jacobians are those of exactly this map, pushed into the 6-dimensional error
coordinates dx = [phi; d_omega], phi the Rodrigues parameters of q_ref* (x) q (seed 004 section 6):

    A_red = E(x_{k+1})^T N (d x~_{k+1} / d x_k) E(x_k),    B_red = E(x_{k+1})^T N (d x~_{k+1} / d u_k)

Seed 004 errata handled here:
- d q_dot / d omega = 1/2 G(q) (the seed drops the 1/2);
- d omega_dot / d q is not zero once the field is rotated into the body with q (the seed's
  section 2 is for a body-fixed torque);
- in its RK2 chain rule d x~_{k+1} / d x_k is the 7x7 identity, not I_4.

The functions take one state or a stack of them (leading axes), so the Jacobians of a whole
horizon come from one vectorised call (`linearise`); MILQR spent most of its time in a per-step
Python loop over 4x4 and 3x3 products before.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.gnc import quaternion as qt


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis (np.cross's axis handling cost more than the arithmetic here)."""
    a1, a2, a3 = a[..., 0], a[..., 1], a[..., 2]
    b1, b2, b3 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a2 * b3 - a3 * b2, a3 * b1 - a1 * b3, a1 * b2 - a2 * b1], axis=-1)


def _skew(v: np.ndarray) -> np.ndarray:
    """[v]x over leading axes: (..., 3) -> (..., 3, 3)."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.sum(a * b, axis=-1)


def body_vector(q: np.ndarray, vector_inertial: np.ndarray) -> np.ndarray:
    """q* (x) [0, b] (x) q = (s^2 - v.v) b + 2 (v.b) v - 2 s (v x b): R(q)' b for a unit q.

    Quadratic in q and evaluated as such off the unit sphere (inside the RK stages), so that the
    Jacobian below is its exact derivative.
    """
    s, v, b = q[..., :1], q[..., 1:4], vector_inertial
    return (s * s - _dot(v, v)[..., None]) * b + 2.0 * _dot(v, b)[..., None] * v - 2.0 * s * _cross(v, b)


def _d_body_vector_dq(q: np.ndarray, vector_inertial: np.ndarray) -> np.ndarray:
    """d body_vector / dq, (..., 3, 4)."""
    s, v, b = q[..., 0], q[..., 1:4], vector_inertial
    out = np.empty(q.shape[:-1] + (3, 4))
    out[..., 0] = 2.0 * s[..., None] * b - 2.0 * _cross(v, b)
    out[..., 1:] = (-2.0 * b[..., :, None] * v[..., None, :] + 2.0 * v[..., :, None] * b[..., None, :]
                    + 2.0 * _dot(v, b)[..., None, None] * np.eye(3) + 2.0 * s[..., None, None] * _skew(b))
    return out


def _attitude_jacobian(q: np.ndarray) -> np.ndarray:
    """G(q) = L(q) H over leading axes, (..., 4, 3)."""
    out = np.empty(q.shape[:-1] + (4, 3))
    out[..., 0, :] = -q[..., 1:4]
    out[..., 1:, :] = q[..., 0, None, None] * np.eye(3) + _skew(q[..., 1:4])
    return out


def _state_error_jacobian(x: np.ndarray) -> np.ndarray:
    """E(x) (..., 7, 6) of `bench.gnc.quaternion.state_error_jacobian`, over leading axes."""
    out = np.zeros(x.shape[:-1] + (7, 6))
    out[..., :4, :3] = _attitude_jacobian(x[..., :4])
    out[..., 4:, 3:] = np.eye(3)
    return out


@dataclass(frozen=True)
class MagnetorquerAttitudeModel:
    """RK4 + normalisation step of a rigid body driven by magnetorquers, and its Jacobians.

    `field_inertial_t` holds B_N for each planning step k (shape (N, 3), tesla); `dt_s` is the step.
    """

    inertia_kgm2: np.ndarray
    field_inertial_t: np.ndarray
    dt_s: float

    def __post_init__(self):
        inertia = np.asarray(self.inertia_kgm2, dtype=float)
        field = np.asarray(self.field_inertial_t, dtype=float)
        if inertia.shape != (3, 3) or not np.all(np.linalg.eigvalsh(0.5 * (inertia + inertia.T)) > 0):
            raise ValueError(f"inertia_kgm2 must be a symmetric positive definite 3x3, got {inertia}")
        if field.ndim != 2 or field.shape[1] != 3 or not np.all(np.isfinite(field)):
            raise ValueError(f"field_inertial_t must be a finite (N, 3) array, got shape {field.shape}")
        if not (np.isfinite(self.dt_s) and self.dt_s > 0):
            raise ValueError(f"dt_s must be positive, got {self.dt_s}")
        object.__setattr__(self, "inertia_kgm2", inertia)
        object.__setattr__(self, "field_inertial_t", field)
        object.__setattr__(self, "_inertia_inv", np.linalg.inv(inertia))

    @property
    def horizon_steps(self) -> int:
        return self.field_inertial_t.shape[0]

    # ---- continuous time (every function takes one state or a stack of them, leading axes first) --

    def derivative(self, x: np.ndarray, dipole_am2: np.ndarray, field_n: np.ndarray) -> np.ndarray:
        if x.ndim == 1:
            return self._derivative_one(x, dipole_am2, field_n)
        q, w = x[..., :4], x[..., 4:]
        torque = _cross(dipole_am2, body_vector(q, field_n))
        w_dot = (torque - _cross(w, w @ self.inertia_kgm2)) @ self._inertia_inv.T
        # q (x) [0, w] = [-v.w, s w + v x w]
        q_dot = 0.5 * np.concatenate([-_dot(q[..., 1:], w)[..., None], q[..., :1] * w + _cross(q[..., 1:], w)], axis=-1)
        return np.concatenate([q_dot, w_dot], axis=-1)

    def _derivative_one(self, x, dipole_am2, field_n):
        """`derivative` for one state, written out by component: the sequential roll-outs of the line
        search call it 4 N times per trial, and array-stacking overhead made the vectorised form
        3x slower there (cProfile, 82-step slew). Test: equal to the vectorised form."""
        s, v1, v2, v3, p, r_, y = x
        b1, b2, b3 = field_n
        vv, vb = v1 * v1 + v2 * v2 + v3 * v3, v1 * b1 + v2 * b2 + v3 * b3
        c0 = s * s - vv
        f1 = c0 * b1 + 2.0 * vb * v1 - 2.0 * s * (v2 * b3 - v3 * b2)
        f2 = c0 * b2 + 2.0 * vb * v2 - 2.0 * s * (v3 * b1 - v1 * b3)
        f3 = c0 * b3 + 2.0 * vb * v3 - 2.0 * s * (v1 * b2 - v2 * b1)
        m1, m2, m3 = dipole_am2
        h1, h2, h3 = self.inertia_kgm2 @ x[4:]
        out = np.empty(7)
        out[0] = -0.5 * (v1 * p + v2 * r_ + v3 * y)
        out[1] = 0.5 * (s * p + v2 * y - v3 * r_)
        out[2] = 0.5 * (s * r_ - v1 * y + v3 * p)
        out[3] = 0.5 * (s * y + v1 * r_ - v2 * p)
        out[4:] = self._inertia_inv @ np.array([m2 * f3 - m3 * f2 - (r_ * h3 - y * h2),
                                                m3 * f1 - m1 * f3 - (y * h1 - p * h3),
                                                m1 * f2 - m2 * f1 - (p * h2 - r_ * h1)])
        return out

    def derivative_jacobians(self, x: np.ndarray, dipole_am2: np.ndarray,
                             field_n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """df/dx (..., 7, 7) and df/du (..., 7, 3) of `derivative`."""
        q, w = x[..., :4], x[..., 4:]
        J, J_inv = self.inertia_kgm2, self._inertia_inv
        lead = x.shape[:-1]
        A = np.zeros(lead + (7, 7))
        # d(1/2 q (x) [0, w])/dq = 1/2 R([0, w]) = 1/2 [[0, -w'], [w, -[w]x]]
        A[..., 0, 1:4] = -0.5 * w
        A[..., 1:4, 0] = 0.5 * w
        A[..., 1:4, 1:4] = -0.5 * _skew(w)
        A[..., :4, 4:] = 0.5 * _attitude_jacobian(q)                  # seed: missing 1/2
        A[..., 4:, :4] = J_inv @ _skew(dipole_am2) @ _d_body_vector_dq(q, field_n)   # tau = [m]x b(q)
        A[..., 4:, 4:] = J_inv @ (_skew(w @ J) - _skew(w) @ J)
        B = np.zeros(lead + (7, 3))
        B[..., 4:, :] = -J_inv @ _skew(body_vector(q, field_n))       # m x b = -[b]x m
        return A, B

    # ---- one discrete step -----------------------------------------------------------------------

    def step(self, x: np.ndarray, dipole_am2: np.ndarray, k: int) -> np.ndarray:
        """x_{k+1} from x_k under dipole u_k held over step k (RK4, then q normalised)."""
        return self._step(np.asarray(x, float), np.asarray(dipole_am2, float), self.field_inertial_t[k], False)[0]

    def step_jacobians(self, x: np.ndarray, dipole_am2: np.ndarray, k: int):
        """(x_{k+1}, A (7x7), B (7x3)): the full-coordinate Jacobians of `step`, normalisation included."""
        return self._step(np.asarray(x, float), np.asarray(dipole_am2, float), self.field_inertial_t[k], True)

    def reduced_jacobians(self, x: np.ndarray, dipole_am2: np.ndarray, k):
        """(x_{k+1}, A (6x6), B (6x3)) in error coordinates [Rodrigues phi; d_omega].

        x, dipole_am2 and k may also be stacks (N, 7), (N, 3), (N,): the whole horizon in one call.
        """
        x = np.asarray(x, float)
        x_next, A, B = self._step(x, np.asarray(dipole_am2, float), self.field_inertial_t[k], True)
        E_next_T = np.swapaxes(_state_error_jacobian(x_next), -1, -2)
        return x_next, E_next_T @ A @ _state_error_jacobian(x), E_next_T @ B

    def linearise(self, states: np.ndarray, dipoles_am2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Reduced Jacobians A (N, 6, 6), B (N, 6, 3) along a trajectory, all steps at once."""
        _, A, B = self.reduced_jacobians(states[:-1], dipoles_am2, np.arange(len(dipoles_am2)))
        return A, B

    def _step(self, x, u, field_n, with_jacobians):
        h = self.dt_s
        stage_offsets = (0.0, 0.5 * h, 0.5 * h, h)
        weights = (h / 6.0, h / 3.0, h / 3.0, h / 6.0)
        eye7 = np.eye(7)
        x_tilde = x.copy()
        A_tilde = np.broadcast_to(eye7, x.shape[:-1] + (7, 7)).copy() if with_jacobians else None
        B_tilde = 0.0
        slope = d_slope_dx = d_slope_du = None
        for c, wt in zip(stage_offsets, weights):
            x_stage = x if slope is None else x + c * slope
            slope = self.derivative(x_stage, u, field_n)
            x_tilde = x_tilde + wt * slope
            if with_jacobians:
                A_c, B_c = self.derivative_jacobians(x_stage, u, field_n)
                if d_slope_dx is None:
                    d_slope_dx, d_slope_du = A_c, B_c
                else:
                    d_slope_dx = A_c @ (eye7 + c * d_slope_dx)
                    d_slope_du = A_c @ (c * d_slope_du) + B_c
                # seed: d x~ / d x_k is I_7 (it writes I_4)
                A_tilde = A_tilde + wt * d_slope_dx
                B_tilde = B_tilde + wt * d_slope_du
        q_tilde = x_tilde[..., :4]
        norm = np.linalg.norm(q_tilde, axis=-1, keepdims=True)
        x_next = np.concatenate([q_tilde / norm, x_tilde[..., 4:]], axis=-1)
        if not with_jacobians:
            return x_next, None, None
        # normalisation Jacobian N = blockdiag(I/|q~| - q~ q~'/|q~|^3, I_3)
        N = np.broadcast_to(eye7, A_tilde.shape).copy()
        N[..., :4, :4] = np.eye(4) / norm[..., None] - q_tilde[..., :, None] * q_tilde[..., None, :] / norm[..., None] ** 3
        return x_next, N @ A_tilde, N @ B_tilde

    def rollout(self, x0: np.ndarray, dipoles_am2: np.ndarray) -> np.ndarray:
        """States x_0..x_N (N+1, 7) under the dipole sequence (N, 3)."""
        X = np.empty((len(dipoles_am2) + 1, 7))
        X[0] = x0
        for k, u in enumerate(dipoles_am2):
            X[k + 1] = self.step(X[k], u, k)
        return X


def field_along_orbit_t(orbit, geomagnetic, start_time_s: float, dt_s: float, steps: int) -> np.ndarray:
    """Inertial field (steps, 3) at t_k = start + k dt from any orbit/field pair of `bench.plant.attitude`."""
    times = start_time_s + dt_s * np.arange(steps)
    return np.array([geomagnetic.field_t(orbit.position_m(t), t) for t in times])


def state_from(q_wxyz, omega_radps) -> np.ndarray:
    return np.concatenate([qt.normalize(q_wxyz), np.asarray(omega_radps, dtype=float)])


# ---- horizon from the controllability Gramian ---------------------------------------------------

# Tolerance on cond(W) for the angular-momentum Gramian W = sum_k [B_k]x [B_k]x' dt.
# Why 3: a field turning in one plane gives W proportional to I - P/2 (P the in-plane projector)
# over a full turn, so cond(W) >= 2 for such a field and a tolerance at or below 2 may never be met.
# On the 500-550 km, 51.6 deg orbits of the bench with the tilted dipole (measured, start times
# 0/1500/3000 s): cond(W) = 9-15 at 10 min, ~4 at 20 min, 2.0-2.7 at 30 min, then flat (1.3-2.0)
# for the rest of the orbit. 3 sits where the curve flattens: the weakest axis already has a third
# of the strongest axis's authority, and going lower buys little controllability for a horizon
# (and a MILQR problem) up to twice as long.
GRAMIAN_CONDITION_TOLERANCE = 3.0


@dataclass(frozen=True)
class GramianHorizon:
    steps: int                     # number of planning steps of dt_s
    horizon_s: float
    condition_number: float        # cond(W) at the chosen horizon
    condition_history: np.ndarray  # cond(W) after 1..steps steps
    reached: bool                  # False: tolerance not met within the samples given


def gramian_horizon(field_inertial_t: np.ndarray, dt_s: float,
                    condition_tolerance: float = GRAMIAN_CONDITION_TOLERANCE) -> GramianHorizon:
    """Shortest horizon whose magnetic controllability Gramian has cond(W) <= tolerance (seed 004 section 7).

    Angular momentum in the inertial frame obeys L_dot = m x B = -[B]x m; with the dipole free in
    direction, W(T) = integral_0^T [B]x [B]x' dt (piecewise constant B over each step, as planned).
    The field is scaled to its mean magnitude first (cond is scale-free; this keeps W near 1).
    """
    if condition_tolerance <= 1.0:
        raise ValueError(f"condition_tolerance must exceed 1, got {condition_tolerance}")
    field = np.asarray(field_inertial_t, dtype=float)
    field = field / np.mean(np.linalg.norm(field, axis=1))
    W = np.zeros((3, 3))
    history = []
    for k, b in enumerate(field):
        S = qt.skew(b)
        W += S @ S.T * dt_s
        sv = np.linalg.svd(W, compute_uv=False)
        cond = sv[0] / sv[-1] if sv[-1] > 0 else np.inf
        history.append(cond)
        if cond <= condition_tolerance:
            return GramianHorizon(k + 1, (k + 1) * dt_s, float(cond), np.array(history), True)
    return GramianHorizon(len(field), len(field) * dt_s, float(history[-1]), np.array(history), False)
