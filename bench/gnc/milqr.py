"""MILQR: iLQR with a multiplicative attitude error and box-constrained controls (seed 004 sections 3-8).

One iteration, as the seed lays it out:
1. the nominal trajectory (X, U) and its discrete Jacobians in error coordinates dx = [phi; d_omega]
   (phi = Rodrigues parameters of the error quaternion; `bench.gnc.attitude_planning`);
2. backward pass: the quadratic model of Q at each step, Q_uu regularised Levenberg-Marquardt
   style (Q_uu + lambda I, lambda raised whenever a Cholesky factorisation fails), the feed-forward
   from the box QP on (Q_uu, Q_u) with the box shifted by the nominal control, warm-started from the
   neighbouring step's solution, and the feedback rows of clamped controls zeroed;
3. forward pass: roll out u = clamp(u_bar + alpha l + K dx) for alpha = 1, 1/2, ... and accept the
   first alpha whose actual cost decrease is at least `armijo` times the expected one.
It stops when the feed-forward is small, when the accepted cost change is small, or on the
iteration/wall-time caps (then returning the best trajectory so far); `info["stop_reason"]` says which.

Sign convention: this module writes the step as du = l + K dx (Tassa et al.); seed 004 writes
du = -l - K dx. The returned `feedback_gains` use the tracking convention of seed 000,
u = u_bar - K_track dx, so K_track = -K.

Cost (seed 004 section 6): geodesic attitude cost w (1 - |q_g' q|), quadratic rate and dipole
costs. In error coordinates its gradient is -w sgn(q_g' q) G(q)' q_g and its Hessian w |q_g' q| I_3.
The seed's general formula for the Hessian of a scalar function of a quaternion,
G' f_qq G + I_3 (f_q q), has the wrong sign on its second term (it is -I_3 (f_q q); the Cayley
map's second derivative at zero is -I on the scalar part); its specific result for the geodesic
cost, +-I_3 (q_g' q) taking the sign of q_g' q, is right and is what is used here.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from bench.gnc import quaternion as qt
from bench.gnc.boxqp import solve_box_qp


@dataclass(frozen=True)
class GeodesicAttitudeCost:
    """Stage cost w_c (1 - |q_g'q|) + 1/2 |omega - omega_g|_Q^2 + 1/2 |u|_R^2; final cost with w_f, Q_f."""

    q_goal_wxyz: np.ndarray
    omega_goal_radps: np.ndarray
    attitude_weight: float
    rate_weight: np.ndarray            # Q (3x3)
    dipole_weight: np.ndarray          # R (3x3), positive definite
    final_attitude_weight: float
    final_rate_weight: np.ndarray      # Q_f (3x3)

    def __post_init__(self):
        object.__setattr__(self, "q_goal_wxyz", qt.normalize(self.q_goal_wxyz))
        for name in ("omega_goal_radps", "rate_weight", "dipole_weight", "final_rate_weight"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=float))
        if not np.all(np.linalg.eigvalsh(self.dipole_weight) > 0):
            raise ValueError("dipole_weight (R) must be positive definite")
        if self.attitude_weight < 0 or self.final_attitude_weight < 0:
            raise ValueError("attitude weights must be non-negative")

    def _attitude(self, q, weight):
        c = float(self.q_goal_wxyz @ q)
        sign = 1.0 if c >= 0 else -1.0       # gradient takes the sign that lowers 1 - |q_g'q|
        value = weight * (1.0 - abs(c))
        grad = -weight * sign * (qt.attitude_jacobian(q).T @ self.q_goal_wxyz)
        hess = weight * abs(c) * np.eye(3)   # seed: +-I(q_g'q) with the sign of q_g'q
        return value, grad, hess

    def stage(self, x, u) -> float:
        dw = x[4:] - self.omega_goal_radps
        return self._attitude(x[:4], self.attitude_weight)[0] + 0.5 * dw @ self.rate_weight @ dw + 0.5 * u @ self.dipole_weight @ u

    def final(self, x) -> float:
        dw = x[4:] - self.omega_goal_radps
        return self._attitude(x[:4], self.final_attitude_weight)[0] + 0.5 * dw @ self.final_rate_weight @ dw

    def total(self, X, U) -> float:
        """Stage costs of x_0..x_{N-1} plus the final cost of x_N, evaluated for the whole trajectory at once."""
        dw = X[:-1, 4:] - self.omega_goal_radps
        stage = (self.attitude_weight * (1.0 - np.abs(X[:-1, :4] @ self.q_goal_wxyz))
                 + 0.5 * np.einsum("ki,ij,kj->k", dw, self.rate_weight, dw)
                 + 0.5 * np.einsum("ki,ij,kj->k", U, self.dipole_weight, U))
        return float(np.sum(stage) + self.final(X[-1]))

    def stage_expansion(self, x, u):
        """(l_x (6), l_u (3), l_xx (6x6), l_uu (3x3)) in error coordinates; l_ux is zero."""
        _, gq, hq = self._attitude(x[:4], self.attitude_weight)
        lx = np.concatenate([gq, self.rate_weight @ (x[4:] - self.omega_goal_radps)])
        lxx = np.zeros((6, 6))
        lxx[:3, :3], lxx[3:, 3:] = hq, self.rate_weight
        return lx, self.dipole_weight @ u, lxx, self.dipole_weight

    def final_expansion(self, x):
        _, gq, hq = self._attitude(x[:4], self.final_attitude_weight)
        lx = np.concatenate([gq, self.final_rate_weight @ (x[4:] - self.omega_goal_radps)])
        lxx = np.zeros((6, 6))
        lxx[:3, :3], lxx[3:, 3:] = hq, self.final_rate_weight
        return lx, lxx


