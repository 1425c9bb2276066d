"""The attitude card of a run's report: pointing error and body rate with the CAN fault windows
shaded, the dipole per axis against the limit (commanded and applied), the field along the orbit.

Fault windows are on the run's simulated time, as every other time of the report
(bench.report.timebase, bench.report.canbus).
"""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from bench.report.attitude_metrics import attitude_metrics, pointing_error_deg  # noqa: E402
from bench.report import canbus, plots  # noqa: E402
from bench.report.document import Figure, Section, Table  # noqa: E402
from bench.report.timebase import RunClock  # noqa: E402

PLOTS_DIR = "plots"


def fault_windows_sim_s(run_dir: Path, scenario, trajectory: dict) -> list[tuple[str, float, float]]:
    """[(fault name, start, end)] in simulated seconds (bench.report.canbus)."""
    return canbus.fault_windows_sim_s(run_dir, scenario.can, RunClock.from_run(trajectory, scenario))


def _criterion_bounds(scenario, metrics: tuple[str, ...]) -> list[tuple[float, str]]:
    """Upper bounds the scenario's criteria put on these metrics, for threshold lines."""
    return [(c.max, c.metric) for c in scenario.criteria if c.metric in metrics and c.max is not None]


def _shade(ax, windows) -> None:
    for i, (name, start, end) in enumerate(windows):
        ax.axvspan(start, max(end, start + 0.1), color=plots.fault_colour(i), alpha=0.25, label=f"fault: {name}")


def loop_figure(trajectory: dict, scenario, windows, path: Path) -> Path:
    t = trajectory["att_time_s"]
    error = pointing_error_deg(trajectory, scenario)
    rows = 2 if error is not None else 1
    fig, axes = plt.subplots(rows, 1, figsize=(11, 3.2 * rows), sharex=True, squeeze=False)
    axes = axes[:, 0]
    if error is not None:
        axes[0].plot(t, error, label="pointing error")
        for bound, why in _criterion_bounds(scenario, ("final_pointing_error_deg", "max_pointing_error_deg")):
            axes[0].axhline(bound, color="tab:red", ls="--", lw=0.8, label=f"criterion: {why} ({bound:g} deg)")
        axes[0].set_ylabel("pointing error [deg]")
        if error.max() > 100 * max(error.min(), 1e-6):
            axes[0].set_yscale("log")
        _shade(axes[0], windows)
        axes[0].legend(fontsize="small")
    ax = axes[-1]
    rate_dps = np.rad2deg(np.linalg.norm(trajectory["att_omega_radps"], axis=1))
    if rate_dps.max() > 100 * max(rate_dps.min(), 1e-9):
        # a detumble spans decades: |w| on a log axis, the components would not show there
        ax.semilogy(t, rate_dps, "k", lw=1, label="|w|")
    else:
        ax.plot(t, np.rad2deg(trajectory["att_omega_radps"]), label=["wx", "wy", "wz"])
        ax.plot(t, rate_dps, "k", lw=1, label="|w|")
    if "detumble" in scenario.attitude_control.law or "bdot" in scenario.attitude_control.law:
        from bench.report.attitude_metrics import DETUMBLE_THRESHOLD_DPS

        ax.axhline(DETUMBLE_THRESHOLD_DPS, color="tab:red", ls="--", lw=0.8,
                   label=f"detumbled below {DETUMBLE_THRESHOLD_DPS:g} deg/s")
    _shade(ax, windows)
    ax.set_ylabel("body rate [deg/s]")
    ax.set_xlabel("simulated time [s]")
    ax.legend(fontsize="small", ncol=4)
    for a in axes:
        a.grid(True, alpha=0.3)
    return plots.save(fig, path, dpi=90)


