"""Estimator error against ground truth, with the estimator's own 3-sigma bounds."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.bus import keys
from bench.report.rundata import RunData

AXES = ("x", "y", "z", "vx", "vy", "vz")
# The first estimates carry the initial velocity prior (10 m/s) and the first fixes: their
# velocity error is metres per second where the converged one is millimetres per second, so an
# RMS over all samples is the first sample's. The smoother's velocity sigma has settled to within
# a factor of 2 of its final value after ~10 fixes; the report's RMS is over the samples after.
CONVERGENCE_SAMPLES = 10


@dataclass
class EstimationResult:
    sim_time_s: np.ndarray       # (n,)
    error: np.ndarray            # (n, 6) estimate - truth, m and m/s
    bound_3sigma: np.ndarray     # (n, 6), NaN where the estimate had no covariance
    nis: np.ndarray | None = None            # (n,) NIS of each step's measurement, NaN without one
    nis_dof: int = 0
    rejected: np.ndarray | None = None       # (n,) the innovation gate rejected the measurement
    # The smoother re-acquires on a fix used after at least this many rejected in a row (None: no gate).
    reacquire_after_rejections: int | None = None

    def to_metrics(self) -> dict:
        rms = np.sqrt(np.mean(self.error**2, axis=0))
        converged = self.error[CONVERGENCE_SAMPLES:] if len(self.error) > CONVERGENCE_SAMPLES else self.error
        rms_converged = np.sqrt(np.mean(converged**2, axis=0))
        median = np.median(np.abs(self.error), axis=0)
        inside = np.abs(self.error) <= self.bound_3sigma
        has_bound = ~np.isnan(self.bound_3sigma)
        nis = None if self.nis is None else self.nis[np.isfinite(self.nis)]
        return {
            "samples": int(self.error.shape[0]),
            "rms_error": {axis: float(v) for axis, v in zip(AXES, rms)},
            "rms_error_converged": {axis: float(v) for axis, v in zip(AXES, rms_converged)},
            "converged_after_samples": CONVERGENCE_SAMPLES,
            "median_abs_error": {axis: float(v) for axis, v in zip(AXES, median)},
            "fraction_within_3sigma": float(inside[has_bound].mean()) if has_bound.any() else None,
            "mean_nis": float(nis.mean()) if nis is not None and nis.size else None,
            "nis_dof": self.nis_dof,
            "rejected_measurements": int(self.rejected.sum()) if self.rejected is not None else 0,
            **self._rejection_runs(),
        }

    def _rejection_runs(self) -> dict:
        """Runs of consecutive rejected measurements (steps without one do not break a run), the
        mean NIS of the measurements used, and re-acquisitions: a used measurement after a run
        of at least reacquire_after_rejections rejected ones, as the smoother counts them."""
        if self.rejected is None or self.nis is None:
            return {"mean_nis_accepted": None, "rejection_runs": 0, "longest_rejection_run": 0, "reacquisitions": 0}
        used = np.isfinite(self.nis) & ~self.rejected
        runs, current, reacquisitions = [], 0, 0
        for has_measurement, rejected in zip(np.isfinite(self.nis), self.rejected):
            if rejected:
                current += 1
            elif has_measurement:
                if current:
                    runs.append(current)
                    limit = self.reacquire_after_rejections
                    reacquisitions += limit is not None and current >= limit
                current = 0
        if current:
            runs.append(current)
        return {"mean_nis_accepted": float(self.nis[used].mean()) if used.any() else None,
                "rejection_runs": len(runs), "longest_rejection_run": max(runs, default=0),
                "reacquisitions": int(reacquisitions)}


def estimation_error(run: RunData) -> EstimationResult | None:
    """None where no estimator ran against truth (truth mode passes truth through: error 0)."""
    if run.scenario is None or run.scenario.estimator.mode == "truth":
        return None
    truth = {m.seq: m.body for m in run.on(keys.TRUTH)}
    rows = []
    for m in run.on(keys.ESTIMATE_TRANSLATION):
        if m.seq not in truth or not m.body.get("valid", True):   # no estimate before the first fix
            continue
        error = np.asarray(m.body["state_m_mps"]) - np.asarray(truth[m.seq]["state_m_mps"])
        cov = m.body.get("covariance")
        bound = 3.0 * np.sqrt(np.diag(np.reshape(cov, (6, 6)))) if cov else np.full(6, np.nan)
        nis = m.body.get("nis")
        rows.append((m.body["header"]["sim_time_s"], error, bound, np.nan if nis is None else nis,
                     m.body.get("nis_dof", 0), bool(m.body.get("measurement_rejected", False))))
    if not rows:
        return None
    t, e, b, nis, dof, rejected = zip(*rows)
    translation = run.scenario.estimator.translation
    reacquire_after = None if translation.gate_probability is None else translation.reacquire_after_rejections
    return EstimationResult(np.asarray(t), np.vstack(e), np.vstack(b), np.asarray(nis, dtype=float),
                            int(max(dof)), np.asarray(rejected), reacquire_after)
