"""`bench compare RUN_DIR...`: runs side by side in one table and one set of plots.

Seed 001's question is the first user: LQR, LQT and MPC, with full state knowledge and with noisy
sensing, compared on fuel, accuracy, compute cost and success. Each run keeps its own report; this
one reads the same analyses (mission metrics, latency, deadlines) and lays them next to each other.

Runs of one loop only: a rendezvous run and an attitude run share no figure worth a column, so a
mix is refused. The rows follow the loop (controller and plant dynamics for the rendezvous; law,
estimator and bus faults for the attitude loop). `--reference RUN` names the clean run the others'
fault effects are measured against (attitude); without it no effect is computed.
"""
from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from bench.report import plots
from bench.report.attitude_metrics import is_detumble
from bench.report.build import PLOTS_DIR, mission_metrics, trajectory_series
from bench.report.deadlines import DeadlineResult, deadlines
from bench.report.document import Document, Figure, Section, Table, fmt, write
from bench.report.latency import END_TO_END, SENSE_TO_PLANT, LatencyResult, latency
from bench.report.rundata import RunData, load_run


@dataclass
class RunSummary:
    label: str
    run: RunData
    mission: dict
    latency: LatencyResult
    deadlines: DeadlineResult


class CompareError(ValueError):
    """Runs that cannot be compared (different loops, a reference that is not among them)."""


def summarise(run_dir: Path) -> RunSummary:
    run = load_run(run_dir)
    s = run.scenario
    label = f"{run.run_id} ({controller_of(s)}, {s.estimator.mode})"
    return RunSummary(label, run, mission_metrics(run), latency(run), deadlines(run))


def controller_of(scenario) -> str:
    return scenario.attitude_control.law if scenario.kind == "attitude" else scenario.controller.type


def faults_of(scenario) -> str:
    faults = getattr(scenario.can, "faults", None) or []
    return ", ".join(f.name for f in faults) or "none"


def _lat(summary: RunSummary, hop: str, key: str):
    return summary.latency.summary.get(hop, {}).get(key)


def _verdict(summary: RunSummary) -> str:
    passed = summary.run.metrics.get("verdict", {}).get("passed")
    return "not judged" if passed is None else ("PASS" if passed else "FAIL")


def driver_events_of(summary: RunSummary) -> str:
    """What the CAN driver detected, per kind: 'kind n, ...'."""
    events = ((summary.run.metrics.get("can_bus") or {}).get("driver") or {}).get("events") or {}
    return ", ".join(f"{kind} {n}" for kind, n in sorted(events.items())) or "none"


def detections_of(summary: RunSummary) -> str:
    """Per fault window, which monitor (driver or FDIR) detected it first and how long after its start."""
    faults = (summary.run.metrics.get("can_bus") or {}).get("faults") or []
    out = []
    for f in faults:
        if f.get("detected"):
            out.append(f"{f['name']}: {f.get('first_detection')} ({f.get('detected_by')}) after "
                       f"{fmt((f.get('detection_latency_s') or 0.0) * 1e3)} ms")
        else:
            out.append(f"{f['name']}: not detected")
    return "; ".join(out) or "none"


def mode_note(summaries: list[RunSummary]) -> str | None:
    """A warning when the runs' time modes differ: what is and what is not comparable."""
    modes = {s.run.scenario.run.mode for s in summaries}
    if len(modes) < 2:
        return None
    which = ", ".join(f"{s.run.run_id}: {s.run.scenario.run.mode}" for s in summaries)
    return (f"The runs' time modes differ ({which}). 'sensed → applied' includes the plant's one-step hold in "
            "real time and not in lock-step, so it is not compared across modes here; 'sensed → command at the "
            "plant' (the loop's own latency, no hold) is the same quantity in both. Deadline misses mean a late "
            "command in real time and a slow cycle in lock-step.")


# One row per quantity: (name, function of a RunSummary), the ones of each loop, then the common ones.
RENDEZVOUS_ROWS = (
    ("scenario", lambda r: r.run.scenario.name),
    ("mode", lambda r: r.run.scenario.run.mode),
    ("controller", lambda r: r.run.scenario.controller.type),
    ("estimator", lambda r: r.run.scenario.estimator.mode),
    ("plant dynamics", lambda r: r.run.scenario.plant.dynamics),
    ("steps", lambda r: r.mission.get("steps")),
    ("final position error [m]", lambda r: r.mission.get("final_position_error_m")),
    ("final velocity error [m/s]", lambda r: r.mission.get("final_velocity_error_mps")),
    ("input cost J_u [N²]", lambda r: r.mission.get("input_cost")),
    ("fuel (L2) [N s]", lambda r: r.mission.get("fuel_l2")),
    ("max |thrust| [N]", lambda r: r.mission.get("max_abs_thrust_N")),
    ("constraints satisfied", lambda r: r.mission.get("constraints_satisfied")),
)
ATTITUDE_ROWS = (
    ("scenario", lambda r: r.run.scenario.name),
    ("mode", lambda r: r.run.scenario.run.mode),
    ("law", lambda r: r.run.scenario.attitude_control.law),
    ("estimator", lambda r: r.run.scenario.estimator.mode),
    ("bus faults", lambda r: faults_of(r.run.scenario)),
    ("steps", lambda r: r.mission.get("steps")),
    ("body rate final [deg/s]", lambda r: r.mission.get("final_rate_dps")),
    ("time to detumble [s]", lambda r: r.mission.get("time_to_detumble_s") if is_detumble(
        r.run.scenario.attitude_control.law) else "n/a (not a detumbling law)"),
    ("pointing error final [deg]", lambda r: r.mission.get("final_pointing_error_deg")),
    ("saturation fraction", lambda r: r.mission.get("saturation_fraction")),
)
COMMON_ROWS = (
    ("verdict", _verdict),
    ("sensed → command at the plant p50 [ms] (loop, no hold)", lambda r: _lat(r, SENSE_TO_PLANT.name, "p50_ms")),
    ("sensed → command at the plant p99 [ms] (loop, no hold)", lambda r: _lat(r, SENSE_TO_PLANT.name, "p99_ms")),
    ("sensed → applied p50 [ms] (with the step hold in real time)", lambda r: _lat(r, END_TO_END.name, "p50_ms")),
    ("controller compute p50 [ms]", lambda r: _lat(r, "controller compute", "p50_ms")),
    ("solve time p50 [ms]", lambda r: r.deadlines.to_metrics()["solve_time_p50_ms"]),
    ("solve time p99 [ms]", lambda r: r.deadlines.to_metrics()["solve_time_p99_ms"]),
    ("controller deadline misses", lambda r: len(r.deadlines.controller_miss_seq)),
    ("plant-side missed steps", lambda r: len(r.deadlines.plant_miss_seq)),
    ("CAN driver events", driver_events_of),
    ("fault detections (first, by which monitor)", detections_of),
)


