"""Campaign report: success rate with Wilson confidence intervals per cell, medians and spreads of
each metric, the seed 001 table (controller rows, dynamics x knowledge columns), box plots.

Reads the Parquet results file `bench campaign` writes; `bench campaign-report RESULTS` re-renders.
"""
from __future__ import annotations

import importlib

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.studies.campaign import CELL_COLUMNS

# The fault campaign's report (bench.studies.fault_report builds on this module's results reading).
FAULT_REPORT = "bench.studies.fault_report"
# 95 % two-sided normal quantile.
Z_95 = 1.959963984540054

# Metrics summarised per cell: (column, label, unit scale, format).
SUMMARY_METRICS = [
    ("final_position_error_m", "final distance [m]", 1.0, "{:.1f}"),
    ("final_velocity_error_mps", "final speed [m/s]", 1.0, "{:.3f}"),
    ("time_to_rendezvous_s", "time to rendezvous [h]", 1 / 3600, "{:.1f}"),
    ("delta_v_mps", "delta-v [m/s]", 1.0, "{:.1f}"),
    ("fuel_l2_n_sqrt_s", "fuel L2 [N s^0.5]", 1.0, "{:.1f}"),
    ("input_cost_n2", "J_u [N^2]", 1.0, "{:.2f}"),
    ("settled_max_position_m", "last-10% max distance [m]", 1.0, "{:.1f}"),
    ("solve_time_p50_ms", "solve p50 [ms]", 1.0, "{:.3f}"),
    ("solve_time_p99_ms", "solve p99 [ms]", 1.0, "{:.3f}"),
    ("solver_iterations_median", "iterations (median)", 1.0, "{:.0f}"),
    ("nees_mean", "run's mean NEES", 1.0, "{:.1f}"),
    ("estimate_position_error_final_m", "final estimate error [m]", 1.0, "{:.1f}"),
]
# The translational estimate's state dimension: a consistent estimator's NEES averages this.
NEES_DOF = 6
BOX_METRICS = ["final_position_error_m", "delta_v_mps", "time_to_rendezvous_s", "solve_time_p99_ms"]


HTML_PAGE = "bench.report.markdown_page"     # Markdown -> HTML beside it, in the run reports' style