@dataclass(frozen=True)
class MilqrOptions:
    max_iterations: int = 200
    max_wall_time_s: float = np.inf
    feedforward_tol: float = 1e-5       # max_k |l_k| / (1 + |u_k|) below this: converged
    cost_change_tol: float = 1e-9       # accepted relative cost decrease below this: converged
    regularisation_init: float = 1.0    # seed: start with lambda <= 1
    regularisation_min: float = 1e-9    # below this lambda is set to 0
    regularisation_max: float = 1e10
    regularisation_factor: float = 10.0
    armijo: float = 1e-4                # accept when actual / expected decrease exceeds this
    line_search_steps: int = 12         # alpha = 1, 1/2, ..., 1/2^(steps-1)


@dataclass
class MilqrResult:
    states: np.ndarray            # (N+1, 7) [q_wxyz, omega_radps]
    dipoles_am2: np.ndarray       # (N, 3)
    # Last backward pass (about the returned trajectory when stop_reason is feedforward_small, about
    # the one before the last accepted step otherwise): u = u_bar - K dx (seed 000), clamped rows zero.
    # The tracker recomputes TVLQR gains along the plan with its own weights (attitude_tracking.py).
    feedback_gains: np.ndarray    # (N, 3, 6)
    feedforward: np.ndarray       # (N, 3) that pass's l
    cost: float
    A: np.ndarray                 # (N, 6, 6) reduced Jacobians along the returned trajectory
    B: np.ndarray                 # (N, 6, 3)
    info: dict = field(default_factory=dict)


def _backward_pass(cost, X, U, A, B, lower, upper, lam, l_prev):
    N = len(U)
    l, K = np.zeros((N, 3)), np.zeros((N, 3, 6))
    Vx, Vxx = cost.final_expansion(X[N])
    dV = np.zeros(2)
    warm = l_prev[N - 1]
    for k in range(N - 1, -1, -1):
        lx, lu, lxx, luu = cost.stage_expansion(X[k], U[k])
        Ak, Bk = A[k], B[k]
        Qx, Qu = lx + Ak.T @ Vx, lu + Bk.T @ Vx
        VxxA = Vxx @ Ak
        Qxx, Qux = lxx + Ak.T @ VxxA, Bk.T @ VxxA
        Quu = luu + Bk.T @ Vxx @ Bk
        Quu_reg = Quu + lam * np.eye(3)
        res = solve_box_qp(Quu_reg, Qu, lower - U[k], upper - U[k], warm)
        if res.status == "not_positive_definite":
            return None, None, None, k
        l[k] = res.x
        warm = res.x                              # seed: warm start l_k from l_{k+1}
        free = ~res.clamped
        if free.any():                            # clamped rows of K stay zero
            K[k][free] = -res.solve_free(Qux[free])
        dV += [l[k] @ Qu, 0.5 * l[k] @ Quu @ l[k]]
        Vx = Qx + K[k].T @ Quu @ l[k] + K[k].T @ Qu + Qux.T @ l[k]
        Vxx = Qxx + K[k].T @ Quu @ K[k] + K[k].T @ Qux + Qux.T @ K[k]
        Vxx = 0.5 * (Vxx + Vxx.T)
    return l, K, dV, None


