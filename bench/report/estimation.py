"""Estimator error against ground truth, with the estimator's own 3-sigma bounds."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.bus import keys
from bench.report.rundata import RunData

AXES = ("x", "y", "z", "vx", "vy", "vz")


@dataclass
class EstimationResult:
    sim_time_s: np.ndarray       # (n,)
    error: np.ndarray            # (n, 6) estimate - truth, m and m/s
    bound_3sigma: np.ndarray     # (n, 6), NaN where the estimate had no covariance

    def to_metrics(self) -> dict:
        rms = np.sqrt(np.mean(self.error**2, axis=0))
        inside = np.abs(self.error) <= self.bound_3sigma
        has_bound = ~np.isnan(self.bound_3sigma)
        return {
            "samples": int(self.error.shape[0]),
            "rms_error": {axis: float(v) for axis, v in zip(AXES, rms)},
            "fraction_within_3sigma": float(inside[has_bound].mean()) if has_bound.any() else None,
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
        rows.append((m.body["header"]["sim_time_s"], error, bound))
    if not rows:
        return None
    t, e, b = zip(*rows)
    return EstimationResult(np.asarray(t), np.vstack(e), np.vstack(b))
