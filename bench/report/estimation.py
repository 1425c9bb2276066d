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
        }


def estimation_error(run: RunData) -> EstimationResult | None:
    """None where no estimator ran against truth (truth mode passes truth through: error 0)."""
    if run.scenario is None or run.scenario.estimator.mode == "truth":
        return None
    truth = {m.seq: m.body for m in run.on(keys.TRUTH)}
    rows = []
    for m in run.on(keys.ESTIMATE_TRANSLATION):
        if m.seq not in truth:
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
    return EstimationResult(np.asarray(t), np.vstack(e), np.vstack(b), np.asarray(nis, dtype=float),
                            int(max(dof)), np.asarray(rejected))
