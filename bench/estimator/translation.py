"""Translational state estimation: gtsam incremental fixed-lag smoothing of the CWH relative state.

One state key x_k (6, SI) per plant step k. Factors:
- motion between k-1 and k from the discretised CWH model with the thrust commanded at k-1 (the
  thrust the plant held over the step), whitened by the assumed process noise;
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
from dataclasses import dataclass, replace

import gtsam
import numpy as np

from bench.estimator import factors
from bench.estimator.config import TranslationSmootherConfig
from bench.estimator.kalman import POSITION_MATRIX, Gaussian, predict
from bench.estimator.motion_model import CwhMotionModel
from bench.gnc.cwh import RendezvousParams

log = logging.getLogger(__name__)

MEAN_MOTION_KEY = gtsam.symbol("n", 0)

# Nonlinear variants (joint mean motion, range/bearing): relinearise a state that moved by more
# than 0.1 m or 0.1 mm/s, delta by more than 1e-4. A bearing linearised 0.1 m off at range r errs
# by ~(0.1 m)^2 / r, a millimetre at the 100 m terminal distance. delta enters the motion model
# smoothly: a 1e-4 step leaves a second-order residual error of millimetres, while relinearising
# delta relinearises every motion factor in the window (a Python callback each).
_STATE_RELINEARISE = np.array([0.1, 0.1, 0.1, 1e-4, 1e-4, 1e-4])
_DELTA_RELINEARISE = np.array([1e-4])
_MAX_EXTRA_GAUSS_NEWTON_STEPS = 3


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

    def covariance_row_major(self) -> list[float]:
        """The 36 numbers of TranslationEstimate.covariance."""
        return [float(v) for v in self.covariance.reshape(-1)]


@dataclass(frozen=True)
class _GoodEstimate:
    seq: int
    state: Gaussian
    delta: float             # relative mean-motion correction (0 when not estimated)
    delta_var: float


class TranslationSmoother:
    """update(seq, sim_time_s, position_m | None, thrust_applied_n) -> TranslationEstimateResult | None.

    `params` are what the flight side believes (`Scenario.onboard_params()`): the smoother's
    model uses their orbit radius, and never sees the plant's.
    """

    def __init__(self, config: TranslationSmootherConfig, params: RendezvousParams):
        self.config = config
        self.believed_params = params
        self.believed_mean_motion_radps = self.believed_params.mean_motion
        self.model = CwhMotionModel(params.mass_kg, params.time_step_s, config.process_noise_psd_m2ps3)
        self.failed_updates = 0
        self._smoother: gtsam.IncrementalFixedLagSmoother | None = None
        self._last: _GoodEstimate | None = None

    @property
    def estimates_mean_motion(self) -> bool:
        return self.config.estimate_mean_motion

    @property
    def is_nonlinear(self) -> bool:
        """Unknown mean motion or range/bearing: relinearise and iterate, the model is not linear."""
        return self.config.estimate_mean_motion or self.config.sensor == "range_bearing"

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
        if self._smoother is None:
            return self._restart(seq, sim_time_s, thrust, measurement)

        graph, guess = self._step_factors(seq, thrust, measurement)
        try:
            return self._apply(self._smoother, seq, sim_time_s, graph, guess)
        except Exception as exc:        # gtsam raises RuntimeError subclasses; never let one out
            self.failed_updates += 1
            log.warning("translation smoother update %d failed (%d so far): %s; restarting from "
                        "the estimate of step %d", seq, self.failed_updates, exc, self._last.seq)
            self._smoother = None
            return self._restart(seq, sim_time_s, thrust, measurement)

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
            std = self.config.position_noise_std_m if position_noise_std_m is None else position_noise_std_m
            if not (np.isfinite(std) and std > 0):
                raise ValueError(f"position_noise_std_m must be positive and finite, got {std}")
            whiten = np.eye(3) / std     # isotropic: no factorisation needed
            return _Measurement(
                lambda key: factors.linear_factor([(key, POSITION_MATRIX)], position, whiten=whiten),
                position,
            )
        rb = _vector("range_bearing", range_bearing, 3)
        if rb[0] <= 0:
            raise ValueError(f"range_bearing range must be positive, got {rb[0]} m")
        return _Measurement(
            lambda key: factors.range_bearing_factor(
                key, rb, self.config.range_noise_std_m, self.config.bearing_noise_std_rad),
            _position_from_range_bearing(rb),
        )

    def _motion_factor(self, seq: int, n_steps: int, thrust: np.ndarray):
        previous, key = state_key(seq - n_steps), state_key(seq)
        if self.estimates_mean_motion:
            return factors.cwh_motion_factor_unknown_mean_motion(
                previous, key, MEAN_MOTION_KEY, thrust, n_steps, self.model, self.believed_mean_motion_radps)
        m = self.model.discrete(self.believed_mean_motion_radps, n_steps)
        return factors.cwh_motion_factor(previous, key, thrust, m)

    def _step_factors(self, seq: int, thrust: np.ndarray, measurement: "_Measurement | None"):
        n_steps = seq - self._last.seq
        graph = gtsam.NonlinearFactorGraph()
        graph.add(self._motion_factor(seq, n_steps, thrust))
        if measurement is not None:
            graph.add(measurement.factor(state_key(seq)))
        guess = self._predict_last(seq, thrust).mean
        return graph, guess

    def _predict_last(self, seq: int, thrust: np.ndarray) -> Gaussian:
        last, n_steps = self._last, seq - self._last.seq
        process_cov = self.model.discrete(self.believed_mean_motion_radps, n_steps).process_cov
        if self.estimates_mean_motion:
            transition, input_matrix = self.model.transition_and_input(self._mean_motion(last.delta), n_steps)
        else:
            m = self.model.discrete(self.believed_mean_motion_radps, n_steps)
            transition, input_matrix = m.transition, m.input_matrix
        return predict(last.state, transition, input_matrix, thrust, process_cov)

    def _mean_motion(self, delta: float) -> float:
        return self.believed_mean_motion_radps * (1.0 + delta)

    # ---- starting and restarting --------------------------------------------------------------

    def _start_from_first_fix(self, seq: int, sim_time_s: float, measurement: "_Measurement"):
        key = state_key(seq)
        graph = gtsam.NonlinearFactorGraph()
        velocity_rows = np.hstack([np.zeros((3, 3)), np.eye(3)])
        graph.add(factors.linear_factor(
            [(key, velocity_rows)], np.zeros(3), np.eye(3) * self.config.initial_velocity_std_mps**2))
        graph.add(measurement.factor(key))
        guess = np.concatenate([measurement.position_guess_m, np.zeros(3)])
        delta_prior = (0.0, self.config.mean_motion_prior_rel_std**2)
        return self._start(seq, sim_time_s, graph, guess, delta_prior, reinitialised=False)

    def _restart(self, seq: int, sim_time_s: float, thrust: np.ndarray, measurement):
        """New smoother at `seq` whose prior is the last good estimate carried to `seq`."""
        predicted = self._predict_last(seq, thrust)
        graph = gtsam.NonlinearFactorGraph()
        graph.add(factors.prior_factor(state_key(seq), predicted.mean, predicted.covariance))
        if measurement is not None:
            graph.add(measurement.factor(state_key(seq)))
        delta_prior = (self._last.delta, self._last.delta_var)
        try:
            return self._start(seq, sim_time_s, graph, predicted.mean, delta_prior, reinitialised=True)
        except Exception as exc:
            # Even the restart failed: report the prediction, and try again next step.
            self.failed_updates += 1
            log.warning("translation smoother restart at step %d failed (%d so far): %s; "
                        "publishing the prediction", seq, self.failed_updates, exc)
            self._smoother = None
            self._last = replace(self._last, seq=seq, state=predicted)
            return self._result(seq, sim_time_s, self._last, reinitialised=True)

    def _start(self, seq, sim_time_s, graph, guess, delta_prior, reinitialised: bool):
        smoother = gtsam.IncrementalFixedLagSmoother(float(self.config.lag_steps), self._isam_params())
        guess_values = gtsam.Values()
        guess_values.insert(state_key(seq), np.asarray(guess, dtype=float))
        if self.estimates_mean_motion:
            delta_mean, delta_var = delta_prior
            graph.add(factors.prior_factor(MEAN_MOTION_KEY, np.array([delta_mean]), np.array([[delta_var]])))
            guess_values.insert(MEAN_MOTION_KEY, np.array([delta_mean]))
        result = self._apply(smoother, seq, sim_time_s, graph, guess_values, reinitialised=reinitialised)
        self._smoother = smoother
        return result

    def _isam_params(self) -> gtsam.ISAM2Params:
        params = gtsam.ISAM2Params()
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
            thresholds.insert(("x", _STATE_RELINEARISE))
            thresholds.insert(("n", _DELTA_RELINEARISE))
            params.setRelinearizeThreshold(thresholds)
            params.relinearizeSkip = 1
        return params

    # ---- solving ------------------------------------------------------------------------------

    def _apply(self, smoother, seq, sim_time_s, graph, guess, reinitialised: bool = False):
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
            for _ in range(_MAX_EXTRA_GAUSS_NEWTON_STEPS):
                if not self._newest_step_is_large(smoother, seq):
                    break
                smoother.update()
        good = self._read_estimate(smoother, seq)
        self._last = good
        return self._result(seq, sim_time_s, good, reinitialised)

    def _newest_step_is_large(self, smoother, seq: int) -> bool:
        """Would another Gauss-Newton step relinearise a variable whose linearisation matters?

        The newest state enters its motion factor linearly, so only a range/bearing factor cares
        where it is linearised; delta enters every motion factor nonlinearly.
        """
        delta = smoother.getDelta()
        if self.config.sensor == "range_bearing" and np.any(np.abs(delta.at(state_key(seq))) > _STATE_RELINEARISE):
            return True
        return self.estimates_mean_motion and abs(delta.at(MEAN_MOTION_KEY)[0]) > _DELTA_RELINEARISE[0]

    def _read_estimate(self, smoother, seq: int) -> _GoodEstimate:
        key = state_key(seq)
        mean = np.asarray(smoother.calculateEstimateVector(key), dtype=float)
        cov = np.asarray(smoother.marginalCovariance(key), dtype=float)
        delta, delta_var = 0.0, 0.0
        if self.estimates_mean_motion:
            delta = float(smoother.calculateEstimateVector(MEAN_MOTION_KEY)[0])
            delta_var = float(np.asarray(smoother.marginalCovariance(MEAN_MOTION_KEY))[0, 0])
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov)) and np.isfinite(delta)):
            raise RuntimeError(f"non-finite estimate at step {seq}")
        return _GoodEstimate(seq, Gaussian(mean, 0.5 * (cov + cov.T)), delta, delta_var)

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
        )


@dataclass(frozen=True)
class _Measurement:
    factor: object                 # key -> gtsam factor
    position_guess_m: np.ndarray   # where the measurement puts the chaser (initial guess only)


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


def _position_from_range_bearing(rb: np.ndarray) -> np.ndarray:
    rng, azimuth, elevation = rb
    return rng * np.array([np.cos(elevation) * np.cos(azimuth),
                           np.cos(elevation) * np.sin(azimuth),
                           np.sin(elevation)])
