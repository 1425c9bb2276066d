"""Clohessy-Wiltshire-Hill relative motion, as seed 003 sets it up (tasks 1 to 5).

State x = [x, y, z, vx, vy, vz] in the target's LVLH frame (x radial out, y along track, z along
the orbit normal), SI units (m, m/s); input u = thrust in N per axis.

The controllers work in the seed's scaled units (Mm, km/s): x_scaled = V x. Everything that
crosses a process boundary stays in SI; only `ScaledModel` speaks scaled units.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from bench.data import load_reference

N_STATE = 6
N_INPUT = 3


def mean_motion_radps(gravitational_parameter_m3ps2: float, target_radius_m: float) -> float:
    """Orbital rate omega_n = sqrt(mu / R^3) of a circular target orbit."""
    return float(np.sqrt(gravitational_parameter_m3ps2 / target_radius_m**3))


def cwh_continuous(mean_motion: float, mass_kg: float) -> tuple[np.ndarray, np.ndarray]:
    """(A_c, B_c) of x_dot = A_c x + B_c u for the CWH equations (seed 003 eq. 1, task 1)."""
    n = mean_motion
    a_c = np.zeros((N_STATE, N_STATE))
    a_c[0:3, 3:6] = np.eye(3)
    a_c[3, 0] = 3.0 * n**2
    a_c[3, 4] = 2.0 * n
    a_c[4, 3] = -2.0 * n
    a_c[5, 2] = -(n**2)
    b_c = np.zeros((N_STATE, N_INPUT))
    b_c[3:6, :] = np.eye(3) / mass_kg
    return a_c, b_c


def discretise_zoh(a_c: np.ndarray, b_c: np.ndarray, time_step_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation (seed 003 task 2), via one matrix exponential.

    expm([[A, B], [0, 0]] dt) = [[Ad, Bd], [0, I]]: the same result as MATLAB's c2d.
    """
    if not time_step_s > 0:
        raise ValueError(f"time_step_s must be positive, got {time_step_s}")
    n_x, n_u = b_c.shape
    block = np.zeros((n_x + n_u, n_x + n_u))
    block[:n_x, :n_x] = a_c
    block[:n_x, n_x:] = b_c
    from scipy.linalg import expm   # here, not at the top: the launcher imports this module for its types

    phi = expm(block * time_step_s)
    return phi[:n_x, :n_x], phi[:n_x, n_x:]


def scale_system(a_d: np.ndarray, b_d: np.ndarray, scaling: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) for x_scaled = V x (seed 003 task 3): A = V Ad V^-1, B = V Bd."""
    v = np.diag(scaling)
    v_inv = np.diag(1.0 / scaling)
    return v @ a_d @ v_inv, v @ b_d


@dataclass(frozen=True)
class RendezvousParams:
    """The seed's `params` struct (seed 003 table 1), built from a scenario or the reference.

    SI units throughout; `scaled` gives the model and constraints in the controllers' units. No
    defaults: the numbers come from `from_reference` (bench/data/rendezvous.toml) only.
    """

    mass_kg: float
    gravitational_parameter_m3ps2: float
    target_radius_m: float
    time_step_s: float
    n_steps: int
    scaling: tuple[float, ...]
    max_abs_thrust_n: float
    max_abs_position_xz_m: float
    max_abs_position_y_m: float
    max_final_position_m: float
    max_final_velocity_mps: float
    initial_conditions_m_mps: dict[str, tuple[float, ...]] = field(default_factory=dict, compare=False)

    @classmethod
    def from_reference(cls, **overrides) -> "RendezvousParams":
        ref = load_reference()
        model, cons = ref["model"], ref["constraints"]
        scaling = tuple(model["scaling_diag"])
        ics = {
            # Rounded to the micrometre: the division leaves float dust (400000.00000000006 m).
            name: tuple(float(v) for v in np.round(np.asarray(x_scaled) / np.asarray(scaling), 6))
            for name, x_scaled in ref["initial_conditions_scaled"].items()
            if len(x_scaled) == N_STATE
        }
        values = dict(
            mass_kg=model["mass_kg"],
            gravitational_parameter_m3ps2=model["gravitational_parameter"],
            target_radius_m=model["target_radius_m"],
            time_step_s=model["time_step_s"],
            n_steps=int(round(model["final_time_s"] / model["time_step_s"])),
            scaling=scaling,
            max_abs_thrust_n=cons["max_abs_thrust_N"],
            max_abs_position_xz_m=cons["max_abs_position_xz_m"],
            max_abs_position_y_m=cons["max_abs_position_y_m"],
            max_final_position_m=cons["max_final_position_m"],
            max_final_velocity_mps=cons["max_final_velocity_mps"],
            initial_conditions_m_mps=ics,
        )
        values.update(overrides)
        return cls(**values)

    @property
    def mean_motion(self) -> float:
        return mean_motion_radps(self.gravitational_parameter_m3ps2, self.target_radius_m)

    @property
    def scaling_matrix(self) -> np.ndarray:
        return np.diag(self.scaling)

    def continuous(self) -> tuple[np.ndarray, np.ndarray]:
        return cwh_continuous(self.mean_motion, self.mass_kg)

    def discrete_si(self) -> tuple[np.ndarray, np.ndarray]:
        """(Ad, Bd) on SI state, one time step."""
        return discretise_zoh(*self.continuous(), self.time_step_s)

    @cached_property
    def scaled(self) -> "ScaledModel":
        return ScaledModel.from_params(self)

    def with_radius_error(self, relative_error: float) -> "RendezvousParams":
        """These params with the target orbit radius R (1 + relative_error): what a flight side
        believes that has the orbit this far wrong (seed 001, third case)."""
        return replace(self, target_radius_m=self.target_radius_m * (1.0 + relative_error))

    def initial_state_m_mps(self, name: str) -> np.ndarray:
        try:
            return np.array(self.initial_conditions_m_mps[name])
        except KeyError:
            known = ", ".join(sorted(self.initial_conditions_m_mps)) or "none"
            raise KeyError(f"unknown initial condition {name!r} (known: {known})") from None


def params_with_mean_motion(params: RendezvousParams, mean_motion_radps: float) -> RendezvousParams:
    """The params whose target orbit has this mean motion (R = (mu / n^2)^(1/3)).

    How a controller adopts the smoother's estimated mean motion: rebuild its model from these.
    """
    if not (np.isfinite(mean_motion_radps) and mean_motion_radps > 0):
        raise ValueError(f"mean_motion_radps must be positive and finite, got {mean_motion_radps}")
    radius_m = (params.gravitational_parameter_m3ps2 / mean_motion_radps**2) ** (1.0 / 3.0)
    return replace(params, target_radius_m=float(radius_m))


class _ModelDimensions:
    """n_x and n_u of a model with A and B, as the seed's params.model.nx / nu."""

    @property
    def nx(self) -> int:
        return self.A.shape[0]

    @property
    def nu(self) -> int:
        return self.B.shape[1]