def board_telemetry_am2(run) -> tuple[np.ndarray, np.ndarray] | None:
    """The board's applied-dipole telemetry as the flight side reads it on the bus (MTQ_TLM_DIPOLE
    frames of can.log, after whatever the fault injector did to them): (simulated s, (n, 3) A m²)."""
    from bench.bus.can import protocol as can_protocol

    if run.can_log is None or run.scenario.can is None:
        return None
    clock = RunClock.from_run(run.trajectory, run.scenario)
    if clock is None:
        return None
    protocol = can_protocol.Protocol(run.scenario.can.node_id, run.scenario.can.security.profile)
    times, dipoles = [], []
    for msg in canbus.read_capture(run.can_log):
        frame = protocol.decode(msg)
        if frame is not None and frame.name == can_protocol.TLM_DIPOLE:
            times.append(msg.timestamp)
            dipoles.append([frame.signals[f"AppliedDipole{axis}"] for axis in "XYZ"])
    if not times:
        return None
    # on simulated time in both modes: a lock-step bus's stamps are bus time, not wall time
    sim_s = canbus.capture_sim_s(run.run_dir, clock, times)
    if sim_s is None:
        return None
    inside = (sim_s >= clock.start_sim_s) & (sim_s <= clock.end_sim_s)
    return sim_s[inside], np.asarray(dipoles, float)[inside]


def dipole_figure(trajectory: dict, limit_am2: float, windows, path: Path, telemetry=None) -> Path:
    """Per axis: the law's dipole, the board's telemetry as the flight side reads it on the bus
    (where a stuck-telemetry fault shows), and the dipole the plant applied (the board's coils);
    steps with the coils in their safe state and real-time steps the plant ran without their
    command are marked."""
    t = trajectory["att_time_s"]
    safe = np.asarray(trajectory.get("att_safe_state", np.zeros(len(t), bool)), bool)
    received = trajectory.get("att_command_received_ns")
    missed = np.zeros(len(t), bool) if received is None else np.asarray(received)[: len(t)] < 0
    fig, axes = plt.subplots(4, 1, figsize=(11, 9), sharex=True)
    for i, axis in enumerate("xyz"):
        ax = axes[i]
        ax.plot(t, trajectory["att_dipole_commanded_am2"][:, i], label="commanded (law)", lw=1)
        if telemetry is not None:
            ax.step(telemetry[0], telemetry[1][:, i], where="post", lw=0.8, alpha=0.8,
                    label="board telemetry on the bus (what the driver reads)")
        ax.plot(t, trajectory["att_dipole_applied_am2"][:, i], "--", label="applied (coils, the plant's torque)", lw=1)
        ax.axhline(limit_am2, color="r", lw=0.8)
        ax.axhline(-limit_am2, color="r", lw=0.8)
        _shade(ax, windows)
        if safe.any():
            ax.plot(t[safe], np.zeros(safe.sum()), "k|", markersize=10, label=f"coils in safe state ({safe.sum()} steps)")
        if missed.any():
            ax.plot(t[missed], np.zeros(missed.sum()), "rx", markersize=6,
                    label=f"plant step without its command ({missed.sum()})")
        ax.set_ylabel(f"m_{axis} [A m²]")
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize="small", ncol=2)
    field = trajectory["att_field_inertial_t"] * 1e9
    axes[3].plot(t, field, lw=1, label=["Bx", "By", "Bz"])
    axes[3].plot(t, np.linalg.norm(field, axis=1), "k", lw=1, label="|B|")
    axes[3].set_ylabel("field, inertial [nT]")
    axes[3].set_xlabel("simulated time [s]")
    axes[3].legend(fontsize="small", ncol=4)
    axes[3].grid(True, alpha=0.3)
    return plots.save(fig, path, dpi=90)


