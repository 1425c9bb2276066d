"""The estimator's CWH motion model: (Ad, Bd, Q) over an interval, and its derivative in the mean motion.

Shared by the smoother and the reference Kalman filter so both use exactly the same numbers.
The plant's linear CWH is noise-free; the estimator assumes a white acceleration of spectral
density `process_noise_psd_m2ps3` on the velocity states, discretised by Van Loan's method, so
that Q is full rank and every motion factor constrains all six states.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property, lru_cache

import numpy as np
from scipy.linalg import expm, expm_frechet

from bench.plant.cwh import N_INPUT, N_STATE, RendezvousParams, cwh_continuous, discretise_zoh


def params_with_mean_motion(params: RendezvousParams, mean_motion_radps: float) -> RendezvousParams:
    """The params whose target orbit has this mean motion (R = (mu / n^2)^(1/3)).

    How a controller adopts the smoother's estimated mean motion: rebuild its model from these.
    """
    if not (np.isfinite(mean_motion_radps) and mean_motion_radps > 0):
        raise ValueError(f"mean_motion_radps must be positive and finite, got {mean_motion_radps}")
    radius_m = (params.gravitational_parameter_m3ps2 / mean_motion_radps**2) ** (1.0 / 3.0)
    return replace(params, target_radius_m=float(radius_m))


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


def cwh_continuous_mean_motion_derivative(mean_motion: float) -> np.ndarray:
    """dA_c/dn of the CWH matrix (B_c does not depend on n)."""
    d = np.zeros((N_STATE, N_STATE))
    d[3, 0] = 6.0 * mean_motion
    d[3, 4] = 2.0
    d[4, 3] = -2.0
    d[5, 2] = -2.0 * mean_motion
    return d


# Acceleration noise enters the velocity states.
_ACCEL_INPUT = np.vstack([np.zeros((3, 3)), np.eye(3)])


class CwhMotionModel:
    """Discrete CWH model for a given mean motion and a whole number of plant steps.

    Results are cached per (mean motion, steps): every motion factor in the window shares one
    mean motion, so a joint estimate costs one matrix exponential per distinct value, not per factor.
    """

    def __init__(self, mass_kg: float, time_step_s: float, process_noise_psd_m2ps3: float):
        if not (mass_kg > 0 and time_step_s > 0 and process_noise_psd_m2ps3 > 0):
            raise ValueError(
                "CwhMotionModel needs positive mass_kg, time_step_s and process_noise_psd_m2ps3, got "
                f"{mass_kg}, {time_step_s}, {process_noise_psd_m2ps3}"
            )
        self.mass_kg = mass_kg
        self.time_step_s = time_step_s
        self.process_noise_psd_m2ps3 = process_noise_psd_m2ps3
        self.discrete = lru_cache(maxsize=64)(self._discrete)
        self.derivative = lru_cache(maxsize=64)(self._derivative)

    def _discrete(self, mean_motion_radps: float, n_steps: int = 1) -> DiscreteModel:
        # The thrust is held over the whole gap, so n steps are one ZOH step of n * dt.
        interval_s = n_steps * self.time_step_s
        a_c, b_c = cwh_continuous(mean_motion_radps, self.mass_kg)
        a_d, b_d = discretise_zoh(a_c, b_c, interval_s)
        q = van_loan_process_cov(a_c, _ACCEL_INPUT, self.process_noise_psd_m2ps3, interval_s)
        return DiscreteModel(a_d, b_d, q)

    def _derivative(self, mean_motion_radps: float, n_steps: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """(dAd/dn, dBd/dn): Frechet derivative of the ZOH block exponential along dA_c/dn."""
        interval_s = n_steps * self.time_step_s
        a_c, b_c = cwh_continuous(mean_motion_radps, self.mass_kg)
        size = N_STATE + N_INPUT
        block = np.zeros((size, size))
        block[:N_STATE, :N_STATE] = a_c
        block[:N_STATE, N_STATE:] = b_c
        direction = np.zeros((size, size))
        direction[:N_STATE, :N_STATE] = cwh_continuous_mean_motion_derivative(mean_motion_radps)
        _, d_phi = expm_frechet(block * interval_s, direction * interval_s)
        return d_phi[:N_STATE, :N_STATE], d_phi[:N_STATE, N_STATE:]
