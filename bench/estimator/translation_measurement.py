"""A fix of the chaser's relative position, direct (relpos) or as range/bearing, as the
translation smoother uses it: its gtsam factor, its residual against a state, and the iterated-EKF
steps on it (a factor linearised about the prediction, a corrected belief, the NIS) that the
smoother's linearise-at-prediction mode and its innovation gate use.
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from bench.estimator import factors
from bench.estimator.kalman import POSITION_MATRIX, Gaussian
from bench.gnc.range_bearing import wrap_angle_rad

# Relinearise a state that moved by more than 0.1 m or 0.1 mm/s (the smoother's nonlinear variants,
# and the iterations here). A bearing linearised 0.1 m off at range r errs by ~(0.1 m)^2 / r, a
# millimetre at the 100 m terminal distance.
_STATE_RELINEARISE = np.array([0.1, 0.1, 0.1, 1e-4, 1e-4, 1e-4])
_MAX_EXTRA_GAUSS_NEWTON_STEPS = 3


@dataclass(frozen=True)
class Measurement:
    factor: object                 # key -> gtsam factor
    position_guess_m: np.ndarray   # where the measurement puts the chaser (initial guess only)
    residual: object               # state -> (measured - predicted measurement, d h / d state)
    variances: np.ndarray          # the measurement noise variances believed (diagonal)

    @property
    def dof(self) -> int:
        return self.variances.size

    def linearised_factor(self, key: int, about: Gaussian) -> gtsam.LinearContainerFactor:
        """A linear factor H x = z - h(x*) + H x*, x* the iterated-EKF estimate from `about`.

        x* is where the newest state will end up given the prior and this measurement (Gauss-
        Newton on the two, iterated until it moves less than the relinearisation thresholds), so
        the factor is linearised where the smoother needs it, once, without a Python callback
        per relinearisation. Measured against relinearising every update: see docs/estimation.md.
        """
        prior_mean, p = about.mean[:6], about.covariance[:6, :6]
        r = np.diag(self.variances)
        x = prior_mean
        for _ in range(_MAX_EXTRA_GAUSS_NEWTON_STEPS + 1):
            innovation, h = self.residual(x)
            s = h @ p @ h.T + r
            x_next = prior_mean + p @ h.T @ np.linalg.solve(s, innovation + h @ (x - prior_mean))
            converged = np.all(np.abs(x_next - x) <= _STATE_RELINEARISE)
            x = x_next
            if converged:
                break
        innovation, h = self.residual(x)
        return factors.linear_factor([(key, h)], innovation + h @ x, whiten=np.diag(1.0 / np.sqrt(self.variances)))

    def _jacobian(self, state: np.ndarray, bias: bool) -> tuple[np.ndarray, np.ndarray]:
        """Innovation at a joint state [x (; delta) (; b)] and its Jacobian (delta does not enter
        the measurement; b, when `bias`, is an offset added to it)."""
        innovation, h = self.residual(state[:6])
        size, dof = state.size, self.dof
        jacobian = np.zeros((dof, size))
        jacobian[:, :6] = h
        if bias:
            innovation = innovation - state[-dof:]
            jacobian[:, -dof:] = np.eye(dof)
        return innovation, jacobian

    def innovation(self, belief: Gaussian, bias: bool = False) -> tuple[float, np.ndarray]:
        """NIS of this measurement against a joint belief, and the innovation covariance S."""
        innovation, h = self._jacobian(belief.mean, bias)
        s = h @ belief.covariance @ h.T + np.diag(self.variances)
        return float(innovation @ np.linalg.solve(s, innovation)), s

    def update(self, belief: Gaussian, bias: bool = False) -> Gaussian:
        """The joint belief corrected by this measurement: an iterated EKF (exact for a position
        fix), covariance in Joseph form at the final linearisation."""
        prior_mean, p, size = belief.mean, belief.covariance, belief.mean.size
        r = np.diag(self.variances)
        x = prior_mean
        for _ in range(_MAX_EXTRA_GAUSS_NEWTON_STEPS + 1):
            innovation, h = self._jacobian(x, bias)
            s = h @ p @ h.T + r
            x_next = prior_mean + p @ h.T @ np.linalg.solve(s, innovation + h @ (x - prior_mean))
            converged = np.all(np.abs(x_next[:6] - x[:6]) <= _STATE_RELINEARISE)
            x = x_next
            if converged:
                break
        _, h = self._jacobian(x, bias)
        gain = np.linalg.solve(h @ p @ h.T + r, h @ p).T
        i_kh = np.eye(size) - gain @ h
        cov = i_kh @ p @ i_kh.T + gain @ r @ gain.T
        return Gaussian(x, 0.5 * (cov + cov.T))

    def nis(self, state: np.ndarray, covariance: np.ndarray) -> float:
        """Normalised innovation squared nu' S^-1 nu, S = H P H' + R (first order in h)."""
        innovation, h = self.residual(state)
        s = h @ covariance @ h.T + np.diag(self.variances)
        return float(innovation @ np.linalg.solve(s, innovation))


def relpos_residual(position: np.ndarray):
    return lambda state: (position - state[:3], POSITION_MATRIX)


def range_bearing_residual(rb: np.ndarray):
    def residual(state):
        nu = rb - factors.range_bearing(state[:3])
        nu[1] = wrap_angle_rad(nu[1])    # azimuth wraps
        return nu, np.hstack([factors.range_bearing_jacobian(state[:3]), np.zeros((3, 3))])
    return residual

