"""`bench report RUN_DIR`: report.md, report.html and plots/*.png of one run; numbers into metrics.json.

Each analysis (latency, deadlines, estimation, CAN) returns its numbers once; the same numbers go
into the tables, the pictures and metrics.json.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.report import canbus, plots, recording_can, summary, tables
from bench.report.attitude import attitude_section
from bench.report.deadlines import DeadlineResult, deadlines
from bench.report.jsonout import write_json
from bench.report.document import Document, Figure, Section, Table, fmt, write
from bench.report.estimation import AXES, estimation_error
from bench.report.latency import LatencyResult, latency
from bench.report.run_metrics import trajectory_metrics
from bench.report.rundata import RunData, ahead_of_plant, load_run

PLOTS_DIR = "plots"
MISSION_ROWS = (
    ("final position error [m]", "final_position_error_m"),
    ("final velocity error [m/s]", "final_velocity_error_mps"),
    ("input cost J_u [N²]", "input_cost"),
    ("fuel (L2) [N s]", "fuel_l2"),
    ("max |thrust| [N]", "max_abs_thrust_N"),
    ("constraints satisfied", "constraints_satisfied"),
    ("steps", "steps"),
)
LATENCY_COLUMNS = ("n", "mean_ms", "p50_ms", "p90_ms", "p99_ms", "max_ms")


def trajectory_series(run: RunData, label: str) -> plots.TrajectorySeries | None:
    t = run.trajectory
    if "state_m_mps" not in t:
        return None
    return plots.TrajectorySeries(label, t["t_s"], t["state_m_mps"], t["thrust_n"].reshape(-1, 3))


def mission_metrics(run: RunData) -> dict:
    """The launcher's metrics where it wrote them, else computed from the trajectory."""
    if "final_position_error_m" in run.metrics or "state_m_mps" not in run.trajectory:
        return run.metrics
    return trajectory_metrics(run.trajectory["state_m_mps"], run.trajectory["thrust_n"], run.scenario.params())


def latency_table(summary: dict[str, dict]) -> Table:
    return Table(["hop", *LATENCY_COLUMNS],
                 [[hop, *(fmt(s.get(c)) for c in LATENCY_COLUMNS)] for hop, s in summary.items()])


# --- sections ---------------------------------------------------------------------------------
def summary_section(run: RunData, mission: dict, judged: dict) -> Section:
    s = run.scenario
    controller = s.attitude_control.law if s.kind == "attitude" else s.controller.type
    text = (f"Scenario {s.name!r}, {s.run.mode}, controller {controller}, estimator {s.estimator.mode}, "
            f"{s.n_steps} steps of {s.step_s:g} s.")
    if s.kind == "attitude":
        rows = [[name, value] for name, value in summary.summary_rows(mission)]
    else:
        rows = [[name, fmt(mission.get(key))] for name, key in MISSION_ROWS if key in mission]
        rows = [[name, summary.constraints_text(mission)] if name == "constraints satisfied" else [name, value]
                for name, value in rows]
    paragraphs = [text]
    if run.metrics.get("partial"):
        paragraphs.insert(0, f"Partial run: {run.metrics.get('end_reason', 'it did not finish')}. "
                             "The numbers cover the steps it ran.")
    section_tables = [Table(["metric", "value"], rows)]
    if mission.get("constraints"):
        judged_metrics = {c["metric"] for c in judged.get("criteria") or []}
        paragraphs.append("The constraints table: each of the mission's constraints with its value and bound"
                          + ("" if "constraints_satisfied" in judged_metrics else
                             " (information: the verdict judges the scenario's criteria, not these)") + ".")
        from bench.gnc.cwh import RendezvousParams

        full = RendezvousParams.from_reference(time_step_s=s.plant.time_step_s).n_steps
        if s.run.steps is not None and s.run.steps < full:
            paragraphs.append(f"This run stops after {s.run.steps} of the mission's {full} steps "
                              f"({s.run.steps * s.step_s / 3600:.3g} h of {full * s.step_s / 3600:.3g} h): the final "
                              "position and velocity checks judge a state the mission has not reached yet.")
        section_tables.append(Table(["constraint", "value", "bound", "holds"],
                                    [[c["name"], f"{fmt(c['value'])} {c['unit']}", f"≤ {fmt(c['bound'])} {c['unit']}",
                                      "yes" if c["satisfied"] else "NO"] for c in mission["constraints"]]))
    if judged.get("passed") is None:
        paragraphs.append("Verdict: not judged (the scenario declares no criteria).")
    else:
        paragraphs.append(f"Verdict: **{'PASS' if judged['passed'] else 'FAIL'}** against the scenario's criteria"
                          + (" (a partial run fails whatever its figures)." if judged.get("partial_run") else "."))
        section_tables.append(Table(["criterion", "bound", "value", "holds", "why"],
                            [[c["metric"], c["bound"], fmt(c["value"]) if not isinstance(c["value"], str) else c["value"],
                              "yes" if c["passed"] else "NO", c["why"]] for c in judged["criteria"]]))
    return Section("Summary", paragraphs, section_tables)


