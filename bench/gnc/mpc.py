"""The MPC family of seed 003 (problems 17 to 20) as condensed QPs on proxsuite.

One builder, `condensed_qp`, writes every variant: the states are eliminated through the
prediction x_i = A^i x_0 + sum_j A^(i-1-j) B u_j, leaving the inputs (and, for soft constraints,
the slacks; for the tube, the nominal initial state) as decision variables. The variants differ
only in which terms and constraints they switch on. The state x enters the QP linearly through
g, b and u, so a cycle updates three vectors and re-solves.

Units: scaled state (Mm, km/s), thrust in N, as `ScaledModel`.
"""
from __future__ import annotations

from dataclasses import dataclass
import time

import numpy as np
from scipy.linalg import block_diag

from bench.gnc.lqr import dlqr
from bench.gnc.qp import DenseBoxQP, QPSolution
from bench.gnc.sets import Polytope
from bench.gnc.weights import check_weights
from bench.gnc.kkt import ActiveSet, PRIMAL_TOL

# The solver meets constraints to its tolerance (1e-7), so a closed loop riding a state constraint
# lands a hair outside it; the i = 0 check allows that much (scaled units: 1e-6 Mm = 1 m).
INITIAL_STATE_TOL = 1e-6
# Key of `info` with the planned inputs (N x nu, N): the deadline's "shifted plan" fallback.
PLAN_INFO_KEY = "u_plan"


@dataclass(frozen=True)
class SoftStatePenalty:
    """Slack penalty of seed 003 eq. (20a): sum_i eps_i' S eps_i + v ||eps_i||_inf."""

    S: np.ndarray
    v: float


@dataclass
class CondensedQP:
    """The QP of one MPC variant, affine in the current state x:

        min 1/2 y'Hy + (G x + g0)'y + x'W x
        s.t. A y = E x,   l0 + Dl x <= C y <= u0 + Du x,   l_box <= y <= u_box.

    Opposite constraint rows (|z| <= s_max as two rows) are stored once, two-sided: half the rows
    for proxsuite, which roughly halves its time per iteration here.
    """

    H: np.ndarray
    G: np.ndarray
    g0: np.ndarray
    W: np.ndarray
    A: np.ndarray | None
    E: np.ndarray | None
    C: np.ndarray | None
    l0: np.ndarray
    Dl: np.ndarray
    u0: np.ndarray
    Du: np.ndarray
    l_box: np.ndarray
    u_box: np.ndarray
    inputs: slice             # where u_0 .. u_{N-1} sit in y
    initial_state: slice | None   # where the nominal z_0 sits in y (tube MPC only)
    slacks: slice | None = None   # eps and t of soft constraints (zero when nothing is violated)


