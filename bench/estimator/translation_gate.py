"""The translation smoother's innovation gate, which a run of outliers cannot walk open: a fix is
rejected when its NIS against the prediction exceeds the gate or, during a run of rejected fixes,
when the run's own track explains it better (a burst); enough mutually consistent rejected fixes
re-acquire. Late measurements are gated against their step's smoothed estimate.

InnovationGate is a part of TranslationSmoother (bench/estimator/translation.py), whose state it
reads and counts in: config, _gate, _run, _innovation, _reacquired, rejected_measurements,
reacquisitions, and its _propagate for the run's track.
"""
from __future__ import annotations

import logging

import numpy as np
import scipy.linalg

from bench.estimator.kalman import Gaussian
from bench.estimator.translation_measurement import Measurement
from bench.estimator.translation_motion import RelativeMotion

# The smoother's logger: these are its messages, as before the gate had a module of its own.
log = logging.getLogger("bench.estimator.translation")

# Position sigma of the prior a track of rejected fixes starts from: far wider than any fix, so
# the track is the fixes' own (its velocity prior is the smoother's initial one).
_TRACK_SEED_POSITION_STD_M = 1.0e4
# Prior of a burst's measurement bias, in measurement sigmas: uninformative next to any burst.
_BURST_BIAS_PRIOR_SIGMAS = 1.0e4


class RejectionRun:
    """The current run of consecutive rejected fixes: the estimate had they been used, and the
    track the latest mutually consistent ones make on their own."""

    def __init__(self):
        self.length = 0                      # consecutive rejected fixes
        # [x (; delta); b]: the prediction corrected by the run's fixes, each offset by the bias b
        self.candidate: Gaussian | None = None
        self.track: Gaussian | None = None   # joint belief from the rejected fixes alone, at track_seq
        self.track_seq = 0
        self.fixes = 0                       # fixes in the track (each within the gate of the ones before)

    def propagate(self, smoother: RelativeMotion, seq: int, thrust: np.ndarray) -> None:
        """Carry the track to step `seq` with the smoother's model (the thrust held since its step)."""
        if self.track is not None and seq > self.track_seq:
            n_steps = seq - self.track_seq
            self.track = smoother._propagate(self.track, n_steps, thrust)
            self.candidate = smoother._propagate(self.candidate, n_steps, thrust)
            self.track_seq = seq


class InnovationGate:
    """Screening the smoother's fixes (a mixin of TranslationSmoother)."""

    def _screen(self, seq: int, measurement: "Measurement | None",
                predicted: Gaussian) -> tuple["Measurement | None", Gaussian | None]:
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
            self._run = RejectionRun()
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
            track, self._run = run.track, RejectionRun()
            log.warning("step %d: %d fixes rejected in a row; re-acquired on the last %d, which agree with "
                        "each other", seq, run.length, run.fixes)
            return None, track
        run.length += 1
        self.rejected_measurements += 1
        self._innovation = (nis, dof, True)
        log.info("measurement of step %d rejected (NIS %.1f, gate %.1f, %d rejected in a row)", seq, nis, gate, run.length)
        return None, None

    def _track_seed(self, measurement: "Measurement", predicted: Gaussian) -> Gaussian:
        """Where a track of rejected fixes starts: the fix alone (a position prior far wider than
        any fix, the smoother's initial velocity prior), the mean motion as predicted."""
        mean = predicted.mean.copy()
        mean[:3] = measurement.position_guess_m
        variances = [_TRACK_SEED_POSITION_STD_M**2] * 3 + [self.config.initial_velocity_std_mps**2] * 3
        if mean.size == 7:
            variances.append(predicted.covariance[6, 6])
        return Gaussian(mean, np.diag(variances))

    def _check_innovation(self, measurement: "Measurement | None", predicted: Gaussian) -> "Measurement | None":
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


def _log_det(matrix: np.ndarray) -> float:
    sign, value = np.linalg.slogdet(matrix)
    return float(value) if sign > 0 else np.inf

