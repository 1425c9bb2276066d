"""Build the controller a scenario's [controller] section asks for.

The controller process calls `build_controller(cfg, params)`; the returned object has
`eval(x_scaled) -> (u_N, info)`: scaled state (Mm, km/s) in, thrust in N out (seed 003 units).
"""
from __future__ import annotations

import time

import numpy as np

from bench.config.controller import ControllerConfig
from bench.gnc.cwh import RendezvousParams, Z_INPUTS, Z_STATES, z_subsystem
from bench.gnc.lqr import LQR, dlqr
from bench.gnc.lqt import TrackingLQT
from bench.gnc.mpc import MPC, MPC_TE, MPC_TS, MPC_TS_SC
from bench.gnc.sets import lqr_max_pi
from bench.gnc.tube import design_tube_mpc

IN_PLANE_STATES = (0, 1, 3, 4)
IN_PLANE_INPUTS = (0, 1)


def weights_from_config(cfg: ControllerConfig) -> tuple[np.ndarray, np.ndarray]:
    """(Q, R) = (diag(q_diag), diag(r_diag)) on the scaled state."""
    q, r = np.asarray(cfg.q_diag, dtype=float), np.asarray(cfg.r_diag, dtype=float)
    if q.size != 6 or r.size != 3:
        raise ValueError(f"controller: q_diag needs 6 weights and r_diag 3, got {q.size} and {r.size}")
    return np.diag(q), np.diag(r)


def terminal_set(Q, R, model):
    """X_LQR of the LQR closed loop with (Q, R) on `model` (seed task 13)."""
    k, _ = dlqr(model.A, model.B, Q, R)
    return lqr_max_pi(k, model.A, model.B, model.H_x, model.h_x, model.H_u, model.h_u)


def build_controller(cfg: ControllerConfig, params: RendezvousParams):
    """A controller object for `cfg` on the scaled CWH model of `params`."""
    Q, R = weights_from_config(cfg)
    model = params.scaled
    if cfg.type == "lqr":
        return LQR(Q, R, model.A, model.B)
    if cfg.type == "lqt":
        _, p_inf = dlqr(model.A, model.B, Q, R)
        # Reference velocities per step -> the scaled velocity unit (km/s from Mm per step).
        velocity_per_step = model.scaling[3] / model.scaling[0] / params.time_step_s
        return TrackingLQT(Q, R, p_inf, model.A, model.B, params.n_steps, cfg.lqt_glide_fraction, velocity_per_step)
    if cfg.type == "mpc":
        return MPC(Q, R, cfg.horizon, model)
    if cfg.type == "mpc_te":
        return MPC_TE(Q, R, cfg.horizon, model)
    if cfg.type == "mpc_ts":
        return MPC_TS(Q, R, cfg.horizon, terminal_set(Q, R, model), model)
    if cfg.type == "mpc_ts_sc":
        S = cfg.soft_quadratic_weight * np.eye(model.H_x.shape[0])
        return MPC_TS_SC(Q, R, cfg.horizon, terminal_set(Q, R, model), S, cfg.soft_linf_weight, model)
    if cfg.type == "mpc_tube":
        return SplitController(params, Q, R, cfg)
    raise ValueError(f"controller.type: unknown controller type {cfg.type!r}")


class SplitController:
    """Tube MPC on [z, vz] and MPC (17) on the decoupled in-plane states: the seed's tube task is
    posed on the out-of-plane subsystem only, and the two CWH subsystems do not interact."""

    def __init__(self, params: RendezvousParams, Q, R, cfg: ControllerConfig):
        model = params.scaled
        in_plane = _project(model, IN_PLANE_STATES, IN_PLANE_INPUTS)
        zs, zu = list(Z_STATES), list(Z_INPUTS)
        self.in_plane = MPC(Q[np.ix_(IN_PLANE_STATES, IN_PLANE_STATES)], R[np.ix_(IN_PLANE_INPUTS, IN_PLANE_INPUTS)],
                            cfg.horizon, in_plane)
        self.out_of_plane = design_tube_mpc(np.diag(Q)[zs], float(R[zu[0], zu[0]]), cfg.tube_horizon,
                                            cfg.tube_poles, z_subsystem(params))

    def eval(self, x):
        start = time.perf_counter()
        x = np.asarray(x, dtype=float)
        u_in, info_in = self.in_plane.eval(x[list(IN_PLANE_STATES)])
        u_z, info_z = self.out_of_plane.eval(x[list(Z_STATES)])
        u = np.empty(3)
        u[list(IN_PLANE_INPUTS)] = u_in
        u[list(Z_INPUTS)] = u_z
        plan = None
        if "u_plan" in info_in and "u_plan" in info_z:      # both solved: the joint plan, shortest horizon
            rows = min(len(info_in["u_plan"]), len(info_z["u_plan"]))
            plan = np.empty((rows, 3))
            plan[:, list(IN_PLANE_INPUTS)] = info_in["u_plan"][:rows]
            plan[:, list(Z_INPUTS)] = info_z["u_plan"][:rows]
        return u, {
            **({"u_plan": plan} if plan is not None else {}),
            "ctrl_feas": info_in["ctrl_feas"] and info_z["ctrl_feas"],
            "objective": info_in["objective"] + info_z["objective"],
            "solve_time": time.perf_counter() - start,
            "iterations": info_in["iterations"] + info_z["iterations"],
            "status": f"in-plane {info_in['status']}, out-of-plane {info_z['status']}",
        }


def _project(model, states, inputs):
    """The scaled model restricted to decoupled `states` and `inputs` (constraint rows on them)."""
    import dataclasses

    s, u = list(states), list(inputs)
    h_x_mat = model.H_x[:, s]
    keep_x = np.any(h_x_mat != 0, axis=1)
    h_u_mat = model.H_u[:, u]
    keep_u = np.any(h_u_mat != 0, axis=1)
    return dataclasses.replace(model, A=model.A[np.ix_(s, s)], B=model.B[np.ix_(s, u)],
                               H_x=h_x_mat[keep_x], h_x=model.h_x[keep_x], H_u=h_u_mat[keep_u],
                               h_u=model.h_u[keep_u], scaling=model.scaling[s])