@dataclass(frozen=True, eq=False)
class ExplicitPath:
    """The explicit law of a CondensedMPC as a small picklable object: y(x) = y_gain x + y_offset
    on the nominal active set, valid where its KKT certificate `check x <= bound` holds.

    `CondensedMPC.eval` answers its explicit cycles through this object, and the solver worker
    (bench.runtime.solver_worker) sends it to the flight process, which answers the same cycles
    without a round trip: one code path, so the two give bit-identical (u, info). Its evaluation
    is a fixed handful of matrix-vector products (a few us): it cannot overrun a deadline.
    `input_from` / `plan_from` also turn a solved QP's y into (u, plan), for every cycle.
    """

    y_gain: np.ndarray            # Ky, n x nx
    y_offset: np.ndarray          # y0, n
    check: np.ndarray             # certificate rows, m x nx
    bound: np.ndarray             # m
    H: np.ndarray                 # objective 1/2 y'Hy + (G x + g0)'y + x'W x
    G: np.ndarray
    g0: np.ndarray
    W: np.ndarray
    inputs: slice                 # u_0 .. u_{N-1} in y
    horizon: int
    nu: int
    initial_state: slice | None = None     # tube MPC: where z_0 sits in y
    feedback: np.ndarray | None = None     # tube MPC: K_tube of u = v_0 + K_tube (x - z_0)
    state_H: np.ndarray | None = None      # the i = 0 state constraint checked before any solve
    state_h: np.ndarray | None = None

    def admits(self, x: np.ndarray) -> bool:
        """True if `CondensedMPC.eval` would reach its explicit law for x (finite, right size,
        i = 0 state constraint met); otherwise the full eval must run (it reports the failure)."""
        if x.shape != (self.check.shape[1],) or not np.all(np.isfinite(x)):
            return False
        return self.state_H is None or not np.any(self.state_H @ x > self.state_h + INITIAL_STATE_TOL)

    def certified_y(self, x: np.ndarray) -> np.ndarray | None:
        """The QP's optimum y if the certificate holds at x (the nominal active set's solution is
        feasible with multipliers of the right signs), else None."""
        y = self.y_gain @ x + self.y_offset
        return y if np.all(self.check @ x <= self.bound) else None

    def input_from(self, y: np.ndarray, x: np.ndarray) -> np.ndarray:
        u = y[self.inputs][:self.nu].copy()
        if self.feedback is not None:
            u = u + self.feedback @ (x - y[self.initial_state])
        return u

    def plan_from(self, y: np.ndarray, x: np.ndarray) -> np.ndarray:
        """The planned inputs u_0 .. u_{N-1} (N x nu): the deadline's shifted-plan fallback. Tube
        MPC: the nominal v_0 .. v_{N-1} with u_0 in place of v_0 (the feedback needs states not
        yet measured)."""
        plan = y[self.inputs].reshape(self.horizon, self.nu)
        if self.feedback is not None:
            plan = plan.copy()
            plan[0] = self.input_from(y, x)
        return plan

    def result(self, y, x, objective, iterations, status, path, start) -> tuple[np.ndarray, dict]:
        """(u, info) of a solved cycle, explicit or iterative."""
        u = self.input_from(y, x)
        elapsed = time.perf_counter() - start
        return u, {
            "ctrl_feas": True,
            "objective": objective + float(x @ self.W @ x),
            "solve_time": elapsed,
            "iterations": iterations,
            "status": status,
            "path": path,
            PLAN_INFO_KEY: self.plan_from(y, x),
        }

    def eval_certified(self, x: np.ndarray, start: float) -> tuple[np.ndarray, dict] | None:
        """(u, info) from the explicit law if its certificate holds at x, else None."""
        y = self.certified_y(x)
        if y is None:
            return None
        objective = float(0.5 * y @ self.H @ y + (self.G @ x + self.g0) @ y)
        return self.result(y, x, objective, 0, "SOLVED", "explicit", start)

    def eval(self, x) -> tuple[np.ndarray, dict] | None:
        """What `CondensedMPC.eval(x)` returns when its explicit law answers, else None (the
        flight process then sends x to the solver worker)."""
        start = time.perf_counter()
        x = np.asarray(x, dtype=float).reshape(-1)
        return self.eval_certified(x, start) if self.admits(x) else None


def two_sided(C: np.ndarray, c0: np.ndarray, D: np.ndarray):
    """Rows C y <= c0 + D x merged with their exact opposites into l <= C y <= u.

    Returns (C, l0, Dl, u0, Du); a row without an opposite gets l = -inf.
    """
    keys = {}
    for i in range(C.shape[0]):
        keys.setdefault((np.concatenate([C[i], D[i]]) + 0.0).tobytes(), []).append(i)   # + 0.0: -0.0 -> 0.0
    used = np.zeros(C.shape[0], dtype=bool)
    rows, l0, dl, u0, du = [], [], [], [], []
    for i in range(C.shape[0]):
        if used[i]:
            continue
        used[i] = True
        rows.append(C[i])
        u0.append(c0[i])
        du.append(D[i])
        partners = [j for j in keys.get((-np.concatenate([C[i], D[i]]) + 0.0).tobytes(), []) if not used[j]]
        if partners:
            j = partners[0]
            used[j] = True
            l0.append(-c0[j])
            dl.append(-D[j])
        else:
            l0.append(-np.inf)
            dl.append(np.zeros(D.shape[1]))
    return np.array(rows), np.array(l0), np.array(dl), np.array(u0), np.array(du)