def _forward_pass(model, cost, x0, X, U, l, K, alpha, lower, upper):
    N = len(U)
    Xn, Un = np.empty_like(X), np.empty_like(U)
    Xn[0] = x0
    with np.errstate(over="ignore", invalid="ignore"):
        for k in range(N):
            try:
                dx = qt.error_state(Xn[k, :4], Xn[k, 4:], X[k, :4], X[k, 4:])
            except ValueError:      # 180 degrees off the nominal: a step this long is rejected
                return Xn, Un, np.inf
            Un[k] = np.clip(U[k] + alpha * l[k] + K[k] @ dx, lower, upper)
            Xn[k + 1] = model.step(Xn[k], Un[k], k)
            if not np.all(np.isfinite(Xn[k + 1])):
                return Xn, Un, np.inf
    return Xn, Un, cost.total(Xn, Un)


def milqr(model, cost: GeodesicAttitudeCost, x0: np.ndarray, dipoles_init_am2: np.ndarray,
          lower_am2: np.ndarray, upper_am2: np.ndarray, options: MilqrOptions = MilqrOptions()) -> MilqrResult:
    """Optimise the dipole sequence from x0 (q_wxyz, omega) over model.horizon_steps steps.

    The wall-time cap is checked between iterations (one iteration is not interrupted), so a call
    may overrun it by one iteration; the planner runs outside the control deadline for that reason.
    """
    started = time.perf_counter()
    x0 = np.asarray(x0, dtype=float)
    if x0.shape != (7,) or not np.all(np.isfinite(x0)):
        raise ValueError(f"x0 must be a finite 7-vector [q_wxyz, omega], got {x0}")
    x0 = np.concatenate([qt.normalize(x0[:4]), x0[4:]])
    lower, upper = np.broadcast_to(lower_am2, (3,)).astype(float), np.broadcast_to(upper_am2, (3,)).astype(float)
    U = np.clip(np.asarray(dipoles_init_am2, dtype=float), lower, upper)
    if U.shape != (model.horizon_steps, 3):
        raise ValueError(f"dipoles_init_am2 must be ({model.horizon_steps}, 3), got {U.shape}")
    X = model.rollout(x0, U)
    J = cost.total(X, U)
    A, B = model.linearise(X, U)
    lam = options.regularisation_init
    l, K = np.zeros_like(U), np.zeros((len(U), 3, 6))
    history = [J]
    iteration_times, stop_reason = [], "max_iterations"
    line_search_failures = 0
    iteration = 0
    for iteration in range(1, options.max_iterations + 1):
        t_iter = time.perf_counter()
        if t_iter - started > options.max_wall_time_s:
            stop_reason, iteration = "wall_time", iteration - 1
            break
        # backward pass, raising lambda until every Q_uu factorises
        while True:
            l_new, K_new, dV, failed_at = _backward_pass(cost, X, U, A, B, lower, upper, lam, l)
            if failed_at is None:
                break
            lam = max(lam * options.regularisation_factor, options.regularisation_min)
            if lam > options.regularisation_max:
                break
        if failed_at is not None:
            stop_reason = "regularisation_limit"
            break
        l, K = l_new, K_new
        feedforward_size = float(np.max(np.abs(l) / (1.0 + np.abs(U))))
        if feedforward_size < options.feedforward_tol:
            stop_reason = "feedforward_small"
            iteration_times.append(time.perf_counter() - t_iter)
            break
        accepted = False
        alpha = 1.0
        for _ in range(options.line_search_steps):
            Xn, Un, Jn = _forward_pass(model, cost, x0, X, U, l, K, alpha, lower, upper)
            expected = -alpha * (dV[0] + alpha * dV[1])
            ratio = (J - Jn) / expected if expected > 0 else np.sign(J - Jn)
            if np.isfinite(Jn) and ratio > options.armijo:
                accepted = True
                break
            alpha *= 0.5
        if accepted:
            cost_change = J - Jn
            X, U, J = Xn, Un, Jn
            A, B = model.linearise(X, U)
            history.append(J)
            lam = lam / options.regularisation_factor
            if lam < options.regularisation_min:
                lam = 0.0
            iteration_times.append(time.perf_counter() - t_iter)
            if cost_change < options.cost_change_tol * max(abs(J), 1e-300):
                stop_reason = "cost_change_small"
                break
        else:
            line_search_failures += 1
            lam = max(lam * options.regularisation_factor, options.regularisation_min)
            iteration_times.append(time.perf_counter() - t_iter)
            if lam > options.regularisation_max:
                stop_reason = "regularisation_limit"
                break
    info = {
        "stop_reason": stop_reason,
        "converged": stop_reason in ("feedforward_small", "cost_change_small"),
        "iterations": iteration,
        "cost_history": history,
        "regularisation": lam,
        "line_search_failures": line_search_failures,
        "iteration_times_s": iteration_times,
        "wall_time_s": time.perf_counter() - started,
    }
    return MilqrResult(X, U, -K, l, J, A, B, info)