def comparison_table(summaries: list[RunSummary]) -> Table:
    loop_rows = ATTITUDE_ROWS if summaries[0].run.scenario.kind == "attitude" else RENDEZVOUS_ROWS
    rows = [[name, *(fmt(get(s)) for s in summaries)] for name, get in (*loop_rows, *COMMON_ROWS)]
    if mode_note(summaries) is not None:    # not like with like: left blank, the note says why
        rows = [[r[0], *(("- (modes differ)",) * len(summaries))] if r[0].startswith("sensed → applied") else r
                for r in rows]
    if not any(s.run.scenario.can for s in summaries):
        rows = [r for r in rows if r[0] not in ("CAN driver events", "fault detections (first, by which monitor)")]
    return Table(["", *(s.run.run_id for s in summaries)], rows)


def check_comparable(summaries: list[RunSummary], reference: Path | None) -> int | None:
    """One loop only; the index of the reference run (None without one)."""
    kinds = {s.run.scenario.kind for s in summaries}
    if len(kinds) > 1:
        which = ", ".join(f"{s.run.run_id}: {s.run.scenario.kind}" for s in summaries)
        raise CompareError(f"runs of different loops cannot be compared ({which})")
    if reference is None:
        return None
    for i, s in enumerate(summaries):
        if Path(s.run.run_dir).resolve() == Path(reference).resolve():
            return i
    raise CompareError(f"--reference {reference} is not one of the runs compared")


def default_out_dir(run_dirs: list[Path]) -> Path:
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S")
    return Path(run_dirs[0]).resolve().parent / f"compare-{stamp}"


def write_comparison(run_dirs: list[str | Path], out_dir: str | Path | None = None,
                     reference: str | Path | None = None) -> tuple[Path, Path]:
    """compare.md, compare.html and plots/ in out_dir (default: runs/compare-<time>). reference:
    the clean run (added to the runs if it is not among them)."""
    run_dirs = [Path(d) for d in run_dirs]
    if reference is not None and all(Path(d).resolve() != Path(reference).resolve() for d in run_dirs):
        run_dirs.insert(0, Path(reference))
    out_dir = Path(out_dir) if out_dir else default_out_dir(run_dirs)
    plot_dir = out_dir / PLOTS_DIR
    plot_dir.mkdir(parents=True, exist_ok=True)
    summaries = [summarise(d) for d in run_dirs]
    reference_index = check_comparable(summaries, Path(reference) if reference is not None else None)

    figures = []
    trajectories = [t for t in (trajectory_series(s.run, s.label) for s in summaries) if t is not None]
    if trajectories:
        path = plots.trajectory(trajectories, summaries[0].run.scenario.params(), plot_dir / "trajectories.png")
        figures.append(Figure(Path(PLOTS_DIR) / path.name, "Trajectories against the constraints (first run's limits)"))
    e2e = {s.label: s.latency.hops[SENSE_TO_PLANT.name] for s in summaries if SENSE_TO_PLANT.name in s.latency.hops}
    if e2e:
        path = plots.latency_cdfs(e2e, plot_dir / "latency_cdf.png", "Sensed → command at the plant (loop latency, CDF)")
        figures.append(Figure(Path(PLOTS_DIR) / path.name, "Loop latency per run: sensed → command at the plant, "
                                                           "no step hold (the same quantity in both modes)"))
    solve = {s.label: s.deadlines.solve_time_s for s in summaries if s.deadlines.solve_time_s.size}
    if solve:
        path = plots.solve_times(solve, plot_dir / "solve_time.png")
        figures.append(Figure(Path(PLOTS_DIR) / path.name, "Solve-time distribution per run"))

    runs_text = "Runs: " + "; ".join(f"{s.run.run_id} = {s.run.run_dir}" for s in summaries) + "."
    note = mode_note(summaries)
    sections = [Section("Runs side by side", [runs_text] + ([note] if note else []), [comparison_table(summaries)],
                        figures)]
    if summaries[0].run.scenario.kind == "attitude":
        from bench.report.attitude import comparison_section

        runs = [s.run for s in summaries]
        if reference_index is not None:
            runs.insert(0, runs.pop(reference_index))
        sections.append(comparison_section(runs, plot_dir, with_reference=reference_index is not None))
    doc = Document(f"Comparison of {len(summaries)} runs", sections)
    return write(doc, out_dir, "compare")
