"""The translation smoother's states in time: one gtsam key per plant step (and one for the
relative mean-motion correction delta), the motion factor between two steps (CWH, or the two-body
relative motion linearised about the previous estimate; nonlinear in delta when the mean motion is
estimated), and a joint belief carried forward with the thrust held.

RelativeMotion is a part of TranslationSmoother (bench/estimator/translation.py), whose model and
beliefs it uses: config, model, believed_params, believed_mean_motion_radps, estimates_mean_motion,
_two_body, _last.
"""
from __future__ import annotations

import gtsam
import numpy as np

from bench.estimator import factors
from bench.estimator.kalman import Gaussian, predict
from bench.estimator.two_body_model import TwoBodyRelativeModel

MEAN_MOTION_KEY = gtsam.symbol("n", 0)


def state_key(seq: int) -> int:
    return gtsam.symbol("x", seq)


class RelativeMotion:
    """The motion model's factors and predictions (a mixin of TranslationSmoother)."""

    def _two_body_model(self, mean_motion_radps: float) -> TwoBodyRelativeModel:
        """The two-body model of the orbit whose mean motion is given (R = (mu / n^2)^(1/3)); the
        last one is kept, as every factor of a step and its prediction share one mean motion."""
        model = self._two_body
        if model is not None and model.mean_motion_radps == mean_motion_radps:
            return model
        mu = self.believed_params.gravitational_parameter_m3ps2
        radius_m = self.believed_params.target_radius_m if mean_motion_radps == self.believed_mean_motion_radps \
            else (mu / mean_motion_radps**2) ** (1.0 / 3.0)
        frame = "cartesian" if self.config.motion_model == "two_body_cartesian" else "curvilinear"
        model = TwoBodyRelativeModel(mu, radius_m, self.believed_params.mass_kg, self.believed_params.time_step_s, frame)
        model.mean_motion_radps = mean_motion_radps     # the very number asked for (cache key)
        self._two_body = model
        return model

    def _two_body_linearised(self, state: np.ndarray, thrust: np.ndarray, n_steps: int,
                             delta: float) -> tuple[np.ndarray, np.ndarray]:
        """(f(x*, u), df/dx at x*) of the two-body model at the mean motion n_believed (1 + delta)."""
        return self._two_body_model(self._mean_motion(delta)).linearise(state, thrust, n_steps)

    def _motion_factor(self, seq: int, n_steps: int, thrust: np.ndarray):
        previous, key = state_key(seq - n_steps), state_key(seq)
        if self._two_body is not None:
            # Linearised about the previous step's estimate (self._last is that step).
            about = self._last.state.mean
            propagated, jacobian = self._two_body_linearised(about, thrust, n_steps, self._last.delta)
            if not self.estimates_mean_motion:
                m = self.model.discrete(self.believed_mean_motion_radps, n_steps)
                return factors.linear_factor([(previous, -jacobian), (key, np.eye(6))],
                                             propagated - jacobian @ about, whiten=m.process_whitening)
            # The CWH factor in delta plus the two-body model's difference from CWH at the estimated
            # mean motion (its own dependence on delta is second order: a few % of a small term).
            mean_motion = self._mean_motion(self._last.delta)
            transition, input_matrix = self.model.transition_and_input(mean_motion, n_steps)
            correction = (propagated - transition @ about - input_matrix @ thrust, jacobian - transition, about)
            return factors.cwh_motion_factor_unknown_mean_motion(
                previous, key, MEAN_MOTION_KEY, thrust, n_steps, self.model, self.believed_mean_motion_radps,
                nonlinear_correction=correction)
        if self.estimates_mean_motion:
            return factors.cwh_motion_factor_unknown_mean_motion(
                previous, key, MEAN_MOTION_KEY, thrust, n_steps, self.model, self.believed_mean_motion_radps)
        m = self.model.discrete(self.believed_mean_motion_radps, n_steps)
        return factors.cwh_motion_factor(previous, key, thrust, m)

    def _predict_last(self, seq: int, thrust: np.ndarray) -> Gaussian:
        """The last good joint estimate ([x] or [x; delta]) carried to step `seq` (first order in delta)."""
        return self._propagate(self._last.joint, seq - self._last.seq, thrust)

    def _propagate(self, joint: Gaussian, n_steps: int, thrust: np.ndarray) -> Gaussian:
        """A joint belief ([x] or [x; delta], then any constant states) carried n_steps with the
        thrust held (first order in delta)."""
        process_cov = self.model.discrete(self.believed_mean_motion_radps, n_steps).process_cov
        if self._two_body is not None:
            return self._propagate_two_body(joint, n_steps, thrust, process_cov)
        if not self.estimates_mean_motion:
            m = self.model.discrete(self.believed_mean_motion_radps, n_steps)
            if joint.mean.size == 6:
                return predict(joint, m.transition, m.input_matrix, thrust, process_cov)
            jacobian = np.eye(joint.mean.size)
            jacobian[:6, :6] = m.transition
            mean = joint.mean.copy()
            mean[:6] = m.transition @ joint.mean[:6] + m.input_matrix @ thrust
            cov = jacobian @ joint.covariance @ jacobian.T
            cov[:6, :6] += process_cov
            return Gaussian(mean, 0.5 * (cov + cov.T))
        delta = float(joint.mean[6])
        mean_motion = self._mean_motion(delta)
        transition, input_matrix = self.model.transition_and_input(mean_motion, n_steps)
        d_transition, d_input = self.model.derivative(mean_motion, n_steps)
        x = joint.mean[:6]
        # x_k = Ad(n) x + Bd(n) u, n = n_b (1 + delta): d x_k / d delta = (dAd/dn x + dBd/dn u) n_b.
        jacobian = np.eye(joint.mean.size)
        jacobian[:6, :6] = transition
        jacobian[:6, 6] = (d_transition @ x + d_input @ thrust) * self.believed_mean_motion_radps
        mean = joint.mean.copy()
        mean[:6] = transition @ x + input_matrix @ thrust
        cov = jacobian @ joint.covariance @ jacobian.T
        cov[:6, :6] += process_cov
        return Gaussian(mean, 0.5 * (cov + cov.T))

    def _propagate_two_body(self, joint: Gaussian, n_steps: int, thrust: np.ndarray, process_cov) -> Gaussian:
        """`_propagate` with the two-body model: the mean through the model, the covariance through
        its Jacobian (and, with the mean motion estimated, the CWH model's derivative in delta)."""
        delta = float(joint.mean[6]) if self.estimates_mean_motion else 0.0
        x = joint.mean[:6]
        propagated, transition = self._two_body_linearised(x, thrust, n_steps, delta)
        jacobian = np.eye(joint.mean.size)
        jacobian[:6, :6] = transition
        if self.estimates_mean_motion:
            d_transition, d_input = self.model.derivative(self._mean_motion(delta), n_steps)
            jacobian[:6, 6] = (d_transition @ x + d_input @ thrust) * self.believed_mean_motion_radps
        mean = joint.mean.copy()
        mean[:6] = propagated
        cov = jacobian @ joint.covariance @ jacobian.T
        cov[:6, :6] += process_cov
        return Gaussian(mean, 0.5 * (cov + cov.T))

    def _mean_motion(self, delta: float) -> float:
        return self.believed_mean_motion_radps * (1.0 + delta)
