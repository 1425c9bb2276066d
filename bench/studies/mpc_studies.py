"""Seed 003's MPC simulation studies, on the discrete CWH model, inputs unsaturated (as `simulate`).

- `horizon_study` (task 21): MPC (17), MPC_TE (18), MPC_TS (19) from A with Q*, R*, N = 40 .. 20:
  infeasible QPs, closed-loop constraint satisfaction, closed-loop cost.
- `soft_constraint_study` (task 24): MPC_TS_SC (20) from C for several S = s I and v.
- `tube_study` (task 32): tube MPC against MPC_TS on the z-subsystem, N = 50, under sampled
  disturbance sequences and under the constant worst case w = [w_max, w_max].

Each returns rows of plain dicts for a table (`bench mpc-studies` prints them).
"""
from __future__ import annotations

import numpy as np

from bench.gnc.lqr import dlqr
from bench.studies.metrics import traj_constraints, traj_cost
from bench.gnc.mpc import MPC, MPC_TE, MPC_TS, MPC_TS_SC
from bench.gnc.sets import lqr_max_pi
from bench.studies.simulate import simulate, simulate_uncertain
from bench.gnc.tube import design_tube_mpc, generate_disturbances
from bench.gnc.cwh import RendezvousParams, z_subsystem

Q_STAR = np.diag([94.0, 0.1579, 300.0, 0.01, 0.10, 0.10])
R_STAR = np.eye(3)


def _terminal_set(model, Q, R):
    k, _ = dlqr(model.A, model.B, Q, R)
    return lqr_max_pi(k, model.A, model.B, model.H_x, model.h_x, model.H_u, model.h_u)


def _closed_loop_row(name, ctrl, x0, params, Q, R, **extra) -> dict:
    model = params.scaled
    X, U, infos = simulate(x0, ctrl, model, params.n_steps)
    m = traj_constraints(X, U, params)
    return {**extra, "controller": name, "infeasible QPs": sum(not i["ctrl_feas"] for i in infos),
            "feasible": m.feasible, "s_max m": m.max_abs_position_xz_m, "y_max m": m.max_abs_position_y_m,
            "u_max N": m.max_abs_thrust_n, "J_u N^2": m.input_cost_n2, "J (x'Qx+u'Ru)": traj_cost(X, U, Q, R),
            "d_f m": m.final_distance_m, "v_f m/s": m.final_speed_mps}


def horizon_study(horizons=range(40, 19, -2), initial_condition="A", progress=None) -> list[dict]:
    params = RendezvousParams.from_reference()
    model = params.scaled
    x0 = model.to_scaled(params.initial_state_m_mps(initial_condition))
    terminal = _terminal_set(model, Q_STAR, R_STAR)
    rows = []
    for n in horizons:
        for name, ctrl in [("MPC", MPC(Q_STAR, R_STAR, n, model)), ("MPC_TE", MPC_TE(Q_STAR, R_STAR, n, model)),
                           ("MPC_TS", MPC_TS(Q_STAR, R_STAR, n, terminal, model))]:
            rows.append(_closed_loop_row(name, ctrl, x0, params, Q_STAR, R_STAR, N=n))
            if progress:
                progress(1)
    return rows


def soft_constraint_study(s_values=(1.0, 1e3, 1e6), v_values=(0.0, 1e3, 1e5), horizon=30,
                          initial_condition="C", progress=None) -> list[dict]:
    params = RendezvousParams.from_reference()
    model = params.scaled
    x0 = model.to_scaled(params.initial_state_m_mps(initial_condition))
    terminal = _terminal_set(model, Q_STAR, R_STAR)
    rows = []
    for s in s_values:
        for v in v_values:
            ctrl = MPC_TS_SC(Q_STAR, R_STAR, horizon, terminal, s * np.eye(model.H_x.shape[0]), v, model)
            rows.append(_closed_loop_row("MPC_TS_SC", ctrl, x0, params, Q_STAR, R_STAR, S=f"{s:g} I", v=v))
            if progress:
                progress(1)
    return rows


def tube_study(n_sequences=20, n_steps=None, seed=0, q_z=(300.0, 0.1), r_z=1.0, horizon=50, poles=(0.05, 0.1),
               progress=None) -> list[dict]:
    """Tube MPC (task 31) and MPC_TS on params_z (task 20's controller on the z-subsystem, N = 50)
    from x_z0^A, under the same disturbance sequences."""
    params = RendezvousParams.from_reference()
    mz = z_subsystem(params)
    n_steps = int(mz.n_steps if n_steps is None else n_steps)
    Q, R = np.diag(q_z), np.atleast_2d(r_z)
    rng = np.random.default_rng(seed)
    cases = [("sampled", generate_disturbances(mz, n_steps, rng)) for _ in range(n_sequences)]
    cases.append(("worst case w = [w_max, w_max]", np.full((2, n_steps), mz.max_abs_disturbance)))
    z_max = float(mz.h_x[0] / np.max(np.abs(mz.H_x[0])))
    u_max = float(mz.h_u[0] / np.max(np.abs(mz.H_u[0])))
    stats = {}
    # One controller of each for all sequences: warm starts carry over, and every solution is
    # certified by the KKT conditions, so that changes the time, not the inputs.
    tube = design_tube_mpc(list(q_z), r_z, horizon, list(poles), mz)
    ts = MPC_TS(Q, R, horizon, _terminal_set(mz, Q, R), mz)
    for label, w in cases:
        for name, ctrl in [("MPC_TUBE", tube), ("MPC_TS", ts)]:
            X, U, infos = simulate_uncertain(mz.initial_state_a, ctrl, w, mz)
            key = (label, name)
            st = stats.setdefault(key, {"runs": 0, "infeasible QPs": 0, "runs with a state violation": 0,
                                        "runs with an input violation": 0, "max abs z / z_max": 0.0,
                                        "max abs u / u_max": 0.0, "J_u": [], "abs z final km": []})
            z_ratio = float(np.max(np.abs(X[0])) / z_max)
            u_ratio = float(np.max(np.abs(U)) / u_max)
            st["runs"] += 1
            st["infeasible QPs"] += sum(not i["ctrl_feas"] for i in infos)
            st["runs with a state violation"] += z_ratio > 1 + 1e-9
            st["runs with an input violation"] += u_ratio > 1 + 1e-6
            st["max abs z / z_max"] = max(st["max abs z / z_max"], z_ratio)
            st["max abs u / u_max"] = max(st["max abs u / u_max"], u_ratio)
            st["J_u"].append(float(np.sum(U * U)))
            st["abs z final km"].append(float(abs(X[0, -1]) * 1e3))
        if progress:
            progress(1)
    rows = []
    for (label, name), st in stats.items():
        rows.append({"disturbance": label, "controller": name, "runs": st["runs"],
                     "infeasible QPs": st["infeasible QPs"],
                     "runs with a state violation": st["runs with a state violation"],
                     "runs with an input violation": st["runs with an input violation"],
                     "max abs z / z_max": st["max abs z / z_max"], "max abs u / u_max": st["max abs u / u_max"],
                     "mean J_u N^2": float(np.mean(st["J_u"])), "mean abs z final km": float(np.mean(st["abs z final km"]))})
    return rows