def prediction_matrices(a: np.ndarray, b: np.ndarray, horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """(Phi, Gamma) with [x_0; ...; x_N] = Phi x_0 + Gamma [u_0; ...; u_{N-1}]."""
    nx, nu = b.shape
    phi = np.empty(((horizon + 1) * nx, nx))
    gamma = np.zeros(((horizon + 1) * nx, horizon * nu))
    power = np.eye(nx)
    for i in range(horizon + 1):
        phi[i * nx:(i + 1) * nx] = power
        power = a @ power
    for i in range(1, horizon + 1):
        for j in range(i):
            gamma[i * nx:(i + 1) * nx, j * nu:(j + 1) * nu] = phi[(i - 1 - j) * nx:(i - j) * nx] @ b
    return phi, gamma


def box_bounds(H: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) of an axis-aligned polytope H u <= h; ValueError if H is not a box."""
    n = H.shape[1]
    lower, upper = np.full(n, -np.inf), np.full(n, np.inf)
    for row, bound in zip(H, h):
        nz = np.flatnonzero(row)
        if nz.size != 1:
            raise ValueError("input constraints must be a box (each row of H_u on one input)")
        i, coef = nz[0], row[nz[0]]
        if coef > 0:
            upper[i] = min(upper[i], bound / coef)
        else:
            lower[i] = max(lower[i], bound / coef)
    if np.any(lower > upper):
        raise ValueError("input constraints are empty (a lower bound exceeds an upper bound)")
    return lower, upper


def condensed_qp(model, Q: np.ndarray, R: np.ndarray, horizon: int, *,
                 terminal_cost: np.ndarray | None = None,
                 terminal_equality: bool = False,
                 terminal_set: Polytope | None = None,
                 soft: SoftStatePenalty | None = None,
                 tube: Polytope | None = None) -> CondensedQP:
    """The condensed QP of seed 003 problem (17), (18), (19), (20) or (23), by options.

    terminal_cost: P of l_f(x) = x'Px. terminal_equality: x_N = 0. terminal_set: x_N in {H x <= h}.
    soft: state constraints H_x x_i <= h_x + eps_i, eps_i >= 0, penalised. tube: the first
    predicted state z_0 is a decision variable with x - z_0 in the tube (23b); constraints then
    also hold at i = 0, and the model passed in must carry the tightened constraints.
    Without a tube the i = 0 state constraint does not depend on the decision and is checked by
    the controller before solving.
    """
    nx, nu, N = model.nx, model.nu, horizon
    a, b = model.A, model.B
    H_x, h_x = model.H_x, model.h_x
    n_hx = H_x.shape[0]
    phi, gamma = prediction_matrices(a, b, N)

    # Decision vector y = [z_0 (tube)] [u_0..u_{N-1}] [eps_0..eps_N (soft)] [t_0..t_N (soft)].
    n_z0 = nx if tube is not None else 0
    n_u = N * nu
    n_eps = (N + 1) * n_hx if soft is not None else 0
    n_t = (N + 1) if soft is not None else 0
    n = n_z0 + n_u + n_eps + n_t
    sl_z0 = slice(0, n_z0)
    sl_u = slice(n_z0, n_z0 + n_u)
    sl_eps = slice(sl_u.stop, sl_u.stop + n_eps)
    sl_t = slice(sl_eps.stop, n)

    # Predicted states X = My y + Mx x.
    My = np.zeros(((N + 1) * nx, n))
    My[:, sl_u] = gamma
    if tube is not None:
        My[:, sl_z0] = phi
        Mx = np.zeros(((N + 1) * nx, nx))
    else:
        Mx = phi

    # Cost: X' Qbar X + U' Rbar U + slack terms; proxsuite minimises 1/2 y'Hy + g'y.
    q_bar = block_diag(*([Q] * N), terminal_cost if terminal_cost is not None else np.zeros((nx, nx)))
    Hess = 2.0 * My.T @ q_bar @ My
    Hess[sl_u, sl_u] += 2.0 * np.kron(np.eye(N), R)
    g0 = np.zeros(n)
    if soft is not None:
        Hess[sl_eps, sl_eps] += 2.0 * np.kron(np.eye(N + 1), soft.S)
        g0[sl_t] = soft.v
    G = 2.0 * My.T @ q_bar @ Mx
    W = Mx.T @ q_bar @ Mx

    rows_C, rows_c0, rows_D = [], [], []

    def add_rows(c, c0, d):
        rows_C.append(c)
        rows_c0.append(c0)
        rows_D.append(d)

    # State constraints (17d): hard for i >= 1 (i = 0 with a tube), soft for all i.
    first = 0 if (tube is not None or soft is not None) else 1
    for i in range(first, N + 1):
        xi = slice(i * nx, (i + 1) * nx)
        c = H_x @ My[xi]
        if soft is not None:
            c[:, sl_eps.start + i * n_hx: sl_eps.start + (i + 1) * n_hx] = -np.eye(n_hx)
        add_rows(c, h_x.copy(), -H_x @ Mx[xi])
    # ||eps_i||_inf <= t_i, as eps_ij - t_i <= 0 (eps >= 0 is a box bound).
    if soft is not None:
        c = np.zeros((n_eps, n))
        c[:, sl_eps] = np.eye(n_eps)
        c[:, sl_t] = -np.kron(np.eye(N + 1), np.ones((n_hx, 1)))
        add_rows(c, np.zeros(n_eps), np.zeros((n_eps, nx)))
    xN = slice(N * nx, (N + 1) * nx)
    if terminal_set is not None:
        add_rows(terminal_set.H @ My[xN], terminal_set.h.copy(), -terminal_set.H @ Mx[xN])
    # Tube (23b): H_E (x - z_0) <= h_E  <=>  -H_E z_0 <= h_E - H_E x.
    if tube is not None:
        c = np.zeros((tube.H.shape[0], n))
        c[:, sl_z0] = -tube.H
        add_rows(c, tube.h.copy(), -tube.H)

    A_eq = E_eq = None
    if terminal_equality:
        A_eq = My[xN].copy()
        E_eq = -Mx[xN]

    l_box, u_box = np.full(n, -np.inf), np.full(n, np.inf)
    u_lo, u_hi = box_bounds(model.H_u, model.h_u)
    l_box[sl_u], u_box[sl_u] = np.tile(u_lo, N), np.tile(u_hi, N)
    l_box[sl_eps] = 0.0
    l_box[sl_t] = 0.0

    if rows_C:
        C, l0, Dl, u0, Du = two_sided(np.vstack(rows_C), np.concatenate(rows_c0), np.vstack(rows_D))
    else:
        C, l0, Dl, u0, Du = None, np.zeros(0), np.zeros((0, nx)), np.zeros(0), np.zeros((0, nx))
    return CondensedQP(H=0.5 * (Hess + Hess.T), G=G, g0=g0, W=W, A=A_eq, E=E_eq, C=C,
                       l0=l0, Dl=Dl, u0=u0, Du=Du, l_box=l_box, u_box=u_box, inputs=sl_u,
                       initial_state=sl_z0 if tube is not None else None,
                       slacks=slice(sl_eps.start, n) if soft is not None else None)


def check_horizon(horizon) -> int:
    if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)) or horizon < 1:
        raise ValueError(f"MPC horizon must be an integer >= 1, got {horizon!r}")
    return int(horizon)


def check_model(model) -> None:
    nx, nu = model.A.shape[0], model.B.shape[1]
    problems = []
    if model.A.shape != (nx, nx):
        problems.append(f"A must be square, got {model.A.shape}")
    if model.B.shape[0] != nx:
        problems.append(f"B has {model.B.shape[0]} rows, A has {nx}")
    if model.H_x.shape[1] != nx or model.h_x.shape != (model.H_x.shape[0],):
        problems.append(f"H_x {model.H_x.shape} / h_x {model.h_x.shape} do not fit {nx} states")
    if model.H_u.shape[1] != nu or model.h_u.shape != (model.H_u.shape[0],):
        problems.append(f"H_u {model.H_u.shape} / h_u {model.h_u.shape} do not fit {nu} inputs")
    if problems:
        raise ValueError("inconsistent model dimensions: " + "; ".join(problems))


def check_polytope(name: str, poly: Polytope, nx: int) -> None:
    if poly.H.shape[1] != nx:
        raise ValueError(f"{name} has {poly.H.shape[1]} columns, the state has {nx}")


class CondensedMPC:
    """An MPC controller on one condensed QP; `eval(x) -> (u, info)` as every bench controller.

    When the QP is not solved (infeasible, iteration limit) `eval` does not raise: info says
    ctrl_feas False with the solver status, and u is the safe action: the LQR input of (Q, R)
    clipped to the input box.
    """

    def __init__(self, Q, R, horizon, model, solver_options: dict | None = None, **formulation):
        check_model(model)
        self.horizon = check_horizon(horizon)
        self.Q, self.R = check_weights(Q, R, model.nx, model.nu)
        self.model = model
        self.K_lqr, self.P = dlqr(model.A, model.B, self.Q, self.R)
        self._u_lo, self._u_hi = box_bounds(model.H_u, model.h_u)
        self.qp_data = condensed_qp(model, self.Q, self.R, self.horizon, **formulation)
        d = self.qp_data
        # The nominal active set also starts the solver's exact fallback when it has no last one.
        self.solver = DenseBoxQP(d.H, d.A, d.C, d.l_box, d.u_box, start_active=self._nominal_active_set(),
                                 **(solver_options or {}))
        # g, b, l, u are all affine in x: one stacked product per cycle.
        n_eq = 0 if d.A is None else d.A.shape[0]
        self._vector_map = np.vstack([d.G, d.E if d.E is not None else np.zeros((0, model.nx)), d.Dl, d.Du])
        self._vector_offset = np.concatenate([d.g0, np.zeros(n_eq), d.l0, d.u0])
        n_g = d.G.shape[0]
        self._splits = (n_g, n_g + n_eq, n_g + n_eq + d.l0.size)
        self._check_initial_state = d.initial_state is None and formulation.get("soft") is None
        self.last_solution: QPSolution | None = None
        self._build_explicit_law()

    def safe_action(self, x: np.ndarray) -> np.ndarray:
        return np.clip(self.K_lqr @ x, self._u_lo, self._u_hi)

    def _tube_feedback(self) -> np.ndarray | None:
        """K_tube of u = v_0 + K_tube (x - z_0) (tube MPC); None: u = u_0."""
        return None

    def explicit_path(self) -> ExplicitPath:
        """The explicit law as a picklable object (the solver worker sends it to the flight process)."""
        return self._explicit

    def eval(self, x) -> tuple[np.ndarray, dict]:
        start = time.perf_counter()
        x = np.asarray(x, dtype=float).reshape(-1)
        if x.shape != (self.model.nx,):
            raise ValueError(f"state must have {self.model.nx} entries, got {x.size}")
        if not np.all(np.isfinite(x)):
            return self._failed(np.zeros(self.model.nu), "NON_FINITE_STATE", 0, start)
        if self._check_initial_state and np.any(self.model.H_x @ x > self.model.h_x + INITIAL_STATE_TOL):
            return self._failed(self.safe_action(x), "INITIAL_STATE_VIOLATES_CONSTRAINTS", 0, start)
        # The explicit law first; no solver state (warm start, last active set) is read or written
        # on this path, so skipping it in the worker (the flight process answers) changes nothing.
        out = self._explicit.eval_certified(x, start)
        if out is not None:
            return out
        vectors = self._vector_map @ x + self._vector_offset
        i_b, i_l, i_u = self._splits
        sol = self.solver.solve(vectors[:i_b], vectors[i_b:i_l], vectors[i_l:i_u], vectors[i_u:])
        self.last_solution = sol
        if not sol.solved:
            return self._failed(self.safe_action(x), sol.status, sol.iterations, start, sol.path)
        return self._explicit.result(sol.y, x, sol.objective, sol.iterations, sol.status, sol.path, start)

    def _input_from(self, y: np.ndarray, x: np.ndarray) -> np.ndarray:
        return self._explicit.input_from(y, x)

    def _plan_from(self, y: np.ndarray, x: np.ndarray) -> np.ndarray:
        return self._explicit.plan_from(y, x)

    def _nominal_active_set(self) -> ActiveSet:
        d = self.qp_data
        active = ActiveSet.empty(0 if d.C is None else d.C.shape[0], d.H.shape[0])
        if d.slacks is not None:
            active.box_lower[d.slacks] = True          # eps = 0, t = 0: no constraint softened
        return active

    def _build_explicit_law(self) -> None:
        """y(x) = Ky x + y0 on the nominal active set, and its KKT certificate as rows
        check x <= bound: both affine in x, so evaluated exactly at x = 0 and x = e_i."""
        d, nx = self.qp_data, self.model.nx
        active = self._nominal_active_set()
        i_b, i_l, i_u = self._splits

        def terms(x):
            v = self._vector_map @ x + self._vector_offset
            g, b, l, u = v[:i_b], v[i_b:i_l], v[i_l:i_u], v[i_u:]
            p = self.solver.kkt.solve_on_active_set(g, b, l, u, active)
            if p is None:
                raise ValueError("the MPC's nominal active set has a singular KKT matrix")
            cy = (d.C @ p.y) if d.C is not None else np.zeros(0)
            # every row must be <= 0 for the certificate
            rows = np.concatenate([cy - u, l - cy, p.y - d.u_box, d.l_box - p.y,
                                   p.z_box[active.box_lower]])
            return p.y, rows

        y0, r0 = terms(np.zeros(nx))
        cols = [terms(e) for e in np.eye(nx)]
        finite = np.isfinite(r0)                # rows against an infinite bound never bind
        check = np.column_stack([c[1][finite] - r0[finite] for c in cols])
        self._explicit = ExplicitPath(
            y_gain=np.column_stack([c[0] - y0 for c in cols]), y_offset=y0,
            check=check, bound=-r0[finite] + PRIMAL_TOL * (1.0 + np.abs(r0[finite])),
            H=d.H, G=d.G, g0=d.g0, W=d.W, inputs=d.inputs, horizon=self.horizon, nu=self.model.nu,
            initial_state=d.initial_state, feedback=self._tube_feedback(),
            state_H=self.model.H_x if self._check_initial_state else None,
            state_h=self.model.h_x if self._check_initial_state else None)

    def _failed(self, u, status, iterations, start, path: str | None = None) -> tuple[np.ndarray, dict]:
        info = {
            "ctrl_feas": False,
            "objective": float("nan"),
            "solve_time": time.perf_counter() - start,
            "iterations": iterations,
            "status": status,
        }
        if path is not None:
            info["path"] = path      # how the solver failed (bench.gnc.qp.QPSolution.path)
        return u, info


class MPC(CondensedMPC):
    """Problem (17): LQR terminal cost l_f(x) = x'Px, no terminal constraint."""

    def __init__(self, Q, R, horizon, model):
        Q, R = check_weights(Q, R, model.nx, model.nu)
        _, P = dlqr(model.A, model.B, Q, R)
        super().__init__(Q, R, horizon, model, terminal_cost=P)


class MPC_TE(CondensedMPC):
    """Problem (18): terminal equality x_N = 0, no terminal cost."""

    def __init__(self, Q, R, horizon, model):
        super().__init__(Q, R, horizon, model, terminal_equality=True)


class MPC_TS(CondensedMPC):
    """Problem (19): LQR terminal cost and terminal set x_N in {H x <= h} (X_LQR of lqr_max_pi)."""

    def __init__(self, Q, R, horizon, terminal_set: Polytope, model):
        check_polytope("terminal set", terminal_set, model.nx)
        Q, R = check_weights(Q, R, model.nx, model.nu)
        _, P = dlqr(model.A, model.B, Q, R)
        super().__init__(Q, R, horizon, model, terminal_cost=P, terminal_set=terminal_set)


class MPC_TS_SC(CondensedMPC):
    """Problem (20): MPC_TS with soft state constraints, slack cost eps'S eps + v ||eps||_inf."""

    def __init__(self, Q, R, horizon, terminal_set: Polytope, S, v: float, model):
        check_polytope("terminal set", terminal_set, model.nx)
        n_hx = model.H_x.shape[0]
        S = np.atleast_2d(np.asarray(S, dtype=float))
        if S.shape != (n_hx, n_hx):
            raise ValueError(f"S must be {n_hx}x{n_hx} (one slack per state constraint row), got {S.shape}")
        if not np.allclose(S, S.T) or np.linalg.eigvalsh(S).min() <= 0:
            raise ValueError("S must be symmetric positive definite")
        if not (np.isfinite(v) and v >= 0):
            raise ValueError(f"v must be a finite non-negative number, got {v!r}")
        Q, R = check_weights(Q, R, model.nx, model.nu)
        _, P = dlqr(model.A, model.B, Q, R)
        super().__init__(Q, R, horizon, model, terminal_cost=P, terminal_set=terminal_set,
                         soft=SoftStatePenalty(S=S, v=float(v)))
