"""The report's pictures (matplotlib, Agg, PNG). Each function draws one figure into `path`.

Functions take lists of labelled series so the single-run report and `bench compare` draw the
same pictures: one series per hop for a run, one series per run for a comparison.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")   # no display: reports are rendered in batch and in CI
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from bench.gnc.cwh import RendezvousParams  # noqa: E402

DPI = 100


@dataclass
class TrajectorySeries:
    label: str
    t_s: np.ndarray            # (n+1,)
    state_m_mps: np.ndarray    # (n+1, 6)
    thrust_n: np.ndarray       # (n, 3)


def fixed_layout(fig, column_gap_in: float = 0.9, row_gap_in: float = 0.75) -> None:
    """Margins and gaps in inches for a figure's subplot grid: room for tick labels, an axis label
    and a title. (tight_layout measures every label by drawing the figure once more: most of a
    report's plotting time, 2.5 of 3.1 s for the latency histograms.)"""
    w_in, h_in = fig.get_size_inches()
    specs = [ax.get_subplotspec() for ax in fig.axes if ax.get_subplotspec() is not None]
    rows, cols = specs[0].get_gridspec().get_geometry() if specs else (1, 1)
    left, right, bottom = 0.85 / w_in, 1 - 0.3 / w_in, 0.6 / h_in
    top = 1 - (0.45 + (0.4 if fig._suptitle is not None else 0.0)) / h_in

    def spacing(n: int, span_in: float, gap_in: float) -> float:   # gap as a fraction of one axes' size
        if n <= 1:
            return 0.2
        size_in = (span_in - (n - 1) * gap_in) / n
        return gap_in / max(size_in, 0.1)
    fig.subplots_adjust(left=left, right=right, bottom=bottom, top=top,
                        wspace=spacing(cols, w_in * (right - left), column_gap_in),
                        hspace=spacing(rows, h_in * (top - bottom), row_gap_in))


def save(fig, path: Path, dpi: int = DPI) -> Path:
    """The figure laid out (fixed_layout), written to `path` and closed."""
    fixed_layout(fig)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def _bounds(ax, limit: float, scale: float = 1.0) -> None:
    for sign in (-1, 1):
        ax.axhline(sign * limit * scale, color="tab:red", linestyle="--", linewidth=1)


def trajectory(series: list[TrajectorySeries], params: RendezvousParams, path: Path) -> Path:
    """States and inputs against the constraints, as seed 003's plot_trajectory: positions (with
    s_max on x, z and y_max on y), velocities, and thrust per axis (with u_max)."""
    fig, axes = plt.subplots(3, 3, figsize=(13, 8), sharex=True)
    position_limits_m = (params.max_abs_position_xz_m, params.max_abs_position_y_m, params.max_abs_position_xz_m)
    for s in series:
        t_h = np.asarray(s.t_s) / 3600.0
        for i, axis in enumerate("xyz"):
            axes[0, i].plot(t_h, s.state_m_mps[:, i] / 1e3, label=s.label)
            axes[1, i].plot(t_h, s.state_m_mps[:, 3 + i], label=s.label)
            if len(s.thrust_n):
                axes[2, i].step(t_h[: len(s.thrust_n)], s.thrust_n[:, i], where="post", label=s.label)
    for i, axis in enumerate("xyz"):
        _bounds(axes[0, i], position_limits_m[i], 1e-3)
        _bounds(axes[2, i], params.max_abs_thrust_n)
        axes[0, i].set_ylabel(f"{axis} [km]")
        axes[1, i].set_ylabel(f"v{axis} [m/s]")
        axes[2, i].set_ylabel(f"u{axis} [N]")
        axes[2, i].set_xlabel("time [h]")
    axes[0, 0].legend(fontsize="small")
    fig.suptitle("Trajectory against constraints (dashed: limits)")
    return save(fig, path)


def _cdf(ax, samples_ms: np.ndarray, label: str, **style) -> None:
    values = np.sort(samples_ms)
    ax.step(values, np.arange(1, values.size + 1) / values.size, where="post", label=f"{label} (n={values.size})",
            **style)


def latency_cdfs(series_s: dict[str, np.ndarray], path: Path, title: str) -> Path:
    """Empirical CDFs of latencies (one line per hop or per run), log time axis."""
    fig, ax = plt.subplots(figsize=(10, 5))
    # one colour per line: the default cycle has 10, a loop with CAN has more hops than that
    colours = plt.get_cmap("tab20").colors
    for i, (label, samples_s) in enumerate(series_s.items()):
        if samples_s.size:
            _cdf(ax, np.asarray(samples_s) * 1e3, label, color=colours[(2 * i) % 20 + (2 * i) // 20 % 2],
                 ls="-" if i < 20 else "--")
    ax.set_xscale("log")
    ax.set_xlabel("latency [ms]")
    ax.set_ylabel("fraction of steps")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small", loc="lower right")
    ax.set_title(title)
    return save(fig, path)


def _histogram(ax, values, bins: int, **style) -> None:
    """A filled histogram as one step artist, not one bar patch per bin as ax.hist draws it: the
    same picture in about half the drawing time."""
    counts, edges = np.histogram(values, bins=bins)
    ax.stairs(counts, edges, fill=True, **style)


def latency_histograms(series_s: dict[str, np.ndarray], path: Path) -> Path:
    """One histogram per hop, one row each on a shared log time axis (hops differ by orders of
    magnitude), p50 and p99 marked in each row. One axes for all hops: a grid of one axes per hop
    spent most of a report's drawing time laying out tick labels."""
    rows = [(label, np.asarray(samples_s, float) * 1e3) for label, samples_s in series_s.items()
            if np.asarray(samples_s).size]
    fig, ax = plt.subplots(figsize=(11, 1.0 + 0.55 * max(1, len(rows))))
    positive = np.concatenate([ms[ms > 0] for _, ms in rows]) if rows else np.array([])
    if positive.size:
        # A latency of 0 (two stages stamped in the same nanosecond) goes into the first bin.
        low_ms, high_ms = max(positive.min(), 1e-3), max(positive.max(), 2e-3)
        edges_ms = np.geomspace(low_ms, high_ms * 1.0001, 61)
        for i, (label, ms) in enumerate(rows):
            baseline = len(rows) - 1 - i        # loop order from the top
            counts, _ = np.histogram(np.clip(ms, edges_ms[0], edges_ms[-1]), bins=edges_ms)
            ax.stairs(baseline + 0.85 * counts / counts.max(), edges_ms, baseline=baseline, fill=True,
                      color="tab:blue", alpha=0.7)
            for q, colour in ((50, "k"), (99, "tab:red")):
                ax.plot([np.percentile(ms, q)] * 2, [baseline, baseline + 0.9], color=colour, linewidth=1.5,
                        label=f"p{q}" if i == 0 else None)
        ax.set_xscale("log")
        ax.legend(fontsize="small", loc="upper right")
    ax.set_yticks(np.arange(len(rows)) + 0.4, [f"{label} (n={ms.size})" for label, ms in reversed(rows)],
                  fontsize="small")
    ax.set_ylim(0, max(1, len(rows)))
    ax.set_xlabel("latency [ms]")
    ax.grid(True, axis="x", which="major", alpha=0.3)
    ax.set_title("Latency per hop: histograms on one log axis (black p50, red p99)")
    # fixed margins in inches (no tight_layout: it draws the figure once more), room for the labels
    w_in, h_in = fig.get_size_inches()
    label_in = 0.3 + 0.065 * max((len(t.get_text()) for t in ax.get_yticklabels()), default=0)
    fig.subplots_adjust(left=min(0.6, label_in / w_in), right=1 - 0.3 / w_in, bottom=0.6 / h_in, top=1 - 0.45 / h_in)
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def cycle_times(seq: np.ndarray, cycle_time_s: np.ndarray, budget_s: float | None,
                controller_misses: list[int], plant_misses: list[int], path: Path) -> Path:
    """Controller cycle time per step against the budget, with the misses of both sides marked."""
    fig, ax = plt.subplots(figsize=(11, 4.5))
    ax.plot(seq, np.asarray(cycle_time_s) * 1e3, ".-", linewidth=0.7, markersize=3, label="controller cycle time")
    if budget_s is not None:
        ax.axhline(budget_s * 1e3, color="tab:red", linestyle="--", label=f"budget {budget_s * 1e3:g} ms")
    by_seq = dict(zip(np.asarray(seq).tolist(), np.asarray(cycle_time_s).tolist()))
    missed = [k for k in controller_misses if k in by_seq]
    if missed:
        ax.plot(missed, [by_seq[k] * 1e3 for k in missed], "rx", markersize=8,
                label=f"controller misses ({len(controller_misses)})")
    for i, k in enumerate(plant_misses):
        ax.axvline(k, color="tab:orange", alpha=0.4, label=f"plant-side misses ({len(plant_misses)})" if i == 0 else None)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("cycle time [ms]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")
    ax.set_title("Deadline: controller cycle time and misses over the run")
    return save(fig, path)


def planning_times(plan_time_s: np.ndarray, wall_s: np.ndarray, budget_s: float | None, path: Path) -> Path:
    """Each plan's planning wall time at the simulated time it started from, against its cap."""
    fig, ax = plt.subplots(figsize=(11, 3.5))
    ax.plot(plan_time_s, wall_s, "o", label="planning wall time")
    if budget_s is not None:
        ax.axhline(budget_s, color="tab:red", linestyle="--", label=f"cap {budget_s:g} s")
    ax.set_yscale("log")
    ax.set_xlabel("simulated time [s]")
    ax.set_ylabel("wall time [s]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")
    ax.set_title("Planner: wall time per plan")
    return save(fig, path)


def solve_times(series_s: dict[str, np.ndarray], path: Path) -> Path:
    """Distribution of solver times (histogram and CDF), one series per run or controller."""
    fig, (hist_ax, cdf_ax) = plt.subplots(1, 2, figsize=(12, 4))
    for label, samples_s in series_s.items():
        ms = np.asarray(samples_s) * 1e3
        if ms.size:
            _histogram(hist_ax, ms, bins=40, alpha=0.6, label=label)
            _cdf(cdf_ax, ms, label)
    hist_ax.set_xlabel("solve time [ms]")
    hist_ax.set_ylabel("cycles")
    cdf_ax.set_xlabel("solve time [ms]")
    cdf_ax.set_ylabel("fraction of cycles")
    for ax in (hist_ax, cdf_ax):
        ax.legend(fontsize="small")
        ax.grid(True, alpha=0.3)
    fig.suptitle("Solve-time distribution")
    return save(fig, path)


def estimator_error(sim_time_s: np.ndarray, error: np.ndarray, bound_3sigma: np.ndarray, path: Path) -> Path:
    """Estimate minus truth per component, inside the estimator's own +-3 sigma."""
    fig, axes = plt.subplots(2, 3, figsize=(13, 6), sharex=True)
    t_h = np.asarray(sim_time_s) / 3600.0
    names = ("x [m]", "y [m]", "z [m]", "vx [m/s]", "vy [m/s]", "vz [m/s]")
    for i, ax in enumerate(axes.flat):
        ax.plot(t_h, error[:, i], linewidth=0.8, label="error")
        if not np.all(np.isnan(bound_3sigma[:, i])):
            ax.fill_between(t_h, -bound_3sigma[:, i], bound_3sigma[:, i], color="tab:gray", alpha=0.3, label="±3σ")
        ax.set_ylabel(names[i])
        # The axis follows the error, not the initial prior: a +-30 m/s prior on the first step
        # would flatten velocity errors of 1e-3 m/s into a line (the band is clipped, not hidden).
        scale = np.nanpercentile(np.abs(error[:, i]), 99) if np.isfinite(error[:, i]).any() else 0.0
        band = np.nanmedian(bound_3sigma[:, i]) if np.isfinite(bound_3sigma[:, i]).any() else 0.0
        limit = 1.3 * max(scale, band)
        if np.isfinite(limit) and limit > 0:
            ax.set_ylim(-limit, limit)
    for ax in axes[1]:
        ax.set_xlabel("time [h]")
    axes[0, 0].legend(fontsize="small")
    fig.suptitle("Estimator error (estimate - truth) with its 3-sigma bounds (axes: 99 % of the error or the median bound)")
    return save(fig, path)


def nis(sim_time_s: np.ndarray, nis_values: np.ndarray, dof: int, rejected: np.ndarray, path: Path) -> Path:
    """Each measurement's NIS against the prediction, with the two-sided 95 % chi-square band."""
    from scipy.stats import chi2

    fig, ax = plt.subplots(figsize=(11, 4))
    t_h = np.asarray(sim_time_s) / 3600.0
    used = ~np.asarray(rejected, dtype=bool)
    ax.semilogy(t_h[used], nis_values[used], ".", markersize=4, label="NIS")
    if (~used).any():
        ax.semilogy(t_h[~used], nis_values[~used], "x", color="tab:red", label="rejected by the gate")
    if dof:
        low, high = chi2.ppf([0.025, 0.975], dof)
        ax.axhspan(low, high, color="tab:gray", alpha=0.25, label=f"95 % of χ²({dof})")
        ax.axhline(dof, color="tab:gray", linewidth=1)
    ax.set_xlabel("time [h]")
    ax.set_ylabel("NIS")
    ax.grid(True, alpha=0.3, which="both")
    ax.legend(fontsize="small")
    ax.set_title("Normalised innovation squared (consistent filter: inside the band 95 % of the time)")
    return save(fig, path)


def fault_colour(i: int) -> str:
    """The colour of the i-th fault window, the same in every plot of a report (C0-C2 are the lines)."""
    return f"C{(i + 3) % 10}"


def bus_load(window_start_s: np.ndarray, load: np.ndarray, fault_windows: list[tuple[str, float, float]],
             injections: list[tuple[float, str, str]], path: Path, xlabel: str = "simulated time [s]") -> Path:
    """CAN bus load per window, the scenario's fault windows shaded, the injector's actions marked."""
    fig, ax = plt.subplots(figsize=(11, 4))
    ax.step(window_start_s, np.asarray(load) * 100, where="post", label="bus load")
    end_s = float(window_start_s[-1]) if len(window_start_s) else 1.0
    for i, (name, start_s, stop_s) in enumerate(fault_windows):
        ax.axvspan(start_s, min(stop_s, end_s), color=fault_colour(i), alpha=0.25, label=f"fault: {name}")
    for i, action in enumerate(sorted({a for _, _, a in injections})):
        t_s = [t for t, _, a in injections if a == action]
        ax.plot(t_s, np.zeros(len(t_s)), "|", color=f"C{i + 5}", markersize=14, label=f"injected: {action} ({len(t_s)})")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("bus load [%]")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small")
    ax.set_title("CAN bus load and fault timeline")
    return save(fig, path)