def trajectory_section(run: RunData, plot_dir: Path) -> Section | None:
    series = trajectory_series(run, run.run_id)
    if series is None:
        return None
    path = plots.trajectory([series], run.scenario.params(), plot_dir / "trajectory.png")
    return Section("Trajectory", figures=[Figure(Path(PLOTS_DIR) / path.name, "States and thrust against the constraints")])


def latency_section(run: RunData, result: LatencyResult, plot_dir: Path) -> Section:
    section = Section("Latency", [
        "From the monotonic stamps each stage writes into the message header (recording.mcap), and the "
        "plant's record of the command it applied (trajectory.npz) for plant_received and applied.",
        "Two end-to-end figures, named by what they measure: 'sensed → command at the plant' is the loop's own "
        "latency, the same quantity in both modes; 'sensed → applied' adds the wait for the step boundary at "
        "which the plant applies a command: in real time the plant's one-step hold (about one step period), "
        "in lock-step nothing (the plant waits for the command and applies it at once)."
        + (" This run is real time: sensed → applied includes the hold." if run.scenario.run.mode == "real-time"
           else " This run is lock-step: the two differ by the plant's own apply time only."),
    ])
    if not result.hops:
        section.paragraphs.append("No stamped messages in this run.")
        return section
    section.tables.append(latency_table(result.summary))
    section.tables.append(clock_table(run))
    hops_only = {k: v for k, v in result.hops.items() if "→" in k or "compute" in k or "apply" in k}
    cdf = plots.latency_cdfs(result.hops, plot_dir / "latency_cdf.png", "Latency per hop (CDF)")
    hist = plots.latency_histograms(hops_only, plot_dir / "latency_hist.png")
    section.figures += [Figure(Path(PLOTS_DIR) / cdf.name, "Latency per hop and end to end, CDF"),
                        Figure(Path(PLOTS_DIR) / hist.name, "Latency per hop, histograms")]
    return section


def clock_table(run: RunData) -> Table:
    """Each process's clock against the launcher's, and the scheduler it ran under (its stats in
    metrics.json: a process at SCHED_FIFO is not held up by other programs on its host)."""
    stats = run.metrics.get("process_stats") or {}

    def scheduler(process: str) -> str:
        if process not in stats:
            return "not reported"     # a part from outside, or a process that died before its stats
        priority = stats[process].get("realtime_priority", 0)
        return f"SCHED_FIFO {priority}" if priority else "default"

    rows = [[p, o.get("host", "?"), fmt(o["offset_ns"] / 1e3), fmt(o["uncertainty_ns"] / 1e3), str(o.get("rounds", "")),
             scheduler(p)] for p, o in sorted(run.clock_offsets.items())]
    if not rows:
        rows = [["(no clock readings)", "", "", "", "", ""]]
    return Table(["process", "host", "offset [µs]", "± [µs]", "pings", "scheduler"], rows)


