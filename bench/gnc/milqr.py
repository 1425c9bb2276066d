"""MILQR: iLQR with a multiplicative attitude error and box-constrained controls (seed 004 sections 3-8).

One iteration, as the seed lays it out:
1. the nominal trajectory (X, U) and its discrete Jacobians in error coordinates dx = [phi; d_omega]
   (phi = Rodrigues parameters of the error quaternion; `bench.gnc.attitude_planning`);
2. backward pass: the quadratic model of Q at each step, Q_uu regularised Levenberg-Marquardt
   style (Q_uu + lambda I, lambda raised on Tassa, Erez and Todorov's 2012 schedule whenever a
   Cholesky factorisation or a line search fails, lowered after a success), the feed-forward
   from the box QP on (Q_uu, Q_u) with the box shifted by the nominal control, warm-started from the
   neighbouring step's solution, and the feedback rows of clamped controls zeroed;
3. forward pass: roll out u = clamp(u_bar + alpha l + K dx) for alpha = 1, 1/2, ... and accept the
   first alpha whose actual cost decrease is at least `armijo` times the expected one.
It converges when the feed-forward or the accepted cost change is small and the projected gradient
of the total cost (exact, by the adjoint recursion) vanishes; it stops unconverged when it stalls far
from stationarity, or on the iteration/wall-time caps (returning the best trajectory so far);
`info["stop_reason"]` says which (issue 27: the feed-forward test alone had ended a 160-degree slew
42 % above IPOPT's cost, reported converged).

Large slews have several local minima (paths round the two ways, with or without extra turns), and
from zero dipoles the descent starts next to the geodesic cost's kink (q_g'q = 0). `milqr` therefore
runs several descents within one wall-time budget (continuation along the short and the long way,
and the given start; `MilqrOptions.rotation_starts`) and returns the lowest cost.

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
from dataclasses import dataclass, field, replace

import numpy as np

from bench.gnc import quaternion as qt
from bench.gnc.boxqp import solve_box_qp


@dataclass(frozen=True)
class GeodesicAttitudeCost:
    """Stage cost w_c (1 - |q_g'q|) + 1/2 |omega - omega_g|_Q^2 + 1/2 |u|_R^2; final cost with w_f, Q_f.

    `hemisphere` +1 or -1 replaces |q_g'q| by hemisphere * q_g'q: the cost then tells q_g from -q_g,
    i.e. the two ways round to the same attitude (a path from q_0 ends near +q_g or -q_g, and which one
    is the path's homotopy class in SO(3)). MILQR uses it only to start a descent in a chosen class;
    the cost it minimises and reports is the geodesic one (hemisphere 0).
    """

    q_goal_wxyz: np.ndarray
    omega_goal_radps: np.ndarray
    attitude_weight: float
    rate_weight: np.ndarray            # Q (3x3)
    dipole_weight: np.ndarray          # R (3x3), positive definite
    final_attitude_weight: float
    final_rate_weight: np.ndarray      # Q_f (3x3)
    hemisphere: int = 0                # 0: geodesic |q_g'q|; +1/-1: signed (a guide, see above)

    def __post_init__(self):
        object.__setattr__(self, "q_goal_wxyz", qt.normalize(self.q_goal_wxyz))
        for name in ("omega_goal_radps", "rate_weight", "dipole_weight", "final_rate_weight"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=float))
        if not np.all(np.linalg.eigvalsh(self.dipole_weight) > 0):
            raise ValueError("dipole_weight (R) must be positive definite")
        if self.attitude_weight < 0 or self.final_attitude_weight < 0:
            raise ValueError("attitude weights must be non-negative")
        if self.hemisphere not in (-1, 0, 1):
            raise ValueError(f"hemisphere must be -1, 0 or +1, got {self.hemisphere}")

    def _alignment(self, c):
        """|q_g'q| (geodesic) or hemisphere * q_g'q (guide)."""
        return np.abs(c) if self.hemisphere == 0 else self.hemisphere * c

    def _attitude(self, q, weight):
        c = float(self.q_goal_wxyz @ q)
        if self.hemisphere == 0:
            sign = 1.0 if c >= 0 else -1.0   # gradient takes the sign that lowers 1 - |q_g'q|
        else:
            sign = float(self.hemisphere)
        value = weight * (1.0 - sign * c)
        grad = -weight * sign * (qt.attitude_jacobian(q).T @ self.q_goal_wxyz)
        # seed: +-I(q_g'q) with the sign of q_g'q. The guide's Hessian, w sign c I, is negative on the
        # far hemisphere; it is clipped at zero there so that the backward pass stays convex.
        hess = weight * max(sign * c, 0.0) * np.eye(3)
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
        stage = (self.attitude_weight * (1.0 - self._alignment(X[:-1, :4] @ self.q_goal_wxyz))
                 + 0.5 * np.einsum("ki,ij,kj->k", dw, self.rate_weight, dw)
                 + 0.5 * np.einsum("ki,ij,kj->k", U, self.dipole_weight, U))
        return float(np.sum(stage) + self.final(X[-1]))

    def gradients(self, X, U):
        """Stage l_x (N, 6), l_u (N, 3) and final l_x (6) in error coordinates along a whole trajectory
        (`cost_gradient`; the same values as stage_expansion / final_expansion, vectorised)."""
        q, g = X[:, :4], self.q_goal_wxyz
        c = q @ g
        sign = (np.where(c >= 0, 1.0, -1.0) if self.hemisphere == 0 else np.full_like(c, float(self.hemisphere)))
        # G(q)' q_g = s g_v - g_0 v - v x g_v  (G = [-v'; s I + [v]x])
        s, v = q[:, :1], q[:, 1:]
        Gt_g = s * g[1:] - g[0] * v - np.cross(v, g[1:])
        weights = np.full(len(X), self.attitude_weight)
        weights[-1] = self.final_attitude_weight
        lq = -(weights * sign)[:, None] * Gt_g
        dw = X[:, 4:] - self.omega_goal_radps
        lw = np.concatenate([dw[:-1] @ self.rate_weight.T, (self.final_rate_weight @ dw[-1])[None]])
        lx = np.concatenate([lq, lw], axis=1)
        return lx[:-1], U @ self.dipole_weight.T, lx[-1]

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
    max_iterations: int = 200           # per descent (each continuation stage and each start has its own)
    max_wall_time_s: float = np.inf     # the whole call, all starts together
    feedforward_tol: float = 1e-5       # max_k |l_k| / (1 + |u_k|) below this (and stationary): converged
    cost_change_tol: float = 1e-9       # accepted relative cost decrease below this (and stationary): converged
    # Stationarity, required by both tests above: the largest component of the projected gradient of
    # the total cost with respect to the dipoles (exact, by the adjoint recursion), in cost per A m^2,
    # relative to max(1, |J|).
    gradient_tol: float = 1e-4
    # Far from stationary (stationarity above stall_gradient_factor * gradient_tol) and the cost down
    # by less than stall_relative_decrease (relative) over the last stall_iterations iterations: stop,
    # not converged ("stalled"). From zero dipoles a 179-degree slew crept down 0.7 % per 25 iterations
    # to the 200-iteration cap at 2e4 in stationarity (the geodesic cost's kink, q_g'q = 0, lies next
    # to that start's path). The factor keeps the linear tail of a converging descent going (a
    # 90-degree slew of the elongated body: 0.3 % over 25 iterations at 6e-4, converged 2 later).
    stall_iterations: int = 25
    stall_relative_decrease: float = 1e-2
    stall_gradient_factor: float = 1e2
    # Regularisation of Q_uu (Tassa, Erez, Todorov 2012): lambda and its multiplier dlambda both grow
    # on failure (dlambda = max(f dlambda, f), lambda = max(lambda dlambda, min)) and shrink after
    # success (dlambda = min(dlambda / f, 1/f), lambda = lambda dlambda, 0 below min).
    regularisation_init: float = 1.0    # seed: start with lambda <= 1
    regularisation_min: float = 1e-6
    regularisation_max: float = 1e10
    regularisation_factor: float = 1.6
    armijo: float = 1e-4                # accept when actual / expected decrease exceeds this
    line_search_steps: int = 12         # alpha = 1, 1/2, ..., 1/2^(steps-1)
    # Continuation starts (issue 27: from zero dipoles a 175-degree slew stopped in local minima
    # 30-63 % above IPOPT's): the slew is solved for a sequence of growing rotations about the same
    # axis, each from the previous answer, on the signed cost of that lift of the goal; the last one is
    # polished with the geodesic cost. "short": the rotation of at most 180 degrees; "long": the other
    # way round (360 degrees minus it), tried only for slews of at least long_way_min_slew_deg. The
    # first stage is at most 2 continuation steps, each further stage one step. The lowest geodesic
    # cost among these and the descent from the given dipoles is returned. Empty: only the given start.
    rotation_starts: tuple[str, ...] = ("short", "long")
    continuation_step_deg: float = 45.0
    # The stages before the last only carry the path round: stopped at this relative cost change
    # (or the feed-forward below 100 feedforward_tol), without the stationarity test.
    continuation_stage_cost_change_tol: float = 1e-4
    long_way_min_slew_deg: float = 150.0


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
        total = cost.total(Xn, Un)          # a wild trial's rates may overflow the final cost: rejected as inf
    return Xn, Un, total if np.isfinite(total) else np.inf


def cost_gradient(cost, X, U, A, B) -> np.ndarray:
    """dJ/du_k (N, 3) of the rolled-out total cost, by the adjoint (costate) recursion on the reduced
    Jacobians: p_N = l_x,N; g_k = l_u,k + B_k' p_{k+1}; p_k = l_x,k + A_k' p_{k+1}. Exact for the
    discrete map (the Cayley map's first derivative at zero is the identity)."""
    lx, lu, p = cost.gradients(X, U)
    grad = np.empty_like(lu)
    for k in range(len(U) - 1, -1, -1):
        grad[k] = lu[k] + B[k].T @ p
        p = lx[k] + A[k].T @ p
    return grad


def projected_gradient(grad, U, lower, upper) -> np.ndarray:
    """The gradient with the components zeroed whose descent direction leaves the box (a dipole on its
    upper bound with a negative gradient, on its lower bound with a positive one): zero at a
    first-order stationary point of the box-constrained problem."""
    out = np.array(grad, dtype=float)
    out[(U >= upper) & (out < 0)] = 0.0
    out[(U <= lower) & (out > 0)] = 0.0
    return out


@dataclass
class _Descent:
    X: np.ndarray
    U: np.ndarray
    J: float
    A: np.ndarray
    B: np.ndarray
    l: np.ndarray
    K: np.ndarray
    stop_reason: str
    converged: bool
    iterations: int
    stationarity: float               # max |projected gradient| / max(1, |J|) at (X, U)
    history: list
    iteration_times: list
    line_search_failures: int
    regularisation: float


def _stationarity(cost, X, U, A, B, lower, upper, J):
    return float(np.max(np.abs(projected_gradient(cost_gradient(cost, X, U, A, B), U, lower, upper)),
                        initial=0.0) / max(1.0, abs(J)))


def _descend(model, cost, x0, U, lower, upper, options: MilqrOptions, deadline: float) -> _Descent:
    """iLQR from the dipoles U (already in the box) until stationary, stalled, or a cap."""
    X = model.rollout(x0, U)
    J = cost.total(X, U)
    A, B = model.linearise(X, U)
    lam, dlam, f = options.regularisation_init, 1.0, options.regularisation_factor

    def increase(lam, dlam):
        dlam = max(dlam * f, f)
        return max(lam * dlam, options.regularisation_min), dlam

    def decrease(lam, dlam):
        dlam = min(dlam / f, 1.0 / f)
        lam = lam * dlam
        return (lam if lam >= options.regularisation_min else 0.0), dlam

    l, K = np.zeros_like(U), np.zeros((len(U), 3, 6))
    history, iteration_times = [J], []
    stop_reason, line_search_failures, small_change = "max_iterations", 0, False
    cost_per_iteration = [J]
    stationarity = _stationarity(cost, X, U, A, B, lower, upper, J)
    iteration = 0
    for iteration in range(1, options.max_iterations + 1):
        t_iter = time.perf_counter()
        if t_iter > deadline:
            stop_reason, iteration = "wall_time", iteration - 1
            break
        stationary = stationarity <= options.gradient_tol
        if small_change and stationary:
            stop_reason, iteration = "cost_change_small", iteration - 1
            break
        # backward pass, raising lambda until every Q_uu factorises
        while True:
            l_new, K_new, dV, failed_at = _backward_pass(cost, X, U, A, B, lower, upper, lam, l)
            if failed_at is None:
                break
            lam, dlam = increase(lam, dlam)
            if lam > options.regularisation_max:
                break
        if failed_at is not None:
            stop_reason = "regularisation_limit"
            break
        l, K = l_new, K_new
        feedforward_size = float(np.max(np.abs(l) / (1.0 + np.abs(U))))
        # A small feed-forward is convergence only where the gradient vanishes too: under a large
        # lambda l ~ -Q_u / lambda is small anywhere (issue 27's 160-degree slew stopped on this test
        # alone, "feedforward_small", 42 % above IPOPT's cost).
        if feedforward_size < options.feedforward_tol and stationary:
            stop_reason = "feedforward_small"
            iteration_times.append(time.perf_counter() - t_iter)
            break
        accepted = False
        alpha = 1.0
        for _ in range(options.line_search_steps):
            Xn, Un, Jn = _forward_pass(model, cost, x0, X, U, l, K, alpha, lower, upper)
            expected = -alpha * (dV[0] + alpha * dV[1])
            ratio = (J - Jn) / expected if expected > 0 else np.sign(J - Jn)
            if np.isfinite(Jn) and ratio > options.armijo and Jn < J:
                accepted = True
                break
            alpha *= 0.5
        if accepted:
            cost_change = J - Jn
            X, U, J = Xn, Un, Jn
            A, B = model.linearise(X, U)
            history.append(J)
            stationarity = _stationarity(cost, X, U, A, B, lower, upper, J)
            small_change = cost_change < options.cost_change_tol * max(abs(J), 1e-300)
            lam, dlam = decrease(lam, dlam)
        else:
            small_change = False
            line_search_failures += 1
            lam, dlam = increase(lam, dlam)
        iteration_times.append(time.perf_counter() - t_iter)
        cost_per_iteration.append(J)
        if lam > options.regularisation_max:
            stop_reason = "regularisation_limit"
            break
        # small or no steps far from stationarity: give up, not converged
        if (len(cost_per_iteration) > options.stall_iterations
                and stationarity > options.stall_gradient_factor * options.gradient_tol
                and cost_per_iteration[-1 - options.stall_iterations] - J < options.stall_relative_decrease * abs(J)):
            stop_reason = "stalled"
            break
    else:
        if small_change and stationarity <= options.gradient_tol:
            stop_reason = "cost_change_small"
    converged = stop_reason in ("feedforward_small", "cost_change_small")
    return _Descent(X, U, J, A, B, l, K, stop_reason, converged, iteration, stationarity, history,
                    iteration_times, line_search_failures, lam)


def continuation_goals(q0_wxyz, q_goal_wxyz, way: str, step_deg: float) -> list[np.ndarray]:
    """The lifts q_0 (x) exp(s r) of the goal along the way chosen ("short": r the rotation vector of
    q_0* (x) q_g, at most 180 degrees; "long": the same axis the other way, 360 degrees minus that),
    at angles 2 step, 3 step, ... below |r| and at |r| itself (scalar part sign included: the last one
    is +q_g or -q_g, the homotopy class of the path)."""
    r = qt.log(qt.multiply(qt.conjugate(q0_wxyz), q_goal_wxyz))
    angle = float(np.linalg.norm(r))
    if angle < 1e-9:
        return [qt.multiply(q0_wxyz, qt.exp(r))]
    if way == "long":
        r = r * (angle - 2.0 * np.pi) / angle
        angle = 2.0 * np.pi - angle
    step = np.deg2rad(step_deg)
    angles = list(np.arange(2.0 * step, angle - 1e-9, step)) + [angle]
    return [qt.multiply(q0_wxyz, qt.exp(r * a / angle)) for a in angles]


def milqr(model, cost: GeodesicAttitudeCost, x0: np.ndarray, dipoles_init_am2: np.ndarray,
          lower_am2: np.ndarray, upper_am2: np.ndarray, options: MilqrOptions = MilqrOptions()) -> MilqrResult:
    """Optimise the dipole sequence from x0 (q_wxyz, omega) over model.horizon_steps steps.

    Several descents: from the given dipoles, and, for slews beyond the first continuation stage,
    by continuation along the short and (near 180 degrees) the long way round
    (`MilqrOptions.rotation_starts`); the lowest geodesic cost is returned. `info["converged"]` is
    that descent's: its projected gradient vanishes (`gradient_tol`) and its step or cost change is
    small; a cap or a stall says False with the reason in `info["stop_reason"]`. The wall-time cap
    covers all descents together and is checked between iterations (one iteration is not
    interrupted), so a call may overrun it by one iteration; the planner runs outside the control
    deadline for that reason. Starts not begun before the cap are listed in `info["starts_skipped"]`.
    """
    started = time.perf_counter()
    deadline = started + options.max_wall_time_s
    x0 = np.asarray(x0, dtype=float)
    if x0.shape != (7,) or not np.all(np.isfinite(x0)):
        raise ValueError(f"x0 must be a finite 7-vector [q_wxyz, omega], got {x0}")
    x0 = np.concatenate([qt.normalize(x0[:4]), x0[4:]])
    lower, upper = np.broadcast_to(lower_am2, (3,)).astype(float), np.broadcast_to(upper_am2, (3,)).astype(float)
    U0 = np.clip(np.asarray(dipoles_init_am2, dtype=float), lower, upper)
    if U0.shape != (model.horizon_steps, 3):
        raise ValueError(f"dipoles_init_am2 must be ({model.horizon_steps}, 3), got {U0.shape}")
    unknown = set(options.rotation_starts) - {"short", "long"}
    if unknown:
        raise ValueError(f"rotation_starts: unknown {sorted(unknown)} (known: 'short', 'long')")
    if cost.hemisphere != 0:
        raise ValueError("milqr minimises the geodesic cost (hemisphere 0); the signed one is only for its stages")
    if not options.continuation_step_deg > 0:
        raise ValueError(f"continuation_step_deg must be positive, got {options.continuation_step_deg}")

    slew_deg = np.rad2deg(qt.angle_between_rad(x0[:4], cost.q_goal_wxyz))
    plans = []                    # (name, goals of the continuation stages or None for the given start)
    for name in options.rotation_starts:
        goals = continuation_goals(x0[:4], cost.q_goal_wxyz, name, options.continuation_step_deg)
        if name == "short" and len(goals) > 1:
            plans.append((name, goals))
        elif name == "long" and slew_deg >= options.long_way_min_slew_deg:
            plans.append((name, goals))
    # The continuations first when there are any: within a wall-time budget they are the likeliest
    # best (from zero dipoles the given start's path lies next to the geodesic cost's kink on large slews).
    plans = plans + [("given", None)]

    finals, starts, skipped, all_descents = [], [], [], []
    for name, goals in plans:
        if finals and time.perf_counter() > deadline:
            skipped.append(name)
            continue
        descents, U = [], U0
        stage_options = replace(options, cost_change_tol=options.continuation_stage_cost_change_tol,
                                feedforward_tol=100.0 * options.feedforward_tol, gradient_tol=np.inf)
        for goal in goals or []:
            stage = _descend(model, replace(cost, q_goal_wxyz=goal, hemisphere=1), x0, U, lower, upper,
                             stage_options, deadline)
            descents.append(stage)
            U = stage.U
        final = _descend(model, cost, x0, U, lower, upper, options, deadline)
        descents.append(final)
        all_descents.extend(descents)
        finals.append(final)
        starts.append(_start_record(name, final, descents))
    best_index = int(np.argmin([r.J for r in finals]))
    best = finals[best_index]
    info = {
        "stop_reason": best.stop_reason,
        "converged": best.converged,
        "stationarity": best.stationarity,
        "iterations": int(sum(r.iterations for r in all_descents)),
        "best_start": starts[best_index]["name"],
        "starts": starts,
        "starts_skipped": skipped,
        "cost_history": best.history,
        "regularisation": best.regularisation,
        "line_search_failures": int(sum(r.line_search_failures for r in all_descents)),
        "iteration_times_s": [t for r in all_descents for t in r.iteration_times],
        "wall_time_s": time.perf_counter() - started,
    }
    return MilqrResult(best.X, best.U, -best.K, best.l, best.J, best.A, best.B, info)


def _start_record(name, final: _Descent, descents) -> dict:
    return {"name": name, "cost": final.J, "stop_reason": final.stop_reason, "converged": final.converged,
            "stationarity": final.stationarity, "iterations": int(sum(d.iterations for d in descents)),
            "stages": len(descents) - 1, "stage_iterations": [d.iterations for d in descents]}
