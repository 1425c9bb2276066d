"""An independent MPC solve for the tests: the seed's problems in their sparse (state-space) form
on quadprog, with states as decision variables. Shares nothing with bench.gnc.mpc but the
model, so a condensing error there shows up as a different first input here."""
from __future__ import annotations

import numpy as np
import quadprog


def reference_mpc_solution(model, Q, R, N, x0, *, P=None, terminal_equality=False, terminal_set=None,
                           soft=None, tube=None):
    """(u_0 or v_0, z_0 or None, objective, status) of problem (17)-(20) or (23) from x0.

    Variables: [x_0..x_N, u_0..u_{N-1}, eps_0..eps_N, t_0..t_N]. For a tube, x_0 is free and
    H_E (x0 - x_0) <= h_E; otherwise x_0 = x0.
    """
    nx, nu = model.nx, model.nu
    n_hx = model.H_x.shape[0]
    n_x_all, n_u_all = (N + 1) * nx, N * nu
    n_eps = (N + 1) * n_hx if soft is not None else 0
    n_t = (N + 1) if soft is not None else 0
    n = n_x_all + n_u_all + n_eps + n_t
    ix = lambda i: slice(i * nx, (i + 1) * nx)
    iu = lambda i: slice(n_x_all + i * nu, n_x_all + (i + 1) * nu)
    ie = lambda i: slice(n_x_all + n_u_all + i * n_hx, n_x_all + n_u_all + (i + 1) * n_hx)
    it = lambda i: n_x_all + n_u_all + n_eps + i

    Pm = np.zeros((n, n))
    q = np.zeros(n)
    for i in range(N):
        Pm[ix(i), ix(i)] = 2 * Q
        Pm[iu(i), iu(i)] = 2 * R
    if P is not None:
        Pm[ix(N), ix(N)] = 2 * P
    if soft is not None:
        S, v = soft
        for i in range(N + 1):
            Pm[ie(i), ie(i)] = 2 * S
            q[it(i)] = v

    rows, lo, hi = [], [], []

    def add(a, l, u):
        rows.append(np.atleast_2d(a))
        lo.extend(np.atleast_1d(l))
        hi.extend(np.atleast_1d(u))

    for i in range(N):                          # dynamics
        a = np.zeros((nx, n))
        a[:, ix(i + 1)] = -np.eye(nx)
        a[:, ix(i)] = model.A
        a[:, iu(i)] = model.B
        add(a, np.zeros(nx), np.zeros(nx))
    if tube is None:                            # x_0 = x0
        a = np.zeros((nx, n))
        a[:, ix(0)] = np.eye(nx)
        add(a, x0, x0)
    else:                                       # H_E (x0 - x_0) <= h_E
        a = np.zeros((tube.H.shape[0], n))
        a[:, ix(0)] = -tube.H
        add(a, -np.inf * np.ones(tube.H.shape[0]), tube.h - tube.H @ x0)
    for i in range(N + 1):                      # state constraints
        a = np.zeros((n_hx, n))
        a[:, ix(i)] = model.H_x
        if soft is not None:
            a[:, ie(i)] = -np.eye(n_hx)
        elif tube is None and i == 0:
            continue
        add(a, -np.inf * np.ones(n_hx), model.h_x)
        if soft is not None:
            e = np.zeros((n_hx, n))
            e[:, ie(i)] = np.eye(n_hx)
            add(e, np.zeros(n_hx), np.full(n_hx, np.inf))
            e = np.zeros((n_hx, n))
            e[:, ie(i)] = np.eye(n_hx)
            e[:, it(i)] = -1.0
            add(e, -np.inf * np.ones(n_hx), np.zeros(n_hx))
    for i in range(N):                          # input constraints
        a = np.zeros((model.H_u.shape[0], n))
        a[:, iu(i)] = model.H_u
        add(a, -np.inf * np.ones(model.H_u.shape[0]), model.h_u)
    if terminal_equality:
        a = np.zeros((nx, n))
        a[:, ix(N)] = np.eye(nx)
        add(a, np.zeros(nx), np.zeros(nx))
    if terminal_set is not None:
        a = np.zeros((terminal_set.H.shape[0], n))
        a[:, ix(N)] = terminal_set.H
        add(a, -np.inf * np.ones(terminal_set.H.shape[0]), terminal_set.h)

    # quadprog (Goldfarb-Idnani dual active set) solves to machine precision; it needs a
    # positive definite Hessian, so the blocks without cost (x_N under MPC_TE, the t_i) get 1e-9.
    A = np.vstack(rows)
    lo, hi = np.array(lo), np.array(hi)
    eq = lo == hi
    lower = ~eq & np.isfinite(lo)
    upper = ~eq & np.isfinite(hi)
    C = np.vstack([A[eq], A[lower], -A[upper]])
    b = np.concatenate([lo[eq], lo[lower], -hi[upper]])
    G = Pm + 1e-9 * np.eye(n)
    try:
        y, obj = quadprog.solve_qp(G, -q, C.T, b, int(eq.sum()))[:2]
    except ValueError as exc:                   # "constraints are inconsistent, no solution"
        return None, None, np.nan, f"infeasible: {exc}"
    objective = float(0.5 * y @ Pm @ y + q @ y)
    return y[iu(0)], (y[ix(0)] if tube is not None else None), objective, "solved"


def reference_condensed_solution(qp, x0):
    """(y, objective without the constant x'Wx) of a bench.gnc.mpc.CondensedQP at state x0 on
    quadprog, or (None, nan) if quadprog finds it infeasible. The same QP as the controller's (not
    its formulation's independent check: that is reference_mpc_solution), fast enough for hundreds
    of states; y, not just u_0, so the tube's input v_0 + K (x - z_0) can be formed."""
    x0 = np.asarray(x0, float)
    n = qp.H.shape[0]
    g = qp.G @ x0 + qp.g0
    lo, hi = qp.l0 + qp.Dl @ x0, qp.u0 + qp.Du @ x0
    rows, rhs, n_eq = [], [], 0
    if qp.A is not None:
        rows.append(qp.A)
        rhs.append(qp.E @ x0)
        n_eq = qp.A.shape[0]
    if qp.C is not None:
        fl, fu = np.isfinite(lo), np.isfinite(hi)
        rows += [qp.C[fl], -qp.C[fu]]
        rhs += [lo[fl], -hi[fu]]
    eye = np.eye(n)
    fl, fu = np.isfinite(qp.l_box), np.isfinite(qp.u_box)
    rows += [eye[fl], -eye[fu]]
    rhs += [qp.l_box[fl], -qp.u_box[fu]]
    # quadprog needs H > 0: variables without curvature (soft constraints' t_i) get 1e-9.
    H = qp.H + 1e-9 * np.diag(np.diag(qp.H) == 0)
    try:
        y = quadprog.solve_qp(H, -g, np.vstack(rows).T, np.concatenate(rhs), n_eq)[0]
    except ValueError:                          # "constraints are inconsistent, no solution"
        return None, np.nan
    return y, float(0.5 * y @ qp.H @ y + g @ y)