def attitude_section(run, plot_dir: Path) -> tuple[Section | None, dict | None]:
    trajectory, scenario = run.trajectory, run.scenario
    if scenario.kind != "attitude" or "att_time_s" not in trajectory:
        return None, None
    from bench.controller.attitude_laws import dipole_limit_am2

    metrics = attitude_metrics(trajectory, scenario)
    windows = fault_windows_sim_s(run.run_dir, scenario, trajectory)
    metrics["fault_windows_sim_s"] = windows
    loop = loop_figure(trajectory, scenario, windows, plot_dir / "attitude.png")
    dipole = dipole_figure(trajectory, dipole_limit_am2(scenario), windows, plot_dir / "dipole.png",
                           board_telemetry_am2(run))
    # Its figures are in the Summary's table already (the same rows): the section draws them.
    section = Section("Attitude", [
        f"Law {scenario.attitude_control.law}, estimator {scenario.estimator.mode}, "
        f"{metrics['steps']} steps of {scenario.step_s:g} s" + ("; fault windows (simulated time) shaded." if windows
                                                                 else ".") + " Its figures are in the Summary."],
        [],
        [Figure(Path(PLOTS_DIR) / loop.name, "Pointing error and body rate" if pointing_error_deg(trajectory, scenario)
                is not None else "Body rate"),
         Figure(Path(PLOTS_DIR) / dipole.name, "Dipole per axis against the limit (commanded, the board's telemetry "
                "on the bus, applied), and the field along the orbit")])
    from bench.report.attitude_plan import PLOT_FILE, plan_figure

    plan = plan_figure(run, plot_dir / PLOT_FILE)      # a run of the MILQR planner: its plans against the flight
    if plan is not None:
        section.figures.append(Figure(Path(PLOTS_DIR) / plan.name, "MILQR plans (dashed, one colour each) against "
                                      "the attitude flown and the dipole commanded (black)"))
    return section, metrics


def comparison_section(runs: list, plot_dir: Path, with_reference: bool = True) -> Section:
    """Attitude runs side by side. with_reference: the first run is the clean reference and every
    other is compared with it: the excess of its pointing error (or body rate) and its loop
    recovery after faults."""
    from bench.report.attitude_metrics import fault_effect

    reference = runs[0]
    rows = []
    fig, ax = plt.subplots(figsize=(11, 4))
    for i, run in enumerate(runs):
        metrics = attitude_metrics(run.trajectory, run.scenario)
        windows = fault_windows_sim_s(run.run_dir, run.scenario, run.trajectory)
        effect = {}
        if with_reference and i > 0:
            fault_end = max((end for _, _, end in windows), default=0.0)
            effect = fault_effect(reference.trajectory, run.trajectory, run.scenario, fault_end)
        error = pointing_error_deg(run.trajectory, run.scenario)
        quantity = error if error is not None else np.rad2deg(np.linalg.norm(run.trajectory["att_omega_radps"], axis=1))
        ax.plot(run.trajectory["att_time_s"], quantity, label=run.run_id, lw=1)
        _shade(ax, windows)
        rows.append([run.run_id, run.scenario.name, f"{metrics.get('final_pointing_error_deg', metrics['final_rate_dps']):.3g}",
                     f"{metrics['saturation_fraction']:.1%}", str(metrics["refused_board_reports"]),
                     "-" if not effect else f"{effect['max_excess']:.3g} ({effect['quantity']})",
                     "-" if not effect or effect["loop_recovery_s"] is None else f"{effect['loop_recovery_s']:.2f}"])
    ax.set_xlabel("simulated time [s]")
    ax.set_ylabel("pointing error [deg] or body rate [deg/s]")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small")
    path = plots.save(fig, plot_dir / "attitude_compare.png", dpi=90)
    note = (f"Reference (clean) run: {reference.run_id}. Excess = this run minus the reference, step by step "
            "(same seed; real-time runs differ slightly in timing even without faults). Loop recovery: simulated "
            "time after the last fault window until every step applies what the law commanded."
            if with_reference else "No reference run given (--reference RUN): no fault effect computed.")
    return Section("Attitude: effect of the faults", [note],
        [Table(["run", "scenario", "final error [deg] or rate [deg/s]", "saturated", "refused reports",
                "max excess", "loop recovery [s]"], rows)],
        [Figure(Path(PLOTS_DIR) / path.name, "Pointing error or body rate per run, fault windows shaded")])
