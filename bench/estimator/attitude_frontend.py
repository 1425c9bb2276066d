"""The attitude estimate the controller gets every gyro tick, from the smoother or from truth.

smoother: gyro samples go into the gtsam attitude smoother (bench.estimator.attitude), which solves
at each magnetometer or star-tracker keyframe; between keyframes the last solution is carried
forward by the bias-corrected gyro, so the controller has an estimate at the gyro rate. Before the
first star-tracker fix the estimate is flagged invalid (only B-dot can fly on it).
truth: the plant's truth passed through (seed 001's "full state knowledge" case).

The field the law uses is the magnetometer's when it sampled this tick, else the on-board field
model's prediction at the last magnetometer sample rotated into the estimated body axes (truth
mode: the true body field).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.estimator.attitude import AttitudeSmoother
from bench.gnc import quaternion as qt
from bench.scenario import Scenario


@dataclass(frozen=True)
class AttitudeEstimateOut:
    valid: bool
    q_wxyz: np.ndarray
    omega_radps: np.ndarray
    gyro_bias_radps: np.ndarray
    field_body_t: np.ndarray
    attitude_covariance_rad2: np.ndarray | None = None
    # The smoother's magnetometer calibration (estimate_magnetometer_calibration): bias (body
    # axes, T) and scale; None when it is not estimated or before the first fix.
    magnetometer_bias_t: np.ndarray | None = None
    magnetometer_scale: float | None = None


class AttitudeEstimator:
    def __init__(self, scenario: Scenario):
        self.mode = scenario.estimator.mode
        self.dt_s = scenario.step_s
        self.smoother = AttitudeSmoother(scenario.estimator.attitude) if self.mode == "smoother" else None
        self._q = qt.IDENTITY_WXYZ.copy()
        self._bias = np.zeros(3)
        self._covariance: np.ndarray | None = None
        self._magnetometer_bias_t: np.ndarray | None = None   # held between keyframes, as the gyro bias
        self._magnetometer_scale: float | None = None
        self._valid = False
        self._last_gyro = np.zeros(3)
        self._field_model_inertial_t = np.zeros(3)    # none until the first magnetometer sample
        self.gyro_samples_held = 0                    # gyro samples lost, the previous one held

    def _magnetometer_calibration(self) -> tuple[np.ndarray, float]:
        """(bias T, scale): the smoother's estimate when it estimates them, else its beliefs."""
        if self._magnetometer_bias_t is not None and self._magnetometer_scale is not None:
            return self._magnetometer_bias_t, self._magnetometer_scale
        c = self.smoother.config
        return np.asarray(c.magnetometer_bias_t, float), float(c.magnetometer_scale)

    @property
    def needs_truth(self) -> bool:
        return self.mode == "truth"

    @property
    def failed_updates(self) -> int:
        return self.smoother.failed_updates if self.smoother is not None else 0

    def truth_step(self, q_wxyz, omega_radps, gyro_bias_radps, field_body_t) -> AttitudeEstimateOut:
        return AttitudeEstimateOut(True, np.asarray(q_wxyz, float), np.asarray(omega_radps, float),
                                   np.asarray(gyro_bias_radps, float), np.asarray(field_body_t, float))

    def step(self, seq: int, sim_time_s: float, gyro_radps=None, magnetometer_t=None, field_model_inertial_t=None,
             star_tracker_wxyz=None) -> AttitudeEstimateOut:
        """The estimate at tick `seq` from that tick's sensors: the gyro (None: its sample was lost,
        the last one is held over the step), and on their ticks the magnetometer with the on-board
        field model's inertial field, and a star-tracker fix (None: no fix, off its tick or in an
        outage; the gyro carries the attitude through)."""
        if gyro_radps is None:
            self.gyro_samples_held += 1
            gyro = self._last_gyro
        else:
            gyro = self._last_gyro = np.asarray(gyro_radps, dtype=float)
        if seq > 0:
            # The gyro sample of tick k is the mean rate over [t_k-1, t_k]: carry the estimate over it.
            self.smoother.add_gyro(gyro, self.dt_s)
            if self._valid:
                self._q = qt.normalize(qt.multiply(self._q, qt.exp((gyro - self._bias) * self.dt_s)))
        mag = None if magnetometer_t is None else np.asarray(magnetometer_t, float)
        if mag is not None:
            self._field_model_inertial_t = np.asarray(field_model_inertial_t, float)
        if self._valid:
            # Carried by the gyro since the last keyframe: so is its uncertainty.
            self._covariance = self.smoother.predicted_attitude_covariance()
        if mag is not None or star_tracker_wxyz is not None:
            result = self.smoother.update(seq, sim_time_s, mag, None if mag is None else self._field_model_inertial_t,
                                          None if star_tracker_wxyz is None else np.asarray(star_tracker_wxyz, float))
            if result is not None:
                self._q, self._bias = result.q_wxyz, result.gyro_bias_radps
                self._covariance = result.attitude_covariance_rad2
                self._magnetometer_bias_t = result.magnetometer_bias_t
                self._magnetometer_scale = result.magnetometer_scale
                self._valid = True
        if mag is not None:
            # The law gets the field, not the reading: measured = scale * B_body + bias, undone
            # with the calibration the smoother holds (estimated, else believed). Uncorrected, a
            # 3 uT bias is a tenth of the LEO field, and the law's dipole points that much off.
            bias_t, scale = self._magnetometer_calibration()
            field_body = (mag - bias_t) / scale
        else:
            # Between magnetometer samples: the model's field at the last sample (the inertial
            # field turns at about twice the orbit rate, ~0.13 deg/s in LEO) in today's body axes.
            field_body = qt.rotation_matrix(self._q).T @ self._field_model_inertial_t
        return AttitudeEstimateOut(self._valid, self._q.copy(), gyro - self._bias, self._bias.copy(), field_body,
                                   None if self._covariance is None else self._covariance.copy(),
                                   None if self._magnetometer_bias_t is None else self._magnetometer_bias_t.copy(),
                                   self._magnetometer_scale)
