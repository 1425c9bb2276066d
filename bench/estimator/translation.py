"""Translational state estimation: gtsam incremental fixed-lag smoothing of the CWH relative state.

One state key x_k (6, SI) per plant step k. Factors:
- motion between k-1 and k from the discretised CWH model with the thrust commanded at k-1 (the
  thrust the plant held over the step), whitened by the assumed process noise; or, with
  `motion_model = "two_body_*"`, from the exact two-body relative motion linearised about the
  previous step's estimate when the factor is made (an extended-Kalman-style factor: linear, never
  relinearised; the second-order error of that linearisation is ~n^2 e^2 / R for an estimate
  error e, 1e-11 m/s^2 at e = 10 m, against the 1e-5 m/s^2 of the terms CWH drops);
- a relative-position (or range/bearing) measurement at k when one is used;
- on the first key, a prior on the velocity (the first fix gives the position);
- with `estimate_mean_motion`, one extra key delta (the mean motion is n_believed (1 + delta)), a
  prior from the believed orbit radius, and the motion factors become nonlinear in delta. delta's
  timestamp is refreshed every update so it never leaves the window.

Every new state key is fully constrained (a full-rank motion factor from the previous key, or the
prior and the first fix), which is what keeps the incremental solver away from indeterminate
systems. A failed gtsam update is logged, counted, and the smoother restarts from its last good
estimate propagated to the current step; it never raises on numerical trouble. Bad input (wrong
shape, non-finite numbers, seq not increasing) raises ValueError naming the problem.

The parts: the fixes (translation_measurement.py), the innovation gate and re-acquisition
(translation_gate.py), the states in time and their motion (translation_motion.py); here the
smoother itself, its gtsam updates, starts and restarts.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np

from bench.estimator import factors
from bench.config.estimator import TranslationSmootherConfig
from bench.estimator.gating import nis_gate
from bench.estimator.kalman import POSITION_MATRIX, Gaussian
from bench.estimator.motion_model import CwhMotionModel
from bench.estimator.translation_gate import InnovationGate, RejectionRun
from bench.estimator.translation_measurement import (_MAX_EXTRA_GAUSS_NEWTON_STEPS, _STATE_RELINEARISE, Measurement,
                                                     range_bearing_residual, relpos_residual)
from bench.estimator.translation_motion import MEAN_MOTION_KEY, RelativeMotion, state_key
from bench.estimator.two_body_model import TwoBodyRelativeModel
from bench.gnc.cwh import RendezvousParams
from bench.gnc.range_bearing import position_from_range_bearing
from bench.config.plant import RangeBearingSensorConfig, RelativePositionSensorConfig

log = logging.getLogger(__name__)

# Nonlinear variants (joint mean motion, range/bearing): relinearise a state as the fixes do
# (translation_measurement._STATE_RELINEARISE), delta when it moved by more than 1e-4. delta
# enters the motion model smoothly: a 1e-4 step leaves a second-order residual error of
# millimetres, while relinearising delta relinearises every motion factor in the window (a Python
# callback each).
_DELTA_RELINEARISE = np.array([1e-4])
# When every measurement factor is linear in the state (relative position, or range/bearing
# linearised about its prediction), the state enters the joint model only through the motion
# factor's bilinear term dAd/d delta * (delta - delta_lin) * (x - x_lin): with |delta - delta_lin|
# below 1e-4 and |dAd/d delta| ~ 4 over a 600 s step, a state 10 m (10 mm/s) from its
# linearisation point errs by ~4 mm. Relinearising it at 0.1 m instead re-ran ~20 Python motion
# factors per update for nothing: measured on bench_estimator's data, 10 m moves the estimates by
# at most 0.02 sigma (state) and 0.004 sigma (mean motion) and cuts the median CPU time 1.5-2.7x.
_STATE_RELINEARISE_LINEAR_MEASUREMENTS = 100.0 * _STATE_RELINEARISE
# A robust loss is iteratively reweighted least squares: each relinearisation recomputes the
# weights, and a fix a few sigma out needs more steps than a smooth nonlinearity to settle.
_MAX_EXTRA_ROBUST_STEPS = 10


@dataclass(frozen=True)
class TranslationEstimateResult:
    seq: int
    sim_time_s: float
    state_m_mps: np.ndarray            # (6,) newest smoothed state, SI
    covariance: np.ndarray             # (6, 6) its marginal covariance, SI
    mean_motion_radps: float | None    # the model's mean motion when it is estimated, else None
    mean_motion_std_radps: float | None
    failed_updates: int                # failed gtsam updates so far (each one re-initialised)
    reinitialised: bool                # this update restarted the smoother from the last good estimate
    # Normalised innovation squared of this step's measurement against the prediction (None
    # without a measurement or on the first fix), its degrees of freedom, whether the gate
    # rejected the measurement, and how many measurements the gate has rejected so far.
    nis: float | None = None
    nis_dof: int = 0
    measurement_rejected: bool = False
    rejected_measurements: int = 0
    # This step's fix ended a run of at least reacquire_after_rejections rejected ones (the
    # smoother re-acquired), and how many times that happened so far; the length of the current
    # run of consecutive rejected fixes.
    reacquired: bool = False
    reacquisitions: int = 0
    rejection_run: int = 0

    def covariance_row_major(self) -> list[float]:
        """The 36 numbers of TranslationEstimate.covariance."""
        return [float(v) for v in self.covariance.reshape(-1)]


@dataclass(frozen=True)
class _GoodEstimate:
    """The newest state and, when estimated, delta, with their *joint* covariance (6 or 7 square).

    Joint, not two marginals: a restart that dropped the state / mean-motion cross-covariance
    came back overconfident (average NEES 8 after an injected failure against 5.7 without).
    """
    seq: int
    joint: Gaussian          # [x (6, SI); delta] when the mean motion is estimated, else [x]

    @property
    def state(self) -> Gaussian:
        return Gaussian(self.joint.mean[:6], self.joint.covariance[:6, :6])

    @property
    def delta(self) -> float:
        """Relative mean-motion correction (0 when not estimated)."""
        return float(self.joint.mean[6]) if self.joint.mean.size == 7 else 0.0

    @property
    def delta_var(self) -> float:
        return float(self.joint.covariance[6, 6]) if self.joint.mean.size == 7 else 0.0


class TranslationSmoother(InnovationGate, RelativeMotion):
    """update(seq, sim_time_s, position_m | None, thrust_applied_n) -> TranslationEstimateResult | None.

    `params` are what the flight side believes (`Scenario.onboard_params()`): the smoother's
    model uses their orbit radius, and never sees the plant's.
    """

    def __init__(self, config: TranslationSmootherConfig, params: RendezvousParams):
        self.config = config
        self.believed_params = params
        self.believed_mean_motion_radps = self.believed_params.mean_motion
        # Beliefs left unset: the plant's default sensors (OnboardBeliefs fills them from a scenario).
        self.position_noise_std_m = _or(config.position_noise_std_m, RelativePositionSensorConfig().noise_std_m)
        self.range_noise_std_m = _or(config.range_noise_std_m, RangeBearingSensorConfig().range_noise_std_m)
        self.bearing_noise_std_rad = _or(config.bearing_noise_std_rad, RangeBearingSensorConfig().bearing_noise_std_rad)
        self.model = CwhMotionModel(params.mass_kg, params.time_step_s, _or(config.process_noise_psd_m2ps3, 0.0))
        self._two_body: TwoBodyRelativeModel | None = None
        if config.motion_model != "cwh":
            self._two_body = self._two_body_model(self.believed_mean_motion_radps)
        self.failed_updates = 0
        self.rejected_measurements = 0
        self.reacquisitions = 0
        self._run = RejectionRun()
        self.late_measurements_applied = 0
        self.late_measurements_dropped = 0     # older than the window: too late to use
        self._gate = (None if config.gate_probability is None
                      else {dof: nis_gate(config.gate_probability, dof) for dof in (3,)})
        self._smoother: gtsam.IncrementalFixedLagSmoother | None = None
        self._last: _GoodEstimate | None = None
        self._innovation: tuple[float | None, int, bool] = (None, 0, False)
        self._reacquired = False

    @property
    def estimates_mean_motion(self) -> bool:
        return self.config.estimate_mean_motion

    @property
    def linearises_measurements(self) -> bool:
        """Range/bearing factors linearised once, about the prediction (iterated), not relinearised.

        A robust loss needs gtsam's noise-model factor (its reweighting happens at linearisation).
        """
        return (self.config.sensor == "range_bearing" and self.config.range_bearing_linearisation == "prediction"
                and self.config.robust_loss == "none")

    @property
    def _relinearises_measurements(self) -> bool:
        """gtsam's nonlinear measurement factors (range/bearing, or any sensor with a robust loss,
        whose weights are recomputed at each linearisation), relinearised as the state moves."""
        return self.config.robust_loss != "none" or (self.config.sensor == "range_bearing"
                                                     and not self.linearises_measurements)

    @property
    def is_nonlinear(self) -> bool:
        """Unknown mean motion or relinearised range/bearing: relinearise and iterate."""
        return (self.config.estimate_mean_motion or self.config.robust_loss != "none"
                or (self.config.sensor == "range_bearing" and not self.linearises_measurements))

    def _measurement_factor(self, measurement: "Measurement", key: int, about: Gaussian):
        """The measurement's factor on `key`: linearised about `about` (the state's prediction or
        smoothed estimate) when the smoother linearises measurements, else gtsam's nonlinear one."""
        if self.linearises_measurements:
            return measurement.linearised_factor(key, about)
        return measurement.factor(key)

    @property
    def newest_seq(self) -> int | None:
        """The step of the newest estimate (None before the first fix)."""
        return None if self._last is None else self._last.seq

    # ---- public -------------------------------------------------------------------------------

    def update(self, seq: int, sim_time_s: float, position_m: np.ndarray | None,
               thrust_applied_n: np.ndarray, position_noise_std_m: float | None = None, *,
               range_bearing: np.ndarray | None = None) -> TranslationEstimateResult | None:
        """Add plant step `seq` and return the newest estimate (None until the first fix).

        thrust_applied_n: the thrust held over the step from the previous update to this one (the
        command issued at the previous step); ignored on the first update.
        position_m / position_noise_std_m: the relative-position fix (sensor "relpos"), or None.
        range_bearing: [range m, azimuth rad, elevation rad] (sensor "range_bearing"), or None.
        """
        thrust = _vector("thrust_applied_n", thrust_applied_n, 3)
        measurement = self._measurement_factor_builder(seq, position_m, position_noise_std_m, range_bearing)
        if self._last is not None and seq <= self._last.seq:
            raise ValueError(f"seq must increase: got {seq} after {self._last.seq}")

        self._innovation = (None, 0, False)
        self._reacquired = False
        if self._last is None:
            if measurement is None:
                return None
            try:
                return self._start_from_first_fix(seq, sim_time_s, measurement)
            except Exception as exc:
                self.failed_updates += 1
                log.warning("translation smoother could not start at step %d (%d failures so far): %s",
                            seq, self.failed_updates, exc)
                self._last = None
                return None
        predicted = self._predict_last(seq, thrust)
        self._run.propagate(self, seq, thrust)
        measurement, track = self._screen(seq, measurement, predicted)
        if track is not None:
            return self._reacquire(seq, sim_time_s, track)
        if self._smoother is None:
            return self._restart(seq, sim_time_s, thrust, measurement)

        graph, guess = self._step_factors(seq, thrust, measurement, predicted)
        try:
            return self._apply(self._smoother, seq, sim_time_s, graph, guess)
        except Exception as exc:        # gtsam raises RuntimeError subclasses; never let one out
            self.failed_updates += 1
            log.warning("translation smoother update %d failed (%d so far): %s; restarting from "
                        "the estimate of step %d", seq, self.failed_updates, exc, self._last.seq)
            self._smoother = None
            return self._restart(seq, sim_time_s, thrust, measurement)

    def add_late_measurement(self, sensed_seq: int, position_m: np.ndarray | None = None,
                             position_noise_std_m: float | None = None, *,
                             range_bearing: np.ndarray | None = None) -> TranslationEstimateResult | None:
        """A measurement sensed at step `sensed_seq` that arrives after later steps were added.

        Applied at its sensing time (on that step's state) when the step is still inside the
        smoother's window, and the newest estimate returned; otherwise it is dropped, counted
        (`late_measurements_dropped`) and None returned. Gated like an on-time measurement, with
        the NIS taken against the smoothed state of that step (which has not seen it).
        """
        if self._last is not None and sensed_seq > self._last.seq:
            raise ValueError(f"sensed_seq {sensed_seq} is not late: the newest step is {self._last.seq}")
        measurement = self._measurement_factor_builder(sensed_seq, position_m, position_noise_std_m, range_bearing)
        key = state_key(sensed_seq)
        if measurement is None:
            return None
        if self._smoother is None or key not in self._smoother.timestamps():
            self.late_measurements_dropped += 1
            log.warning("measurement of step %d arrived outside the smoother's window (newest step %s); dropped",
                        sensed_seq, None if self._last is None else self._last.seq)
            return None
        smoothed = Gaussian(np.asarray(self._smoother.calculateEstimateVector(key), dtype=float),
                            np.asarray(self._smoother.marginalCovariance(key), dtype=float))
        measurement = self._check_innovation(measurement, smoothed)
        if measurement is None:
            return self._result(self._last.seq, self._newest_time_s, self._last, reinitialised=False)
        graph = gtsam.NonlinearFactorGraph()
        graph.add(self._measurement_factor(measurement, key, smoothed))
        try:
            result = self._apply(self._smoother, self._last.seq, self._newest_time_s, graph, gtsam.Values(),
                                 measured_key=key)
        except Exception as exc:
            # The smoother may be half-updated: the next step restarts from the last good estimate.
            self.failed_updates += 1
            log.warning("late measurement of step %d failed in gtsam (%d failures so far): %s",
                        sensed_seq, self.failed_updates, exc)
            self._smoother = None
            return None
        self.late_measurements_applied += 1
        return result

    # ---- factor construction ------------------------------------------------------------------

    def _measurement_factor_builder(self, seq, position_m, position_noise_std_m, range_bearing):
        """A function key -> measurement factor for this step, or None if no measurement is used."""
        sensor = self.config.sensor
        if sensor == "relpos" and range_bearing is not None:
            raise ValueError("range_bearing given but estimator.translation.sensor is 'relpos'")
        if sensor == "range_bearing" and position_m is not None:
            raise ValueError("position_m given but estimator.translation.sensor is 'range_bearing'")
        if seq < 0:
            raise ValueError(f"seq must be non-negative, got {seq}")
        measured = position_m if sensor == "relpos" else range_bearing
        if measured is None or seq % self.config.measurement_every_steps != 0:
            return None
        if sensor == "relpos":
            position = _vector("position_m", position_m, 3)
            std = self.position_noise_std_m if position_noise_std_m is None else position_noise_std_m
            if not (np.isfinite(std) and std > 0):
                raise ValueError(f"position_noise_std_m must be positive and finite, got {std}")
            if self._robust_loss() is None:
                whiten = np.eye(3) / std     # isotropic: no factorisation needed
                factor = lambda key: factors.linear_factor([(key, POSITION_MATRIX)], position, whiten=whiten)  # noqa: E731
            else:
                noise = gtsam.noiseModel.Robust.Create(self._robust_loss(), gtsam.noiseModel.Isotropic.Sigma(3, std))
                factor = lambda key: factors.position_factor(key, position, noise)  # noqa: E731
            return Measurement(factor, position, relpos_residual(position), np.full(3, std**2))
        rb = _vector("range_bearing", range_bearing, 3)
        if rb[0] <= 0:
            raise ValueError(f"range_bearing range must be positive, got {rb[0]} m")
        sigmas = np.array([self.range_noise_std_m, self.bearing_noise_std_rad, self.bearing_noise_std_rad])
        noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
        if self._robust_loss() is not None:
            noise = gtsam.noiseModel.Robust.Create(self._robust_loss(), noise)
        return Measurement(lambda key: factors.range_bearing_factor(key, rb, noise),
                            position_from_range_bearing(rb), range_bearing_residual(rb), sigmas**2)

    def _robust_loss(self):
        """gtsam's m-estimator for the measurement factors, or None for plain least squares.

        Its threshold is on the whitened residual's norm (sigma units): a 3-D Gaussian residual
        has a norm below 3 in 97 % of samples, so the default 3 leaves those at full weight.
        """
        loss, k = self.config.robust_loss, self.config.robust_threshold_sigma
        if loss == "huber":
            return gtsam.noiseModel.mEstimator.Huber.Create(k)
        if loss == "cauchy":
            return gtsam.noiseModel.mEstimator.Cauchy.Create(k)
        return None

    def _step_factors(self, seq: int, thrust: np.ndarray, measurement: "Measurement | None", predicted: Gaussian):
        n_steps = seq - self._last.seq
        graph = gtsam.NonlinearFactorGraph()
        graph.add(self._motion_factor(seq, n_steps, thrust))
        if measurement is not None:
            graph.add(self._measurement_factor(measurement, state_key(seq), predicted))
        return graph, predicted.mean[:6]

    # ---- starting and restarting --------------------------------------------------------------

    def _reacquire(self, seq: int, sim_time_s: float, track: Gaussian) -> TranslationEstimateResult:
        """The smoother restarted from the track of the consistent rejected fixes (this one included):
        the old estimate disagreed with all of them, so its history is dropped."""
        self._smoother = None
        try:
            return self._start(seq, sim_time_s, gtsam.NonlinearFactorGraph(), track, reinitialised=False)
        except Exception as exc:
            self.failed_updates += 1
            log.warning("re-acquisition at step %d failed in gtsam (%d failures so far): %s; publishing the track",
                        seq, self.failed_updates, exc)
            self._last = _GoodEstimate(seq, track)
            return self._result(seq, sim_time_s, self._last, reinitialised=True)

    def _start_from_first_fix(self, seq: int, sim_time_s: float, measurement: "Measurement"):
        # The first fix gives the position; the prior the velocity (and delta, around zero). The
        # prior's position is left free: an information-form prior with zero weight there.
        key = state_key(seq)
        graph = gtsam.NonlinearFactorGraph()
        velocity_rows = np.hstack([np.zeros((3, 3)), np.eye(3)])
        graph.add(factors.linear_factor(
            [(key, velocity_rows)], np.zeros(3), np.eye(3) * self.config.initial_velocity_std_mps**2))
        graph.add(measurement.factor(key))
        guess = gtsam.Values()
        guess.insert(key, np.concatenate([measurement.position_guess_m, np.zeros(3)]))
        if self.estimates_mean_motion:
            graph.add(factors.prior_factor(MEAN_MOTION_KEY, np.zeros(1), np.array([[self.config.mean_motion_prior_rel_std**2]])))
            guess.insert(MEAN_MOTION_KEY, np.zeros(1))
        smoother = gtsam.IncrementalFixedLagSmoother(float(self.config.lag_steps), self._isam_params())
        result = self._apply(smoother, seq, sim_time_s, graph, guess)
        self._smoother = smoother
        return result

    def _restart(self, seq: int, sim_time_s: float, thrust: np.ndarray, measurement):
        """New smoother at `seq` whose prior is the last good joint estimate carried to `seq`."""
        predicted = self._predict_last(seq, thrust)
        graph = gtsam.NonlinearFactorGraph()
        if measurement is not None:
            graph.add(self._measurement_factor(measurement, state_key(seq), predicted))
        try:
            return self._start(seq, sim_time_s, graph, predicted, reinitialised=True)
        except Exception as exc:
            # Even the restart failed: report the prediction, and try again next step.
            self.failed_updates += 1
            log.warning("translation smoother restart at step %d failed (%d so far): %s; "
                        "publishing the prediction", seq, self.failed_updates, exc)
            self._smoother = None
            self._last = _GoodEstimate(seq, predicted)
            return self._result(seq, sim_time_s, self._last, reinitialised=True)

    def _start(self, seq, sim_time_s, graph, prior: Gaussian, reinitialised: bool):
        """A new smoother at `seq` with `graph` plus one joint prior ([x] or [x; delta]) on its keys."""
        smoother = gtsam.IncrementalFixedLagSmoother(float(self.config.lag_steps), self._isam_params())
        keys = [state_key(seq)] + ([MEAN_MOTION_KEY] if self.estimates_mean_motion else [])
        selectors = np.split(np.eye(prior.mean.size), [6], axis=1)
        graph.add(factors.linear_factor(list(zip(keys, selectors)), prior.mean, prior.covariance))
        guess_values = gtsam.Values()
        guess_values.insert(state_key(seq), np.asarray(prior.mean[:6], dtype=float))
        if self.estimates_mean_motion:
            guess_values.insert(MEAN_MOTION_KEY, np.asarray(prior.mean[6:], dtype=float))
        result = self._apply(smoother, seq, sim_time_s, graph, guess_values, reinitialised=reinitialised)
        self._smoother = smoother
        return result

    def _isam_params(self) -> gtsam.ISAM2Params:
        params = gtsam.ISAM2Params()
        # QR, not iSAM2's default Cholesky: with a fix only every second step (or rarer) the
        # first states are jointly so badly conditioned (condition number ~2e10: a position
        # known to metres, a velocity prior of 10 m/s, a 600 s step) that forming the normal
        # equations squares it past double precision and Cholesky reports an "indeterminate
        # linear system". QR works on the Jacobian itself, whose condition number is the square
        # root of the normal equations'. Measured: 0 failures on every measurement pattern of
        # tests/test_estimator_translation.py (1 to 51 per 60 steps with Cholesky).
        params.setFactorization("QR")
        gauss_newton = gtsam.ISAM2GaussNewtonParams()
        # Update every variable's delta every time (the window is small): the newest estimate is
        # then the exact least-squares solution, equal to a Kalman filter's for the linear model.
        gauss_newton.setWildfireThreshold(0.0)
        params.setOptimizationParams(gauss_newton)
        if not self.is_nonlinear:
            # Every factor is linear and exact at any linearisation point: relinearising (iSAM2's
            # default, every 10th update) re-eliminates the whole window for nothing, a periodic
            # spike in the update time.
            params.enableRelinearization = False
        else:
            thresholds = gtsam.ISAM2ThresholdMap()
            thresholds.insert(("x", _STATE_RELINEARISE if self._relinearises_measurements
                                    else _STATE_RELINEARISE_LINEAR_MEASUREMENTS))
            thresholds.insert(("n", _DELTA_RELINEARISE))
            params.setRelinearizeThreshold(thresholds)
            params.relinearizeSkip = 1
        return params

    # ---- solving ------------------------------------------------------------------------------

    def _apply(self, smoother, seq, sim_time_s, graph, guess, reinitialised: bool = False, measured_key=None):
        if not isinstance(guess, gtsam.Values):
            values = gtsam.Values()
            values.insert(state_key(seq), np.asarray(guess, dtype=float))
            guess = values
        stamps = gtsam.FixedLagSmootherKeyTimestampMap()
        stamps.insert((state_key(seq), float(seq)))
        if self.estimates_mean_motion:
            stamps.insert((MEAN_MOTION_KEY, float(seq)))   # keep delta inside the window
        smoother.update(graph, guess, stamps)
        if self.is_nonlinear:
            # iSAM2 takes one Gauss-Newton step per update. While the newest keys' step is still
            # above the relinearisation thresholds (their first linearisation point, a prediction,
            # can be kilometres off early on), take more, up to a bound.
            extra_steps = _MAX_EXTRA_ROBUST_STEPS if self.config.robust_loss != "none" else _MAX_EXTRA_GAUSS_NEWTON_STEPS
            for _ in range(extra_steps):
                if not self._newest_step_is_large(smoother, seq, measured_key):
                    break
                smoother.update()
        good = self._read_estimate(smoother, seq)
        self._last = good
        self._newest_time_s = float(sim_time_s)
        return self._result(seq, sim_time_s, good, reinitialised)

    def _newest_step_is_large(self, smoother, seq: int, measured_key=None) -> bool:
        """Would another Gauss-Newton step relinearise a variable whose linearisation matters?

        The newest state enters its motion factor linearly, so only a range/bearing or robust
        factor cares where it is linearised; delta enters every motion factor nonlinearly.
        """
        delta = smoother.getDelta()
        key = state_key(seq) if measured_key is None else measured_key
        if self._relinearises_measurements and np.any(np.abs(delta.at(key)) > _STATE_RELINEARISE):
            return True
        return self.estimates_mean_motion and abs(delta.at(MEAN_MOTION_KEY)[0]) > _DELTA_RELINEARISE[0]

    def _read_estimate(self, smoother, seq: int) -> _GoodEstimate:
        key = state_key(seq)
        mean = np.asarray(smoother.calculateEstimateVector(key), dtype=float)
        if self.estimates_mean_motion:
            delta = np.asarray(smoother.calculateEstimateVector(MEAN_MOTION_KEY), dtype=float)
            mean = np.concatenate([mean, delta])
            # fullMatrix() is in the query keys' order (checked against its blocks, tests).
            cov = np.asarray(smoother.getISAM2().jointMarginalCovariance([key, MEAN_MOTION_KEY]).fullMatrix())
        else:
            cov = np.asarray(smoother.marginalCovariance(key), dtype=float)
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
            raise RuntimeError(f"non-finite estimate at step {seq}")
        return _GoodEstimate(seq, Gaussian(mean, 0.5 * (cov + cov.T)))

    def _result(self, seq, sim_time_s, good: _GoodEstimate, reinitialised: bool) -> TranslationEstimateResult:
        n_mean = n_std = None
        if self.estimates_mean_motion:
            n_mean = self._mean_motion(good.delta)
            n_std = self.believed_mean_motion_radps * float(np.sqrt(good.delta_var))
        return TranslationEstimateResult(
            seq=seq, sim_time_s=float(sim_time_s),
            state_m_mps=good.state.mean.copy(), covariance=good.state.covariance.copy(),
            mean_motion_radps=n_mean, mean_motion_std_radps=n_std,
            failed_updates=self.failed_updates, reinitialised=reinitialised,
            nis=self._innovation[0], nis_dof=self._innovation[1], measurement_rejected=self._innovation[2],
            rejected_measurements=self.rejected_measurements,
            reacquired=self._reacquired, reacquisitions=self.reacquisitions, rejection_run=self._run.length,
        )


def _vector(name: str, value, size: int) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be {size} numbers, got {value!r}") from None
    if v.size != size:
        raise ValueError(f"{name} must have {size} elements, got {v.size}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} has non-finite entries: {v}")
    return v


def _or(value, default):
    return default if value is None else value
