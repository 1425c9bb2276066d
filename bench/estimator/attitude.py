"""Attitude and gyro-bias estimation: gtsam incremental fixed-lag smoothing for the magnetorquer loop.

States per keyframe k (one per magnetometer or star-tracker sample): R_k = ^N R ^B (Rot3, body to
inertial) and the gyro bias b_k (rad/s). Factors:
- gyro samples between keyframes preintegrated (`PreintegratedAhrsMeasurements`) into one
  `AHRSFactor` (R_{k-1}, R_k, b_{k-1}): it fixes all three degrees of freedom of R_k;
- bias random walk b_k - b_{k-1} ~ N(0, sigma_bw^2 dt): linear, so a whitened JacobianFactor; it
  fixes b_k. With these two, every new key is fully constrained whatever else arrives;
- `MagFactor1` for the magnetometer against the on-board field model (two degrees of freedom),
  with the believed bias and scale factor; or, with `estimate_magnetometer_calibration`, a factor
  on the attitude and one constant calibration variable m = [bias (uT); scale - 1] (its timestamp
  refreshed every update so it never leaves the window), which has a prior from the beliefs;
- a Rot3 prior for a star-tracker fix (three degrees of freedom), its covariance larger about the
  star tracker's boresight than across it.
The smoother starts at the first star-tracker fix (the magnetometer alone cannot fix attitude).
A failed gtsam update is logged, counted, and the smoother restarts from the last good estimate
carried forward by the gyro; bad input raises ValueError naming the problem.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np

from bench.estimator import factors
from bench.config.estimator import AttitudeSmootherConfig
from bench.estimator.gating import nis_gate
from bench.gnc.quaternion import skew

log = logging.getLogger(__name__)


def attitude_key(seq: int) -> int:
    return gtsam.symbol("r", seq)


def bias_key(seq: int) -> int:
    return gtsam.symbol("b", seq)


MAGNETOMETER_CALIBRATION_KEY = gtsam.symbol("m", 0)


@dataclass(frozen=True)
class AttitudeEstimateResult:
    seq: int
    sim_time_s: float
    q_wxyz: np.ndarray                    # body to inertial, scalar first
    attitude_covariance_rad2: np.ndarray  # (3, 3), of the body-frame error: R_true = R_est Exp(e)
    gyro_bias_radps: np.ndarray           # (3,)
    gyro_bias_covariance: np.ndarray      # (3, 3), (rad/s)^2
    failed_updates: int
    reinitialised: bool
    # (6, 6) joint covariance of [attitude error; gyro bias], the cross terms included.
    joint_covariance: np.ndarray | None = None
    # The magnetometer calibration, when it is estimated: bias (body frame, T) and scale factor.
    magnetometer_bias_t: np.ndarray | None = None
    magnetometer_scale: float | None = None
    # Normalised innovation squared of this keyframe's measurements (magnetometer and/or star
    # tracker, stacked) against the gyro prediction, and its degrees of freedom (3 per sensor).
    nis: float | None = None
    nis_dof: int = 0
    measurement_rejected: bool = False    # the innovation gate rejected this keyframe's measurements

    @property
    def rotation(self) -> gtsam.Rot3:
        return gtsam.Rot3.Quaternion(*self.q_wxyz)


@dataclass(frozen=True)
class _GoodEstimate:
    seq: int
    sim_time_s: float
    rotation: gtsam.Rot3
    bias: np.ndarray
    covariance: np.ndarray    # joint, [attitude error (body frame); gyro bias; calibration if estimated]
    calibration: np.ndarray | None = None    # [magnetometer bias uT; scale - 1] when estimated

    @property
    def rotation_cov(self) -> np.ndarray:
        return self.covariance[:3, :3]

    @property
    def bias_cov(self) -> np.ndarray:
        return self.covariance[3:6, 3:6]


class AttitudeSmoother:
    """add_gyro(omega_radps, dt_s) between keyframes; update(seq, sim_time_s, ...) at each keyframe."""

    def __init__(self, config: AttitudeSmootherConfig):
        self.config = config
        self.failed_updates = 0
        self._gyro_params = gtsam.PreintegratedRotationParams()
        self._gyro_params.setGyroscopeCovariance(np.eye(3) * config.gyro_noise_density_radps_per_rthz**2)
        self._magnetometer_noise = gtsam.noiseModel.Isotropic.Sigma(3, config.magnetometer_noise_std_t)
        self._star_tracker_covariance = star_tracker_covariance(
            config.star_tracker_noise_std_rad, config.star_tracker_boresight_noise_std_rad,
            config.star_tracker_boresight_body)
        self._star_tracker_noise = gtsam.noiseModel.Gaussian.Covariance(self._star_tracker_covariance)
        self._nis: tuple[float | None, int] = (None, 0)
        self._rejected = False
        self.rejected_measurements = 0
        self._smoother: gtsam.IncrementalFixedLagSmoother | None = None
        self._last: _GoodEstimate | None = None
        self._preintegrated: gtsam.PreintegratedAhrsMeasurements | None = None
        self._d_rotation_d_bias = np.zeros((3, 3))

    @property
    def estimates_magnetometer_calibration(self) -> bool:
        return self.config.estimate_magnetometer_calibration

    def add_gyro(self, omega_radps: np.ndarray, dt_s: float) -> None:
        """One gyro sample (mean body rate over dt_s, bias included). Ignored before the first fix."""
        omega = np.asarray(omega_radps, dtype=float).reshape(-1)
        if omega.size != 3 or not np.all(np.isfinite(omega)):
            raise ValueError(f"omega_radps must be 3 finite numbers, got {omega_radps!r}")
        if not (np.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"gyro dt_s must be positive and finite, got {dt_s}")
        if self._preintegrated is not None:
            self._preintegrated.integrateMeasurement(omega, float(dt_s))
            # d(deltaRij)/d(bias), as gtsam's PreintegratedRotation keeps it (delRdelBiasOmega,
            # not exposed in Python): D <- Exp(theta)^T D - Jr(theta) dt, theta = (omega - b) dt.
            theta = (omega - self._preintegrated.biasHat()) * dt_s
            increment = gtsam.Rot3.Expmap(theta).matrix()
            self._d_rotation_d_bias = increment.T @ self._d_rotation_d_bias - gtsam.Rot3.ExpmapDerivative(theta) * dt_s

    def update(self, seq: int, sim_time_s: float, magnetometer_t: np.ndarray | None = None,
               field_inertial_t: np.ndarray | None = None,
               star_tracker_wxyz: np.ndarray | None = None) -> AttitudeEstimateResult | None:
        """A keyframe at `seq`: the measured body-frame field with the model's inertial field, and/or
        a star-tracker quaternion (body to inertial). None until the first star-tracker fix."""
        measurement_factors = self._measurement_factors(seq, magnetometer_t, field_inertial_t, star_tracker_wxyz)
        self._nis, self._rejected = (None, 0), False
        if self._last is None:
            if star_tracker_wxyz is None:
                return None
            try:
                return self._start(seq, sim_time_s, self._first_prior(seq, star_tracker_wxyz), measurement_factors)
            except Exception as exc:
                self.failed_updates += 1
                log.warning("attitude smoother could not start at keyframe %d (%d failures so far): %s",
                            seq, self.failed_updates, exc)
                self._last = self._smoother = self._preintegrated = None
                return None
        if seq <= self._last.seq:
            raise ValueError(f"seq must increase: got {seq} after {self._last.seq}")
        if self._preintegrated.deltaTij() <= 0.0:
            raise ValueError(f"no gyro samples between keyframe {self._last.seq} and {seq}: "
                             "the new attitude would be unconstrained")
        self._nis = self._innovation(magnetometer_t, field_inertial_t, star_tracker_wxyz)
        self._rejected = False
        nis, dof = self._nis
        if self.config.gate_probability is not None and nis is not None and nis > nis_gate(self.config.gate_probability, dof):
            # The gyro alone still constrains the new keys (AHRS and bias-walk factors).
            self._rejected = True
            self.rejected_measurements += 1
            log.info("attitude keyframe %d: measurements rejected by the innovation gate (NIS %.1f, %d dof)",
                     seq, nis, dof)
            measurement_factors = []
        if self._smoother is None:
            return self._restart(seq, sim_time_s, measurement_factors)

        graph = gtsam.NonlinearFactorGraph()
        previous = self._last.seq
        graph.add(gtsam.AHRSFactor(attitude_key(previous), attitude_key(seq), bias_key(previous), self._preintegrated))
        graph.add(self._bias_walk_factor(previous, seq))
        for f in measurement_factors:
            graph.add(f)
        rotation_guess, bias_guess = self._predict_last()
        guess = gtsam.Values()
        guess.insert(attitude_key(seq), rotation_guess)
        guess.insert(bias_key(seq), bias_guess)
        try:
            return self._apply(self._smoother, seq, sim_time_s, graph, guess, reinitialised=False)
        except Exception as exc:     # gtsam raises RuntimeError subclasses; never let one out
            self.failed_updates += 1
            log.warning("attitude smoother update %d failed (%d so far): %s; restarting from the "
                        "estimate of keyframe %d", seq, self.failed_updates, exc, self._last.seq)
            self._smoother = None
            return self._restart(seq, sim_time_s, measurement_factors)

    # ---- factors ------------------------------------------------------------------------------

    def _measurement_factors(self, seq, magnetometer_t, field_inertial_t, star_tracker_wxyz) -> list:
        out = []
        if (magnetometer_t is None) != (field_inertial_t is None):
            raise ValueError("magnetometer_t and field_inertial_t come together (measurement and model)")
        if magnetometer_t is not None:
            measured = _vector("magnetometer_t", magnetometer_t)
            model = _vector("field_inertial_t", field_inertial_t)
            strength = float(np.linalg.norm(model))
            if strength == 0.0:
                raise ValueError("field_inertial_t is zero: no direction to compare with")
            if self.estimates_magnetometer_calibration:
                out.append(factors.magnetometer_calibrated_factor(
                    attitude_key(seq), MAGNETOMETER_CALIBRATION_KEY, measured, model, self._magnetometer_noise))
            else:
                out.append(gtsam.MagFactor1(attitude_key(seq), measured, self.config.magnetometer_scale * strength,
                                            gtsam.Unit3(model), np.asarray(self.config.magnetometer_bias_t, dtype=float),
                                            self._magnetometer_noise))
        if star_tracker_wxyz is not None:
            out.append(gtsam.PriorFactorRot3(attitude_key(seq), _rotation("star_tracker_wxyz", star_tracker_wxyz),
                                             self._star_tracker_noise))
        return out

    def _innovation(self, magnetometer_t, field_inertial_t, star_tracker_wxyz) -> tuple[float | None, int]:
        """NIS of this keyframe's measurements against the gyro prediction (first order).

        Errors are in the smoother's variables: attitude e (R_true = R Exp(e)), gyro bias, and the
        magnetometer calibration when it is estimated; the prediction's joint covariance is the
        restart's (`_predict_joint_covariance`).
        """
        rows, innovations, noise = [], [], []
        rotation, _ = self._predict_last()
        covariance = self._predict_joint_covariance()
        size = covariance.shape[0]
        if magnetometer_t is not None:
            field = np.asarray(field_inertial_t, dtype=float)
            body = rotation.unrotate(field)
            c = self._last.calibration
            if c is None:
                scale, bias_t = self.config.magnetometer_scale, np.asarray(self.config.magnetometer_bias_t, dtype=float)
            else:
                scale, bias_t = 1.0 + c[3], c[:3] * factors.MAGNETOMETER_BIAS_UNIT_T
            h = np.zeros((3, size))
            h[:, :3] = scale * skew(body)
            if c is not None:
                h[:, 6:9] = np.eye(3) * factors.MAGNETOMETER_BIAS_UNIT_T
                h[:, 9] = body
            rows.append(h)
            innovations.append(np.asarray(magnetometer_t, dtype=float) - (scale * body + bias_t))
            noise.append(np.eye(3) * self.config.magnetometer_noise_std_t**2)
        if star_tracker_wxyz is not None:
            h = np.zeros((3, size))
            h[:, :3] = np.eye(3)
            rows.append(h)
            innovations.append(gtsam.Rot3.Logmap(rotation.between(_rotation("star_tracker_wxyz", star_tracker_wxyz))))
            noise.append(self._star_tracker_covariance)
        if not rows:
            return None, 0
        h, innovation = np.vstack(rows), np.concatenate(innovations)
        s = h @ covariance @ h.T
        for i, block in enumerate(noise):     # the 3x3 noise blocks on the diagonal (scipy's block_diag: ~0.3 ms a call)
            s[3 * i:3 * i + 3, 3 * i:3 * i + 3] += block
        return float(innovation @ np.linalg.solve(s, innovation)), innovation.size

    def _bias_walk_factor(self, previous: int, seq: int):
        # Isotropic: the whitening is 1 / (sigma_bw sqrt(dt)), no factorisation needed.
        std_radps = self.config.gyro_bias_random_walk_radps2_per_rthz * np.sqrt(self._preintegrated.deltaTij())
        return factors.linear_factor([(bias_key(previous), -np.eye(3)), (bias_key(seq), np.eye(3))],
                                     np.zeros(3), whiten=np.eye(3) / std_radps)

    def _first_prior(self, seq: int, star_tracker_wxyz) -> list:
        # The star-tracker fix (a measurement factor) fixes R_0; the bias needs its prior.
        bias_var = self.config.initial_gyro_bias_std_radps**2
        priors = [factors.prior_factor(bias_key(seq), np.zeros(3), np.eye(3) * bias_var)]
        calibration = None
        if self.estimates_magnetometer_calibration:
            c = self.config
            calibration = np.array([*np.asarray(c.magnetometer_bias_t) / factors.MAGNETOMETER_BIAS_UNIT_T,
                                    c.magnetometer_scale - 1.0])
            sigmas = np.array([c.magnetometer_bias_prior_std_t / factors.MAGNETOMETER_BIAS_UNIT_T] * 3
                              + [c.magnetometer_scale_prior_std])
            priors.append(factors.prior_factor(MAGNETOMETER_CALIBRATION_KEY, calibration, np.diag(sigmas**2)))
        return priors, _rotation("star_tracker_wxyz", star_tracker_wxyz), np.zeros(3), calibration

    def _predict_last(self) -> tuple[gtsam.Rot3, np.ndarray]:
        """Last estimate carried across the preintegrated gyro interval (the new keys' guess)."""
        # The preintegration was started about last.bias, so deltaRij needs no bias correction.
        last = self._last
        return last.rotation.compose(self._preintegrated.deltaRij()), last.bias.copy()

    # ---- starting and restarting --------------------------------------------------------------

    def _start(self, seq, sim_time_s, prior, measurement_factors, reinitialised: bool = False):
        prior_factors, rotation_guess, bias_guess, calibration_guess = prior
        graph = gtsam.NonlinearFactorGraph()
        for f in [*prior_factors, *measurement_factors]:
            graph.add(f)
        guess = gtsam.Values()
        guess.insert(attitude_key(seq), rotation_guess)
        guess.insert(bias_key(seq), np.asarray(bias_guess, dtype=float))
        if calibration_guess is not None:
            guess.insert(MAGNETOMETER_CALIBRATION_KEY, np.asarray(calibration_guess, dtype=float))
        smoother = gtsam.IncrementalFixedLagSmoother(self.config.lag_s, self._isam_params())
        result = self._apply(smoother, seq, sim_time_s, graph, guess, reinitialised)
        self._smoother = smoother
        return result

    def predicted_attitude_covariance(self) -> np.ndarray | None:
        """The attitude covariance (rad^2, body frame) of the last keyframe's estimate carried by
        the gyro to now: what an estimate between keyframes is worth (the keyframe's own leaves
        out the gyro's noise and the bias error since, which grow the error as t^2). None before
        the first fix."""
        if self._last is None:
            return None
        if self._preintegrated is None or self._preintegrated.deltaTij() <= 0.0:
            return self._last.covariance[:3, :3].copy()
        return self._predict_joint_covariance()[:3, :3]

    def _predict_joint_covariance(self) -> np.ndarray:
        """The last joint covariance carried across the preintegrated gyro interval.

        With R_true = R Exp(e) and the bias error db: e_k = dR' e_{k-1} + D db + n, db_k = db + w,
        where dR is the preintegrated rotation (the old body frame's error seen in the new body
        frame), D = d dR / d bias and n the preintegration noise (covariance preintMeasCov).
        """
        pim = self._preintegrated
        size = self._last.covariance.shape[0]      # the calibration, if estimated, is constant
        transition = np.eye(size)
        transition[:3, :3] = pim.deltaRij().matrix().T
        transition[:3, 3:6] = self._d_rotation_d_bias
        noise = np.zeros((size, size))
        noise[:3, :3] = pim.preintMeasCov()
        noise[3:6, 3:6] = np.eye(3) * self.config.gyro_bias_random_walk_radps2_per_rthz**2 * pim.deltaTij()
        cov = transition @ self._last.covariance @ transition.T + noise
        return 0.5 * (cov + cov.T)

    def _restart(self, seq, sim_time_s, measurement_factors):
        """New smoother at `seq` with the last good estimate, carried by the gyro, as its prior."""
        rotation, bias = self._predict_last()
        calibration = self._last.calibration
        covariance = self._predict_joint_covariance()
        variables = [(attitude_key(seq), rotation), (bias_key(seq), bias)]
        if calibration is not None:
            variables.append((MAGNETOMETER_CALIBRATION_KEY, calibration))
        prior = factors.joint_prior_factor(variables, covariance)
        try:
            return self._start(seq, sim_time_s, ([prior], rotation, bias, calibration), measurement_factors,
                               reinitialised=True)
        except Exception as exc:
            self.failed_updates += 1
            log.warning("attitude smoother restart at keyframe %d failed (%d so far): %s; "
                        "publishing the gyro prediction", seq, self.failed_updates, exc)
            self._smoother = None
            self._last = _GoodEstimate(seq, sim_time_s, rotation, bias, covariance, calibration)
            self._reset_preintegration()
            return self._result(self._last, reinitialised=True)

    def _isam_params(self) -> gtsam.ISAM2Params:
        params = gtsam.ISAM2Params()
        # Rotations are nonlinear: relinearise any variable that moved by more than 1e-3 rad (or
        # rad/s), checked every update. The linearisation error left is second order, ~1e-6 rad,
        # far below the star tracker's 1e-4 rad; a tighter threshold costs time for nothing.
        params.setRelinearizeThreshold(1e-3)
        params.relinearizeSkip = 1
        return params

    # ---- solving ------------------------------------------------------------------------------

    def _apply(self, smoother, seq, sim_time_s, graph, guess, reinitialised: bool):
        stamps = gtsam.FixedLagSmootherKeyTimestampMap()
        stamps.insert((attitude_key(seq), float(sim_time_s)))
        stamps.insert((bias_key(seq), float(sim_time_s)))
        if self.estimates_magnetometer_calibration:
            stamps.insert((MAGNETOMETER_CALIBRATION_KEY, float(sim_time_s)))   # keep it in the window
        smoother.update(graph, guess, stamps)
        r_key, b_key = attitude_key(seq), bias_key(seq)
        rotation = smoother.calculateEstimateRot3(r_key)
        bias = np.asarray(smoother.calculateEstimateVector(b_key), dtype=float)
        # Joint, not two marginals: a restart needs the attitude / bias (/ calibration) correlation.
        keys = [r_key, b_key]
        calibration = None
        if self.estimates_magnetometer_calibration:
            keys.append(MAGNETOMETER_CALIBRATION_KEY)
            calibration = np.asarray(smoother.calculateEstimateVector(MAGNETOMETER_CALIBRATION_KEY), dtype=float)
        # fullMatrix() is in the query keys' order (checked against its blocks, tests).
        covariance = np.asarray(smoother.getISAM2().jointMarginalCovariance(keys).fullMatrix())
        if not all(np.all(np.isfinite(a)) for a in (rotation.matrix(), bias, covariance)):
            raise RuntimeError(f"non-finite attitude estimate at keyframe {seq}")
        self._last = _GoodEstimate(seq, float(sim_time_s), rotation, bias, 0.5 * (covariance + covariance.T),
                                   calibration)
        self._reset_preintegration()
        return self._result(self._last, reinitialised)

    def _reset_preintegration(self) -> None:
        # Preintegrate about the newest bias estimate: the factor's first-order bias correction
        # is then applied to small deviations only.
        self._preintegrated = gtsam.PreintegratedAhrsMeasurements(self._gyro_params, self._last.bias)
        self._d_rotation_d_bias = np.zeros((3, 3))

    def _result(self, good: _GoodEstimate, reinitialised: bool) -> AttitudeEstimateResult:
        q = good.rotation.toQuaternion()
        return AttitudeEstimateResult(
            seq=good.seq, sim_time_s=good.sim_time_s,
            q_wxyz=np.array([q.w(), q.x(), q.y(), q.z()]),
            attitude_covariance_rad2=0.5 * (good.rotation_cov + good.rotation_cov.T),
            gyro_bias_radps=good.bias.copy(),
            gyro_bias_covariance=0.5 * (good.bias_cov + good.bias_cov.T),
            failed_updates=self.failed_updates, reinitialised=reinitialised,
            joint_covariance=good.covariance[:6, :6].copy(),
            magnetometer_bias_t=None if good.calibration is None else good.calibration[:3] * factors.MAGNETOMETER_BIAS_UNIT_T,
            magnetometer_scale=None if good.calibration is None else 1.0 + float(good.calibration[3]),
            nis=self._nis[0], nis_dof=self._nis[1], measurement_rejected=self._rejected,
        )


def _vector(name: str, value) -> np.ndarray:
    v = np.asarray(value, dtype=float).reshape(-1)
    if v.size != 3 or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return v


def _rotation(name: str, q_wxyz) -> gtsam.Rot3:
    q = np.asarray(q_wxyz, dtype=float).reshape(-1)
    if q.size != 4 or not np.all(np.isfinite(q)):
        raise ValueError(f"{name} must be 4 finite numbers [w, x, y, z], got {q_wxyz!r}")
    norm = np.linalg.norm(q)
    if abs(norm - 1.0) > 1e-3:
        raise ValueError(f"{name} must be a unit quaternion, got norm {norm:.6f}")
    return gtsam.Rot3.Quaternion(*(q / norm))


def star_tracker_covariance(cross_std_rad: float, boresight_std_rad: float, boresight_body) -> np.ndarray:
    """Covariance of a star tracker's body-frame attitude error: sigma^2 across the boresight
    axis a, sigma_b^2 about it: sigma^2 (I - a a') + sigma_b^2 a a'."""
    axis = np.asarray(boresight_body, dtype=float)
    norm = np.linalg.norm(axis)
    if not (np.all(np.isfinite(axis)) and norm > 0):
        raise ValueError(f"star_tracker_boresight_body must be a non-zero vector, got {boresight_body!r}")
    axis = axis / norm
    along = np.outer(axis, axis)
    return cross_std_rad**2 * (np.eye(3) - along) + boresight_std_rad**2 * along