def deadline_section(result: DeadlineResult, plot_dir: Path) -> Section:
    m = result.to_metrics()

    def ms(value_s: float | None) -> str:
        return fmt(None if value_s is None else value_s * 1e3)

    rows = [
        ["budget [ms]", fmt(None if m["budget_s"] is None else m["budget_s"] * 1e3)],
        ["controller cycles", fmt(m["controller_cycles"])],
        ["controller misses (cycle over budget)", fmt(m["controller_misses"])],
        ["worst cycle time [ms]", fmt(None if m["worst_cycle_time_s"] is None else m["worst_cycle_time_s"] * 1e3)],
        ["fallbacks applied", ", ".join(f"{k}: {v}" for k, v in sorted(m["fallbacks_applied"].items())) or "none"],
        ["plant-side missed steps (real-time)", fmt(m["plant_missed_steps"])],
        ["  of which the controller was slow (over budget, or its estimate passed over)",
         fmt(m["plant_misses_controller_slow"])],
        ["  of which transport/estimator was slow", fmt(m["plant_misses_transport_slow"])],
        ["estimates passed over for a newer one (real-time controller behind)", fmt(m["stale_estimates_skipped"])],
        ["solve time p50 / p99 [ms]", f"{fmt(m['solve_time_p50_ms'])} / {fmt(m['solve_time_p99_ms'])}"],
        ["host late to wake the controller after a worker timeout, max [ms]", ms(m["host_wake_late_max_s"])],
        ["controller cycle p99 less that lateness [ms]", ms(m["cycle_time_less_host_p99_s"])],
    ]
    nodes = [name for name in result.external if name != "board"]
    if nodes:
        rows.insert(0, ["provided from outside (not measured: cycle time, stamps)", ", ".join(nodes)])
    if "board" in result.external:
        rows.insert(0, ["magnetorquer board provided from outside (not measured: its command-to-coil time, the bus "
                        "traffic; applied dipole: its telemetry's coil current in real time, its acknowledged set-point "
                        "(MTQ_TLM_SETPOINT) in lock-step, stamped on arrival at the plant)", "board"])
    if "planner" in m:
        planner = m["planner"]
        rows += [["planner: plans", fmt(planner["plans"])],
                 ["planner: wall time p50 / worst [s]", f"{fmt(planner['wall_time_p50_s'])} / {fmt(planner['worst_wall_time_s'])}"],
                 ["planner: wall-time cap [s] (real time only)", fmt(planner["budget_s"])],
                 ["planner: plans over the cap", fmt(planner["over_budget"])]]
    section = Section("Deadlines", [
        "A controller miss is a cycle (estimate received to command ready) over the budget; the fallback "
        "replaced its late result. A plant-side miss is a real-time step integrated before its command arrived."
    ], [Table(["deadline", "value"], rows)])
    if result.cycle_time_s.size:
        cycle = plots.cycle_times(result.cycle_seq, result.cycle_time_s, result.budget_s,
                                  result.controller_miss_seq, result.plant_miss_seq, plot_dir / "cycle_time.png")
        section.figures.append(Figure(Path(PLOTS_DIR) / cycle.name, "Cycle time per step and deadline misses"))
    if result.plan_wall_s.size:
        planning = plots.planning_times(result.plan_time_s, result.plan_wall_s, result.plan_budget_s,
                                        plot_dir / "planning_time.png")
        section.figures.append(Figure(Path(PLOTS_DIR) / planning.name, "Planner: wall time of each plan"))
    if result.solve_time_s.size:
        solve = plots.solve_times({"solver": result.solve_time_s}, plot_dir / "solve_time.png")
        section.figures.append(Figure(Path(PLOTS_DIR) / solve.name, "Solve-time distribution (on-time cycles)"))
    return section


def estimation_section(run: RunData, plot_dir: Path) -> tuple[Section | None, dict | None]:
    result = estimation_error(run)
    if result is None:
        return None, None
    m = result.to_metrics()
    rows = [[axis, fmt(m["rms_error_converged"][axis]), fmt(m["median_abs_error"][axis])] for axis in AXES]
    path = plots.estimator_error(result.sim_time_s, result.error, result.bound_3sigma, plot_dir / "estimator_error.png")
    section = Section("Estimator", [
        f"Fraction of errors inside ±3σ: {fmt(m['fraction_within_3sigma'])}. RMS over the samples after the "
        f"first {m['converged_after_samples']} (the first carry the initial velocity prior); mean NIS "
        f"{fmt(m['mean_nis'])} ({m['nis_dof']} expected; {fmt(m.get('mean_nis_accepted'))} over the fixes used); measurements "
        f"rejected by the gate: {m['rejected_measurements']}, in {m.get('rejection_runs', 0)} runs (longest "
        f"{m.get('longest_rejection_run', 0)}); re-acquisitions after a long run: {m.get('reacquisitions', 0)}."],
        [Table(["component", "RMS error after convergence (m, m/s)", "median |error| (m, m/s)"], rows)],
        [Figure(Path(PLOTS_DIR) / path.name, "Estimator error with bounds")])
    if result.nis is not None and np.isfinite(result.nis).any():
        nis_path = plots.nis(result.sim_time_s, result.nis, result.nis_dof, result.rejected, plot_dir / "nis.png")
        section.figures.append(Figure(Path(PLOTS_DIR) / nis_path.name, "Normalised innovation squared per step"))
    return section, m


