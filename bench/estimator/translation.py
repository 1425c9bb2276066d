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
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np
import scipy.linalg

from bench.estimator import factors
from bench.estimator.config import TranslationSmootherConfig
from bench.estimator.gating import nis_gate
from bench.estimator.kalman import POSITION_MATRIX, Gaussian, predict
from bench.estimator.motion_model import CwhMotionModel
from bench.estimator.two_body_model import TwoBodyRelativeModel
from bench.gnc.cwh import RendezvousParams
from bench.gnc.range_bearing import position_from_range_bearing, wrap_angle_rad
from bench.plant.config import RangeBearingSensorConfig, RelativePositionSensorConfig

log = logging.getLogger(__name__)

MEAN_MOTION_KEY = gtsam.symbol("n", 0)

# Nonlinear variants (joint mean motion, range/bearing): relinearise a state that moved by more
# than 0.1 m or 0.1 mm/s, delta by more than 1e-4. A bearing linearised 0.1 m off at range r errs
# by ~(0.1 m)^2 / r, a millimetre at the 100 m terminal distance. delta enters the motion model
# smoothly: a 1e-4 step leaves a second-order residual error of millimetres, while relinearising
# delta relinearises every motion factor in the window (a Python callback each).
_STATE_RELINEARISE = np.array([0.1, 0.1, 0.1, 1e-4, 1e-4, 1e-4])
_DELTA_RELINEARISE = np.array([1e-4])
# When every measurement factor is linear in the state (relative position, or range/bearing
# linearised about its prediction), the state enters the joint model only through the motion
# factor's bilinear term dAd/d delta * (delta - delta_lin) * (x - x_lin): with |delta - delta_lin|
# below 1e-4 and |dAd/d delta| ~ 4 over a 600 s step, a state 10 m (10 mm/s) from its
# linearisation point errs by ~4 mm. Relinearising it at 0.1 m instead re-ran ~20 Python motion
# factors per update for nothing: measured on bench_estimator's data, 10 m moves the estimates by
# at most 0.02 sigma (state) and 0.004 sigma (mean motion) and cuts the median CPU time 1.5-2.7x.
_STATE_RELINEARISE_LINEAR_MEASUREMENTS = 100.0 * _STATE_RELINEARISE
_MAX_EXTRA_GAUSS_NEWTON_STEPS = 3
# A robust loss is iteratively reweighted least squares: each relinearisation recomputes the
# weights, and a fix a few sigma out needs more steps than a smooth nonlinearity to settle.
_MAX_EXTRA_ROBUST_STEPS = 10
# Position sigma of the prior a track of rejected fixes starts from: far wider than any fix, so
# the track is the fixes' own (its velocity prior is the smoother's initial one).
_TRACK_SEED_POSITION_STD_M = 1.0e4
# Prior of a burst's measurement bias, in measurement sigmas: uninformative next to any burst.
_BURST_BIAS_PRIOR_SIGMAS = 1.0e4


def state_key(seq: int) -> int:
    return gtsam.symbol("x", seq)


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


