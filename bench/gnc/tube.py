"""Tube MPC of seed 003 (problem 23, tasks 25 to 31) on the out-of-plane subsystem [z, vz].

The nominal system z+ = A z + B v is steered by an MPC on constraints tightened by the tube E
(a robust positively invariant set of the error x - z under u = v + K_tube (x - z)); the applied
input is u = v_0* + K_tube (x - z_0*) (eq. 24).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from bench.gnc.lqr import dlqr
from bench.gnc.mpc import CondensedMPC, box_bounds, check_polytope
from bench.gnc.sets import Polytope, min_robust_positively_invariant, pontryagin_difference, support
from bench.gnc.weights import check_weights


def disturbance_set(model) -> Polytope:
    return Polytope(np.asarray(model.H_w, float), np.asarray(model.h_w, float))


def generate_disturbances(model, n_steps: int | None = None, rng: np.random.Generator | None = None) -> np.ndarray:
    """W_t (nx x N_t): disturbances drawn uniformly on {w | H_w w <= h_w} (seed task 25).

    Rejection sampling from the set's bounding box, which is exact for the seed's box.
    """
    rng = rng if rng is not None else np.random.default_rng()
    n_steps = int(model.n_steps if n_steps is None else n_steps)
    w_set = disturbance_set(model)
    eye = np.eye(model.nx)
    hi, lo = support(w_set, eye), -support(w_set, -eye)
    out = np.empty((model.nx, 0))
    while out.shape[1] < n_steps:
        draw = rng.uniform(lo, hi, size=(2 * n_steps, model.nx))
        out = np.hstack([out, draw[w_set.contains(draw)].T])
    return out[:, :n_steps]


def compute_tube_controller(poles, model) -> np.ndarray:
    """K_tube (nu x nx) placing the eigenvalues of A + B K_tube at `poles` (seed task 27)."""
    poles = np.asarray(poles)
    if poles.shape != (model.nx,):
        raise ValueError(f"need {model.nx} poles, got {poles.size}")
    if np.any(np.abs(poles) >= 1):
        raise ValueError(f"poles must lie inside the unit circle for a stabilising tube controller, got {poles}")
    from scipy.signal import place_poles   # here: scipy.signal imports scipy.stats, 0.4 s of every node's start

    return -place_poles(model.A, model.B, poles).gain_matrix


def compute_min_rpi(k_tube: np.ndarray, model) -> tuple[Polytope, int]:
    """(E, n_iter): minimal RPI set of x+ = (A + B K_tube) x + w (seed task 28)."""
    return min_robust_positively_invariant(model.A + model.B @ k_tube, disturbance_set(model))


def compute_tightening(k_tube: np.ndarray, tube: Polytope, model):
    """The model with X - E and U - K_tube E in place of X and U (seed task 29, eq. 23d, 23e)."""
    x_tight = pontryagin_difference(Polytope(model.H_x, model.h_x), tube)
    u_tight = pontryagin_difference(Polytope(model.H_u, model.h_u), tube, linear_map=k_tube)
    if np.any(x_tight.h <= 0) or np.any(u_tight.h <= 0):
        raise ValueError("the tube is too large: the tightened constraints leave no room (choose faster poles "
                         "or a smaller disturbance bound)")
    return dataclasses.replace(model, H_x=x_tight.H, h_x=x_tight.h, H_u=u_tight.H, h_u=u_tight.h)


class MPC_TUBE(CondensedMPC):
    """Problem (23): nominal MPC with the tube, LQR terminal cost and terminal set; input (24).

    `model` carries the tightened constraints (compute_tightening). `eval` returns
    u = v_0 + K_tube (x - z_0); when the QP fails, the safe action is K_tube x clipped to the
    original input box.
    """

    def __init__(self, Q, R, horizon, terminal_set: Polytope, tube: Polytope, k_tube, model, u_box_original=None):
        check_polytope("terminal set", terminal_set, model.nx)
        check_polytope("tube", tube, model.nx)
        self.K_tube = np.atleast_2d(np.asarray(k_tube, dtype=float))
        if self.K_tube.shape != (model.nu, model.nx):
            raise ValueError(f"K_tube must be {model.nu}x{model.nx}, got {self.K_tube.shape}")
        Q, R = check_weights(Q, R, model.nx, model.nu)
        _, P = dlqr(model.A, model.B, Q, R)
        self.terminal_set, self.tube = terminal_set, tube
        # The tube rows are ~1e-4 in scaled units and K_tube ~ 1e3: unpreconditioned, or with the
        # duality-gap test, proxsuite hit its iteration limit or declared infeasibility on a third
        # of the cycles; with Ruiz scaling, residuals at 1e-7 and a strict infeasibility certificate
        # (1e-9 still gave one false "infeasible" in 6000 cycles) none failed in 100 runs.
        super().__init__(Q, R, horizon, model, terminal_cost=P, terminal_set=terminal_set, tube=tube,
                         solver_options={"precondition": True, "eps_abs": 1e-7, "duality_gap_eps": None,
                                        "infeasibility_eps": 1e-11})
        self._u_safe = u_box_original if u_box_original is not None else box_bounds(model.H_u, model.h_u)

    def safe_action(self, x: np.ndarray) -> np.ndarray:
        return np.clip(self.K_tube @ x, *self._u_safe)

    def _tube_feedback(self) -> np.ndarray:
        """u = v_0 + K_tube (x - z_0), eq. (24); the plan is the nominal v_0 .. v_{N-1} with u_0 in
        place of v_0 (ExplicitPath.plan_from)."""
        return self.K_tube

def design_tube_mpc(q_z_diag, r_z: float, horizon: int, poles, model_z) -> MPC_TUBE:
    """The seed's MPC_TUBE_script (task 31): K_tube, E, tightening, terminal set, controller."""
    from bench.gnc.sets import lqr_max_pi

    Q, R = np.diag(q_z_diag), np.atleast_2d(r_z)
    k_tube = compute_tube_controller(poles, model_z)
    tube, _ = compute_min_rpi(k_tube, model_z)
    tight = compute_tightening(k_tube, tube, model_z)
    k_lqr, _ = dlqr(tight.A, tight.B, *check_weights(Q, R, tight.nx, tight.nu))
    terminal = lqr_max_pi(k_lqr, tight.A, tight.B, tight.H_x, tight.h_x, tight.H_u, tight.h_u)
    return MPC_TUBE(Q, R, horizon, terminal, tube, k_tube, tight,
                    u_box_original=box_bounds(model_z.H_u, model_z.h_u))
