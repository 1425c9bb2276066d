"""Report figure: estimation error against its 3-sigma bounds, one panel per state.

Plotting the error (estimate - truth) rather than the two curves: on a 400 km approach a 10 m
error is invisible next to the trajectory, but against +-3 sigma it shows at once whether the
covariance the controller is told is honest.
"""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

STATE_LABELS = ("x [m]", "y [m]", "z [m]", "vx [m/s]", "vy [m/s]", "vz [m/s]")


def plot_estimate_vs_truth(time_s: np.ndarray, truth: np.ndarray, estimate: np.ndarray,
                           covariance: np.ndarray, path: str | Path,
                           labels: tuple[str, ...] = STATE_LABELS, title: str = "estimate - truth, +-3 sigma") -> Path:
    """Write the figure to `path` (PNG) and return it. truth, estimate: (N, n); covariance: (N, n, n)."""
    time_s, truth, estimate, covariance = (np.asarray(a, dtype=float) for a in (time_s, truth, estimate, covariance))
    n_samples, n_states = estimate.shape
    if truth.shape != estimate.shape or time_s.shape != (n_samples,) or covariance.shape != (n_samples, n_states, n_states):
        raise ValueError(
            f"plot_estimate_vs_truth: shapes disagree: time {time_s.shape}, truth {truth.shape}, "
            f"estimate {estimate.shape}, covariance {covariance.shape}")
    if len(labels) != n_states:
        raise ValueError(f"plot_estimate_vs_truth: {len(labels)} labels for {n_states} states")
    error = estimate - truth
    three_sigma = 3.0 * np.sqrt(np.diagonal(covariance, axis1=1, axis2=2))
    hours = time_s / 3600.0
    rows = (n_states + 1) // 2
    fig, axes = plt.subplots(rows, 2, figsize=(10, 2.2 * rows), sharex=True, squeeze=False)
    for i, ax in enumerate(axes.T.reshape(-1)[:n_states]):
        ax.fill_between(hours, -three_sigma[:, i], three_sigma[:, i], color="tab:blue", alpha=0.2, label="+-3 sigma")
        ax.plot(hours, error[:, i], color="tab:red", lw=0.8, label="error")
        ax.set_ylabel(labels[i])
        # The first fix leaves velocity unknown (3 sigma of tens of m/s); scale to the settled
        # bounds so the steady-state error is readable, the transient is clipped.
        settled = 2.0 * max(np.median(three_sigma[:, i]), np.max(np.abs(error[n_samples // 10:, i])))
        if settled > 0:
            ax.set_ylim(-settled, settled)
        inside = np.mean(np.abs(error[:, i]) <= three_sigma[:, i])
        ax.set_title(f"{inside:.0%} inside", fontsize=8, loc="right")
    for ax in axes[-1]:
        ax.set_xlabel("time [h]")
    axes[0, 0].legend(fontsize=7, loc="upper right")
    fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