class TranslationSmoother:
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
        self._run = _RejectionRun()
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

    def _measurement_factor(self, measurement: "_Measurement", key: int, about: Gaussian):
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
            return _Measurement(factor, position, _relpos_residual(position), np.full(3, std**2))
        rb = _vector("range_bearing", range_bearing, 3)
        if rb[0] <= 0:
            raise ValueError(f"range_bearing range must be positive, got {rb[0]} m")
        sigmas = np.array([self.range_noise_std_m, self.bearing_noise_std_rad, self.bearing_noise_std_rad])
        noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
        if self._robust_loss() is not None:
            noise = gtsam.noiseModel.Robust.Create(self._robust_loss(), noise)
        return _Measurement(lambda key: factors.range_bearing_factor(key, rb, noise),
                            position_from_range_bearing(rb), _range_bearing_residual(rb), sigmas**2)

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

    def _step_factors(self, seq: int, thrust: np.ndarray, measurement: "_Measurement | None", predicted: Gaussian):
        n_steps = seq - self._last.seq
        graph = gtsam.NonlinearFactorGraph()
        graph.add(self._motion_factor(seq, n_steps, thrust))
        if measurement is not None:
            graph.add(self._measurement_factor(measurement, state_key(seq), predicted))
        return graph, predicted.mean[:6]

    def _screen(self, seq: int, measurement: "_Measurement | None",
                predicted: Gaussian) -> tuple["_Measurement | None", Gaussian | None]:
        """The gate of an on-time fix, which a run of outliers cannot walk open.

        Returns (the measurement, or None when rejected; the track to restart from when this fix
        re-acquires). A fix is rejected when its NIS against the prediction exceeds the gate, or,
        during a run of rejected fixes, when the track of those rejected fixes explains it better
        than the prediction by more than gate_burst_likelihood_ratio (it looks like the burst's
        next fix, however wide the prediction has grown). After reacquire_after_rejections
        rejected fixes, reacquire_consistent_fixes that agree with each other re-acquire.
        """
        if measurement is None:
            return None, None
        nis, innovation_cov = measurement.innovation(predicted)
        dof = measurement.dof
        if self._gate is None:
            self._innovation = (nis, dof, False)
            return measurement, None
        gate, run, config = self._gate[dof], self._run, self.config
        rejected = nis > gate
        if run.candidate is not None and not rejected:
            candidate_nis, candidate_cov = measurement.innovation(run.candidate, bias=True)
            # log of p(fix | it is offset like the run's rejected fixes) / p(fix | it is good)
            log_ratio = 0.5 * (nis - candidate_nis) + 0.5 * (_log_det(innovation_cov) - _log_det(candidate_cov))
            rejected = log_ratio > np.log(config.gate_burst_likelihood_ratio)
        if not rejected:
            if run.length >= config.reacquire_after_rejections:
                self.reacquisitions += 1
                self._reacquired = True
            self._run = _RejectionRun()
            self._innovation = (nis, dof, False)
            return measurement, None
        # Rejected. The hypothesis that the run's fixes are all offset by one unknown bias b (a
        # burst): the prediction with b appended (diffuse), corrected by them.
        if run.candidate is None:
            bias_var = (_BURST_BIAS_PRIOR_SIGMAS * np.sqrt(measurement.variances))**2
            run.candidate = Gaussian(np.concatenate([predicted.mean, np.zeros(dof)]),
                                     scipy.linalg.block_diag(predicted.covariance, np.diag(bias_var)))
        run.candidate = measurement.update(run.candidate, bias=True)
        # The track of the fixes alone: extended, or started anew from this fix when it does not
        # fit the track (the run's first fix, or an isolated outlier inside a run).
        track_nis = None if run.track is None else measurement.innovation(run.track)[0]
        if run.track is None or track_nis > gate:
            run.track = measurement.update(self._track_seed(measurement, predicted))
            run.fixes, run.track_seq = 1, seq
        else:
            run.track = measurement.update(run.track)
            run.fixes += 1
        if run.length >= config.reacquire_after_rejections and run.fixes >= config.reacquire_consistent_fixes:
            self.reacquisitions += 1
            self._reacquired = True
            self._innovation = (nis, dof, False)
            track, self._run = run.track, _RejectionRun()
            log.warning("step %d: %d fixes rejected in a row; re-acquired on the last %d, which agree with "
                        "each other", seq, run.length, run.fixes)
            return None, track
        run.length += 1
        self.rejected_measurements += 1
        self._innovation = (nis, dof, True)
        log.info("measurement of step %d rejected (NIS %.1f, gate %.1f, %d rejected in a row)", seq, nis, gate, run.length)
        return None, None

    def _track_seed(self, measurement: "_Measurement", predicted: Gaussian) -> Gaussian:
        """Where a track of rejected fixes starts: the fix alone (a position prior far wider than
        any fix, the smoother's initial velocity prior), the mean motion as predicted."""
        mean = predicted.mean.copy()
        mean[:3] = measurement.position_guess_m
        variances = [_TRACK_SEED_POSITION_STD_M**2] * 3 + [self.config.initial_velocity_std_mps**2] * 3
        if mean.size == 7:
            variances.append(predicted.covariance[6, 6])
        return Gaussian(mean, np.diag(variances))

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

    def _check_innovation(self, measurement: "_Measurement | None", predicted: Gaussian) -> "_Measurement | None":
        """NIS of a late measurement against its step's estimate; None in its place if the gate rejects it."""
        if measurement is None:
            return None
        nis = measurement.nis(predicted.mean[:6], predicted.covariance[:6, :6])
        dof = measurement.dof
        rejected = self._gate is not None and nis > self._gate[dof]
        self._innovation = (nis, dof, rejected)
        if rejected:
            self.rejected_measurements += 1
            log.info("measurement of step rejected by the innovation gate: NIS %.1f > %.1f", nis, self._gate[dof])
            return None
        return measurement

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

    # ---- starting and restarting --------------------------------------------------------------

    def _start_from_first_fix(self, seq: int, sim_time_s: float, measurement: "_Measurement"):
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


class _RejectionRun:
    """The current run of consecutive rejected fixes: the estimate had they been used, and the
    track the latest mutually consistent ones make on their own."""

    def __init__(self):
        self.length = 0                      # consecutive rejected fixes
        # [x (; delta); b]: the prediction corrected by the run's fixes, each offset by the bias b
        self.candidate: Gaussian | None = None
        self.track: Gaussian | None = None   # joint belief from the rejected fixes alone, at track_seq
        self.track_seq = 0
        self.fixes = 0                       # fixes in the track (each within the gate of the ones before)

    def propagate(self, smoother: "TranslationSmoother", seq: int, thrust: np.ndarray) -> None:
        """Carry the track to step `seq` with the smoother's model (the thrust held since its step)."""
        if self.track is not None and seq > self.track_seq:
            n_steps = seq - self.track_seq
            self.track = smoother._propagate(self.track, n_steps, thrust)
            self.candidate = smoother._propagate(self.candidate, n_steps, thrust)
            self.track_seq = seq


@dataclass(frozen=True)
class _Measurement:
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


def _relpos_residual(position: np.ndarray):
    return lambda state: (position - state[:3], POSITION_MATRIX)


def _range_bearing_residual(rb: np.ndarray):
    def residual(state):
        nu = rb - factors.range_bearing(state[:3])
        nu[1] = wrap_angle_rad(nu[1])    # azimuth wraps
        return nu, np.hstack([factors.range_bearing_jacobian(state[:3]), np.zeros((3, 3))])
    return residual


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


def _log_det(matrix: np.ndarray) -> float:
    sign, value = np.linalg.slogdet(matrix)
    return float(value) if sign > 0 else np.inf


def _or(value, default):
    return default if value is None else value