def can_section(run: RunData, plot_dir: Path) -> tuple[Section | None, dict | None]:
    load, m, driver_rows = canbus.can_metrics(run)
    if load is None:
        return None, None
    rows = [["frames", fmt(m["frames"])], ["bitrate [bit/s]", fmt(m["bitrate_bps"])],
            ["mean load [%]", fmt(m["mean_load"] * 100)], ["peak load [%]", fmt(m["peak_load"] * 100)]]
    rows.append(["authentication", {True: "SecOC: commands and NMT carry an AES-CMAC (the run's key)", None: "unknown",
                                    False: "NONE (e2e profile): the bus is unauthenticated, anyone on it can command "
                                           "the coils or stop the board"}[m["authenticated"]]])
    rows += [[f"fault {f['name']}{' (injected live)' if f.get('live') else ''} (simulated time)",
              f"{fmt(f['start_sim_s'])} s to {fmt(f['end_sim_s'])} s; "
              + (f"first detected by the {f['detected_by']} ({f['first_detection']}) {fmt(f['detection_latency_s'] * 1e3)} ms "
                 f"after its start" if f.get("detected") else "not detected before the next fault or the end")]
             for f in m["faults"]]
    live = m.get("live_faults")
    if live:
        refused = ", ".join(f"{reason} {n}" for reason, n in sorted(live["refused"].items())) or "none"
        rows.append(["live fault injection", f"{'allowed' if live['allowed'] else 'not allowed (no --allow-live-faults)'}; "
                                             f"{live['taken']} taken, refused: {refused}"])
    rows += [[f"injected {what}", fmt(n)] for what, n in sorted(m["injections"].items())]
    rows += canbus.bus_off_rows(m.get("bus_off") or {})
    rows += canbus.board_power_rows(m.get("board_power") or {})
    section = Section("CAN bus", ["From can.log (candump format); bus-off episodes from can/busmodel.json, the "
                                  "board's power losses and reboots from can/board.json."],
                      [Table(["bus", "value"], rows)])
    driver_table = None if driver_rows is None else Table(
        ["driver event", "count", "first latency [ms]", "worst latency [ms]"], driver_rows)
    if driver_table is not None:
        section.paragraphs.append("What the flight side detected (can/driver.json), with the latency from the "
                                  "fault's evidence to its detection: the CAN driver's events from the bus, and the "
                                  "FDIR's (fdir_*, docs/fdir.md) from the dynamics, whose latency is the span of "
                                  "simulated data the monitor judged.")
        if run.scenario is not None and "controller" in run.scenario.run.external:
            section.paragraphs.append("The flight software (controller and driver) was provided from outside: "
                                      "can/driver.json is its own account, if it wrote one, not the bench's measurement.")
        section.tables.append(driver_table)
    if load.load.size:
        path = plots.bus_load(load.window_start_s, load.load, load.fault_windows, load.injections,
                              plot_dir / "bus_load.png",
                              "simulated time [s]" if load.on_sim_time else "time since the first frame [s]")
        section.figures.append(Figure(Path(PLOTS_DIR) / path.name, "Bus load and fault timeline"))
    return section, m