def wilson_interval(successes: int, n: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (Wilson 1927): good near 0 and 1, unlike
    the normal approximation, which matters when a cell succeeds 30 times out of 30."""
    if n <= 0:
        return float("nan"), float("nan")
    p = successes / n
    denominator = 1 + z**2 / n
    centre = (p + z**2 / (2 * n)) / denominator
    half = z * math.sqrt(p * (1 - p) / n + z**2 / (4 * n**2)) / denominator
    return max(0.0, centre - half), min(1.0, centre + half)


def nees_bounds(runs: int, dof: int = NEES_DOF, probability: float = 0.95) -> tuple[float, float]:
    """Two-sided bounds of the mean over `runs` runs of one NEES each: runs x mean ~ chi-square with
    runs x dof degrees of freedom (Bar-Shalom, Li, Kirubarajan 2001, 5.4.2). A run's *time-averaged*
    NEES varies less than one step's, so for the mean of time averages the bounds are generous."""
    from scipy.stats import chi2

    if runs <= 0:
        return float("nan"), float("nan")
    tail = (1 - probability) / 2
    return float(chi2.ppf(tail, runs * dof) / runs), float(chi2.ppf(1 - tail, runs * dof) / runs)


@dataclass
class CellSummary:
    cell: tuple[str, ...]
    runs: int
    failed_runs: int              # status error/timeout
    successes: int
    diverged: int
    ci_low: float
    ci_high: float
    stats: dict[str, tuple[float, float, float]]      # metric -> (median, p25, p75) of ok runs
    values: dict[str, np.ndarray]
    # Mean over the runs of each run's time-averaged NEES, and its 95 % bounds (NaN: no estimator).
    nees_mean: float = float("nan")
    nees_low: float = float("nan")
    nees_high: float = float("nan")

    @property
    def nees_consistent(self) -> bool:
        return bool(self.nees_low <= self.nees_mean <= self.nees_high)

    @property
    def success_rate(self) -> float:
        return self.successes / self.runs if self.runs else float("nan")


def read_results(path: Path) -> list[dict]:
    import pyarrow.parquet as pq

    return pq.read_table(path).to_pylist()


def summarise(rows: list[dict]) -> list[CellSummary]:
    cells: dict[tuple, list[dict]] = {}
    for row in sorted(rows, key=lambda r: r["case_index"]):
        cells.setdefault(tuple(row[c] for c in CELL_COLUMNS), []).append(row)
    out = []
    for cell, group in cells.items():
        ok = [r for r in group if r["status"] == "ok"]
        # A failed run (exception, timeout) is not a success: it counts in n.
        successes = sum(bool(r["success"]) for r in ok)
        low, high = wilson_interval(successes, len(group))
        values, stats = {}, {}
        for metric, *_ in SUMMARY_METRICS:
            v = np.array([r[metric] for r in ok if r[metric] is not None], dtype=float)
            v = v[np.isfinite(v)]
            values[metric] = v
            stats[metric] = tuple(float(np.percentile(v, q)) for q in (50, 25, 75)) if v.size else (float("nan"),) * 3
        nees = values["nees_mean"]
        nees_low, nees_high = nees_bounds(nees.size)
        out.append(CellSummary(cell, len(group), len(group) - len(ok), successes,
                               sum(bool(r["diverged"]) for r in ok), low, high, stats, values,
                               float(nees.mean()) if nees.size else float("nan"), nees_low, nees_high))
    return out


def _pct(x: float) -> str:
    return "-" if math.isnan(x) else f"{100 * x:.0f}"


def _nees(s: CellSummary) -> str:
    """Mean NEES [95 % bounds], '-' without an estimator."""
    if math.isnan(s.nees_mean):
        return "-"
    return f"{s.nees_mean:.1f} [{s.nees_low:.1f}, {s.nees_high:.1f}]"


def seed001_table(summaries: list[CellSummary]) -> str:
    """Controller rows, dynamics x knowledge columns: success % [95 % CI], mean NEES [95 % bounds],
    median final distance, median delta-v (first initial-condition set and fault kind)."""
    first_ic = summaries[0].cell[3]
    first_fault = summaries[0].cell[4]
    by = {(s.cell[0], s.cell[1], s.cell[2]): s for s in summaries if s.cell[3] == first_ic and s.cell[4] == first_fault}
    controllers = list(dict.fromkeys(k[0] for k in by))
    columns = list(dict.fromkeys((k[1], k[2]) for k in by))
    lines = ["| controller | " + " | ".join(f"{d} / {k}" for d, k in columns) + " |",
             "|---|" + "---|" * len(columns)]
    for ctrl in controllers:
        cells = []
        for d, k in columns:
            s = by.get((ctrl, d, k))
            if s is None:
                cells.append("")
                continue
            cells.append(f"{_pct(s.success_rate)} % [{_pct(s.ci_low)}, {_pct(s.ci_high)}] of {s.runs}; "
                         f"NEES {_nees(s)}; "
                         f"{s.stats['final_position_error_m'][0]:.0f} m; {s.stats['delta_v_mps'][0]:.1f} m/s")
        lines.append(f"| {ctrl} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def cell_table(summaries: list[CellSummary]) -> str:
    header = ["cell", "runs", "failed", "success % [95 % CI]", "diverged", "mean NEES [95 % bounds]"]
    header += [f"{label} median (p25-p75)" for _, label, _, _ in SUMMARY_METRICS]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for s in summaries:
        row = ["/".join(s.cell), str(s.runs), str(s.failed_runs),
               f"{_pct(s.success_rate)} [{_pct(s.ci_low)}, {_pct(s.ci_high)}]", str(s.diverged), _nees(s)]
        for metric, _, scale, fmt in SUMMARY_METRICS:
            med, lo, hi = (v * scale for v in s.stats[metric])
            row.append("-" if math.isnan(med) else f"{fmt.format(med)} ({fmt.format(lo)}-{fmt.format(hi)})")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def box_plots(summaries: list[CellSummary], out_dir: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    labels = ["\n".join(s.cell[:3]) for s in summaries]
    for metric in BOX_METRICS:
        label, scale = next((lab, sc) for m, lab, sc, _ in SUMMARY_METRICS if m == metric)
        data = [s.values[metric] * scale for s in summaries]
        fig, ax = plt.subplots(figsize=(max(8, 0.7 * len(summaries)), 5))
        ax.boxplot([d if d.size else [np.nan] for d in data], showfliers=True)
        ax.set_xticks(range(1, len(labels) + 1), labels, fontsize=6, rotation=90)
        ax.set_ylabel(label)
        if metric == "final_position_error_m":
            from bench.gnc.cwh import RendezvousParams

            ax.axhline(RendezvousParams.from_reference().max_final_position_m, color="k", ls="--", lw=0.8)
        if metric in ("final_position_error_m", "solve_time_p99_ms") and any(d.size and d.max() > 0 for d in data):
            ax.set_yscale("log")
        ax.set_title(f"{label} per cell (runs that finished)")
        fig.tight_layout()
        path = out_dir / f"box_{metric}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def write_report(results: Path, out_dir: Path | None = None) -> Path:
    """report.md (+ box plots) beside the results file or in out_dir; returns the report path."""
    results = Path(results)
    rows = read_results(results)
    if not rows:
        raise ValueError(f"{results}: no rows")
    out_dir = Path(out_dir) if out_dir else results.with_name(results.stem + "_report")
    out_dir.mkdir(parents=True, exist_ok=True)
    if "fault_kind" in rows[0]:          # a fault campaign's rows: its own report, found by name
        return importlib.import_module(FAULT_REPORT).write_fault_report(results, rows, out_dir)
    summaries = summarise(rows)
    plots = box_plots(summaries, out_dir)
    failures = [r for r in rows if r["status"] != "ok"]
    text = [f"# Campaign report: {results.name}", "",
            f"{len(rows)} runs in {len(summaries)} cells; {len(failures)} failed (exception or timeout).", "",
            "## Seed 001 table", "",
            "Success % [Wilson 95 % CI] of n runs; the estimator's NEES (mean over the runs of each run's "
            "time-averaged NEES) [its 95 % chi-square bounds], '-' with full state knowledge; median final "
            "distance; median delta-v.", "",
            seed001_table(summaries), "", "## Every cell", "", cell_table(summaries), "", "## Distributions", ""]
    text += [f"![{p.stem}]({p.name})" for p in plots]
    if failures:
        text += ["", "## Failed runs", ""] + [f"- `{r['case_id']}` {r['status']}: {r['error']}" for r in failures[:50]]
    path = out_dir / "report.md"
    path.write_text("\n".join(text) + "\n")
    # Above the studies layer (bench.report): looked up by name, as the attitude metrics are.
    importlib.import_module(HTML_PAGE).write_html_beside(path)          # report.html: the same, for a browser
    return path