@dataclass(frozen=True)
class ScaledModel(_ModelDimensions):
    """The discrete model and constraints in scaled units (seed 003 tasks 3 and 4).

    Constraints: H_u u <= h_u (|u_i| <= u_max), H_x x <= h_x (|x|,|z| <= s_max, |y| <= y_max),
    with rows ordered +e_i, -e_i per constrained coordinate.
    """

    A: np.ndarray
    B: np.ndarray
    H_u: np.ndarray
    h_u: np.ndarray
    H_x: np.ndarray
    h_x: np.ndarray
    scaling: np.ndarray

    @classmethod
    def from_params(cls, p: RendezvousParams) -> "ScaledModel":
        scaling = np.asarray(p.scaling, dtype=float)
        a, b = scale_system(*p.discrete_si(), scaling)
        h_u_mat, h_u = box_constraints(np.full(N_INPUT, p.max_abs_thrust_n))
        position_limits_m = np.array([p.max_abs_position_xz_m, p.max_abs_position_y_m, p.max_abs_position_xz_m])
        h_pos_mat, h_x = box_constraints(position_limits_m * scaling[:3])
        h_x_mat = np.hstack([h_pos_mat, np.zeros((h_pos_mat.shape[0], 3))])
        return cls(A=a, B=b, H_u=h_u_mat, h_u=h_u, H_x=h_x_mat, h_x=h_x, scaling=scaling)


    def to_scaled(self, state_si: np.ndarray) -> np.ndarray:
        return self.scaling * np.asarray(state_si)

    def to_si(self, state_scaled: np.ndarray) -> np.ndarray:
        return np.asarray(state_scaled) / self.scaling


def box_constraints(limits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """|v_i| <= limits_i as H v <= h, rows +e_i then -e_i for each i."""
    limits = np.asarray(limits, dtype=float)
    n = limits.size
    h_mat = np.zeros((2 * n, n))
    h_mat[0::2] = np.eye(n)
    h_mat[1::2] = -np.eye(n)
    return h_mat, np.repeat(limits, 2)


@dataclass(frozen=True)
class ZSubsystem(_ModelDimensions):
    """The out-of-plane subsystem [z, vz] with additive disturbance (seed 003 eq. 21, table 11).

    Same field names as `ScaledModel` so every controller runs on either; scaled units (Mm, km/s).
    Disturbance set H_w w <= h_w is the box |w_i| <= max_abs_disturbance (the seed's eq. 22 prints
    h_w = w_max [1, 1, 1, -1], which would pin w_2 = w_max; its own generate_params_z uses the box).
    """

    A: np.ndarray
    B: np.ndarray
    H_u: np.ndarray
    h_u: np.ndarray
    H_x: np.ndarray
    h_x: np.ndarray
    H_w: np.ndarray
    h_w: np.ndarray
    max_abs_disturbance: float
    initial_state_a: np.ndarray
    n_steps: int



Z_STATES = (2, 5)     # z, vz in the full state
Z_INPUTS = (2,)       # u_z


def z_subsystem(params: RendezvousParams) -> ZSubsystem:
    """The seed's generate_params_z: project the scaled model and constraints onto [z, vz], u_z."""
    ref = load_reference()
    model = params.scaled
    sx, su = list(Z_STATES), list(Z_INPUTS)
    h_x_mat = model.H_x[:, sx]
    keep_x = np.any(h_x_mat != 0, axis=1)          # rows on x and y say 0 <= s_max: drop them
    h_u_mat = model.H_u[:, su]
    keep_u = np.any(h_u_mat != 0, axis=1)
    w_max = float(ref["weights"]["max_abs_disturbance"])
    h_w_mat, h_w = box_constraints(np.full(len(sx), w_max))
    return ZSubsystem(
        A=model.A[np.ix_(sx, sx)], B=model.B[np.ix_(sx, su)],
        H_u=h_u_mat[keep_u], h_u=model.h_u[keep_u], H_x=h_x_mat[keep_x], h_x=model.h_x[keep_x],
        H_w=h_w_mat, h_w=h_w, max_abs_disturbance=w_max,
        initial_state_a=np.asarray(ref["initial_conditions_scaled"]["z_subsystem_A"], dtype=float),
        n_steps=params.n_steps,
    )