def recording_section(run: RunData) -> tuple[Section, dict]:
    counts = run.recorder_counts if isinstance(run.recorder_counts, dict) else None
    topics = counts.get("topics", {}) if counts else {}
    topics = {t: c for t, c in topics.items() if isinstance(c, dict)} if isinstance(topics, dict) else {}

    def n(c: dict, key: str) -> int:
        value = c.get(key)
        return value if isinstance(value, int) else 0

    rows = [[topic, fmt(c.get("published")), fmt(c.get("recorded")), fmt(c.get("malformed")), fmt(c.get("missing")),
             fmt(c.get("dropped", 0))] for topic, c in topics.items()]
    missing = sum(n(c, "missing") for c in topics.values())
    malformed = sum(n(c, "malformed") for c in topics.values())
    dropped = sum(n(c, "dropped") for c in topics.values())
    wrong_type = dict(run.wrong_type)
    ahead = ahead_of_plant(run)
    note = ("recording.mcap holds every sample the recorder kept; 'published' is what each publisher reported "
            f"at shutdown. Missing in total: {missing}; malformed (kept raw): {malformed}; dropped over the "
            f"recorder's budget: {dropped}.")
    if wrong_type:
        note += (" Messages of a type their topic does not carry (left out of every analysis): "
                 + ", ".join(f"{t}: {k}" for t, k in sorted(wrong_type.items())) + ".")
    if ahead:
        note += (" Messages for a step the plant never reached: "
                 + ", ".join(f"{t}: {k}" for t, k in sorted(ahead.items())) + ".")
    if run.recording_truncated:
        note += " The recording ends early (the recorder did not finish it): samples after its last chunk are lost."
    if counts is None:
        note = "No recorder ran in this run, or it did not finish." if not run.messages else "The recorder did not finish (no counts)."
    section = Section("Recording", [note], [Table(["topic", "published", "recorded", "malformed", "missing", "dropped"], rows)])
    return section, {"missing": missing, "malformed": malformed, "truncated": run.recording_truncated,
                     "recorded": sum(n(c, "recorded") for c in topics.values()), "dropped": dropped,
                     "wrong_type": wrong_type, "ahead_of_plant": ahead}


def acceptance_section(run: RunData) -> Section | None:
    """What the plant's output stage refused, per actuator and reason (command_acceptance.json)."""
    counts = run.metrics.get("command_acceptance")
    if not isinstance(counts, dict):
        return None
    rows = []
    for actuator, c in sorted(counts.items()):
        if not isinstance(c, dict):
            continue
        rejected = c.get("rejected") if isinstance(c.get("rejected"), dict) else {}
        rows.append([actuator, fmt(c.get("accepted")), ", ".join(f"{r}: {k}" for r, k in sorted(rejected.items())) or "none",
                     str(c.get("on_reject", ""))])
    return Section("Command acceptance", [
        "Commands the plant applied, and those its output stage refused (non-finite, not for the current step, "
        "out of the actuator envelope), whoever sent them."
    ], [Table(["actuator", "accepted", "refused", "on refusal"], rows)])


# --- the report -------------------------------------------------------------------------------
def write_report(run_dir: str | Path) -> tuple[Path, Path]:
    """Write report.md, report.html, plots/ and the report's numbers into metrics.json."""
    run = load_run(run_dir)
    tables.write_tables(run.run_dir)    # steps.parquet, can_frames.parquet
    recording_can.place_can_frames(run)  # recording.mcap's CAN frames on simulated time, decoded, every mode
    plot_dir = run.run_dir / PLOTS_DIR
    plot_dir.mkdir(exist_ok=True)
    mission = mission_metrics(run)
    lat = latency(run)
    dl = deadlines(run)
    est_section, est_metrics = estimation_section(run, plot_dir)
    if est_section is None and run.scenario.kind == "attitude":   # the attitude loop's smoother
        from bench.report.attitude_estimation import attitude_estimation_section

        est_section, est_metrics = attitude_estimation_section(run, plot_dir)
    can_sec, can_metrics = can_section(run, plot_dir)
    rec_section, rec_metrics = recording_section(run)
    att_section, _ = attitude_section(run, plot_dir)
    metrics = {**mission, **run.metrics}
    metrics.update({
        "latency_ms": lat.to_metrics(),
        "deadlines": dl.to_metrics(),
        "recording": rec_metrics,
        "clock_offsets": run.clock_offsets,
        "estimator_error": est_metrics,
        "can_bus": can_metrics,
    })
    metrics["verdict"] = summary.verdict(run.scenario, metrics)
    sections = [summary_section(run, metrics, metrics["verdict"]), att_section, trajectory_section(run, plot_dir),
                latency_section(run, lat, plot_dir),
                deadline_section(dl, plot_dir), est_section, can_sec, acceptance_section(run), rec_section]
    doc = Document(f"Run {run.run_id}", [s for s in sections if s is not None])
    paths = write(doc, run.run_dir, "report")
    write_json(run.run_dir / "metrics.json", metrics)
    return paths
