"""A textbook linear Kalman filter: the reference the translational smoother is checked against.

For a linear Gaussian model the fixed-lag smoother's newest estimate is the Kalman filter's
(marginalising old states is exact), so the tests compare the two to numerical precision. The
`predict` step is also what the smoother uses to carry its last good estimate across a failed
update.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Gaussian:
    mean: np.ndarray
    covariance: np.ndarray


def predict(belief: Gaussian, transition: np.ndarray, input_matrix: np.ndarray,
            control: np.ndarray, process_cov: np.ndarray) -> Gaussian:
    mean = transition @ belief.mean + input_matrix @ control
    cov = transition @ belief.covariance @ transition.T + process_cov
    return Gaussian(mean, 0.5 * (cov + cov.T))


def correct(belief: Gaussian, measurement: np.ndarray, measurement_matrix: np.ndarray,
            measurement_cov: np.ndarray) -> Gaussian:
    """Measurement update in Joseph form (stays symmetric positive definite)."""
    h, p = measurement_matrix, belief.covariance
    innovation_cov = h @ p @ h.T + measurement_cov
    gain = np.linalg.solve(innovation_cov, h @ p).T
    mean = belief.mean + gain @ (measurement - h @ belief.mean)
    i_kh = np.eye(p.shape[0]) - gain @ h
    cov = i_kh @ p @ i_kh.T + gain @ measurement_cov @ gain.T
    return Gaussian(mean, 0.5 * (cov + cov.T))


POSITION_MATRIX = np.hstack([np.eye(3), np.zeros((3, 3))])


def initial_belief_from_position(position_m: np.ndarray, position_noise_std_m: float,
                                 velocity_std_mps: float) -> Gaussian:
    """First fix: position measured, velocity unknown around zero (the smoother's first factors)."""
    mean = np.concatenate([np.asarray(position_m, dtype=float), np.zeros(3)])
    cov = np.diag([position_noise_std_m**2] * 3 + [velocity_std_mps**2] * 3)
    return Gaussian(mean, cov)
