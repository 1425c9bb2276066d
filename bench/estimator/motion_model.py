"""The estimator's CWH motion model: (Ad, Bd, Q) over an interval, and its derivative in the mean motion.

Shared by the smoother and the reference Kalman filter so both use exactly the same numbers.
The plant's linear CWH is noise-free; the estimator assumes a white acceleration of spectral
density `process_noise_psd_m2ps3` (its belief, zero by default) on the velocity states,
discretised by Van Loan's method. A density below PROCESS_NOISE_FLOOR_M2PS3 is raised to it, so
that Q stays full rank and every whitened motion factor constrains all six states.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
from scipy.linalg import expm

from bench.gnc.cwh import cwh_continuous, discretise_zoh


@dataclass(frozen=True)
class DiscreteModel:
    """x_k = transition x_{k-1} + input_matrix u_{k-1} + w, w ~ N(0, process_cov)."""

    transition: np.ndarray      # (6, 6)
    input_matrix: np.ndarray    # (6, 3), thrust in N
    process_cov: np.ndarray     # (6, 6), SI

    @cached_property
    def process_whitening(self) -> np.ndarray:
        """W with W' W = Q^-1: motion factors are whitened with it (computed once per model)."""
        return np.linalg.inv(np.linalg.cholesky(self.process_cov))


def van_loan_process_cov(a_c: np.ndarray, noise_input: np.ndarray, psd: float, interval_s: float) -> np.ndarray:
    """Q = integral_0^dt e^(A t) G psd G' e^(A' t) dt, by Van Loan's block exponential."""
    n = a_c.shape[0]
    block = np.zeros((2 * n, 2 * n))
    block[:n, :n] = -a_c
    block[:n, n:] = psd * noise_input @ noise_input.T
    block[n:, n:] = a_c.T
    phi = expm(block * interval_s)
    q = phi[n:, n:].T @ phi[:n, n:]
    return 0.5 * (q + q.T)


def cwh_discrete_closed_form(mean_motion_radps, mass_kg: float, interval_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(Ad, Bd) of the CWH equations in closed form (thrust held over the interval).

    The same matrices as the plant's `discretise_zoh` (to ~1e-15, checked in the tests) but
    without a matrix exponential, and written so a complex mean motion goes through: that is how
    `mean_motion_derivative` gets dAd/dn and dBd/dn exactly, by the complex step.
    Phi is the Clohessy-Wiltshire state-transition matrix; Bd = (1/m) int_0^T Phi_(:, v)(t) dt.
    """
    n, t = mean_motion_radps, interval_s
    tau = n * t
    s, c = np.sin(tau), np.cos(tau)
    o = 0.0 * n     # a zero of n's type, so the arrays stay complex under the complex step
    transition = np.array([
        [4 - 3 * c, o, o, s / n, 2 * (1 - c) / n, o],
        [6 * (s - tau), 1 + o, o, -2 * (1 - c) / n, (4 * s - 3 * tau) / n, o],
        [o, o, c, o, o, s / n],
        [3 * n * s, o, o, c, 2 * s, o],
        [-6 * n * (1 - c), o, o, -2 * s, 4 * c - 3, o],
        [o, o, -n * s, o, o, c],
    ])
    velocity_columns_integral = np.array([
        [(1 - c) / n**2, 2 * (tau - s) / n**2, o],
        [-2 * (tau - s) / n**2, 4 * (1 - c) / n**2 - 1.5 * t**2, o],
        [o, o, (1 - c) / n**2],
        [s / n, 2 * (1 - c) / n, o],
        [-2 * (1 - c) / n, 4 * s / n - 3 * t, o],
        [o, o, s / n],
    ])
    return transition, velocity_columns_integral / mass_kg


# Complex-step size relative to n: no subtraction, so it can be tiny (the derivative is exact to
# rounding whatever the step).
_COMPLEX_STEP = 1e-30


# A noise-free model still needs an invertible Q for its whitened motion factors. 1e-16 m^2/s^3
# is 2.4e-7 m/s of velocity random walk per 600 s step, 3e-4 of the ~8e-4 m/s velocity sigma the
# smoother settles at; measured in the closed loop (10 seeds): average NEES 5.37 at 1e-16, 5.24
# at 1e-14, 3.2 at 1e-9. The whitened system is then badly conditioned, which QR handles.
PROCESS_NOISE_FLOOR_M2PS3 = 1.0e-16

# Acceleration noise enters the velocity states.
_ACCEL_INPUT = np.vstack([np.zeros((3, 3)), np.eye(3)])


class CwhMotionModel:
    """Discrete CWH model for a given mean motion and a whole number of plant steps.

    `discrete` (with Q) uses the plant's own ZOH discretisation; the joint mean-motion factors use
    the closed form and its derivative. Results are cached per (mean motion, steps): every motion
    factor in the window shares one mean motion, so they cost one evaluation, not one per factor.
    """

    def __init__(self, mass_kg: float, time_step_s: float, process_noise_psd_m2ps3: float):
        if not (mass_kg > 0 and time_step_s > 0 and process_noise_psd_m2ps3 >= 0):
            raise ValueError(
                "CwhMotionModel needs positive mass_kg and time_step_s and a non-negative "
                f"process_noise_psd_m2ps3, got {mass_kg}, {time_step_s}, {process_noise_psd_m2ps3}"
            )
        self.mass_kg = mass_kg
        self.time_step_s = time_step_s
        self.process_noise_psd_m2ps3 = max(process_noise_psd_m2ps3, PROCESS_NOISE_FLOOR_M2PS3)
        self.discrete = lru_cache(maxsize=64)(self._discrete)
        self.derivative = lru_cache(maxsize=64)(self._derivative)
        self.transition_and_input = lru_cache(maxsize=64)(self._transition_and_input)

    def _discrete(self, mean_motion_radps: float, n_steps: int = 1) -> DiscreteModel:
        # The thrust is held over the whole gap, so n steps are one ZOH step of n * dt.
        interval_s = n_steps * self.time_step_s
        a_c, b_c = cwh_continuous(mean_motion_radps, self.mass_kg)
        a_d, b_d = discretise_zoh(a_c, b_c, interval_s)
        q = van_loan_process_cov(a_c, _ACCEL_INPUT, self.process_noise_psd_m2ps3, interval_s)
        return DiscreteModel(a_d, b_d, q)

    def _derivative(self, mean_motion_radps: float, n_steps: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """(dAd/dn, dBd/dn) by the complex step on the closed form: exact, ~20 us, no expm."""
        h = _COMPLEX_STEP * mean_motion_radps
        a_d, b_d = cwh_discrete_closed_form(mean_motion_radps + 1j * h, self.mass_kg, n_steps * self.time_step_s)
        return a_d.imag / h, b_d.imag / h

    def _transition_and_input(self, mean_motion_radps: float, n_steps: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """(Ad, Bd) in closed form: what the joint smoother evaluates at every new mean motion."""
        return cwh_discrete_closed_form(mean_motion_radps, self.mass_kg, n_steps * self.time_step_s)
