"""A run's figures and verdict: metrics.json as the launcher leaves it, and the terminal summary.

`run_metrics` is written as soon as the processes are down (a partial run too); the report
(bench.report.build) adds its sections to the same file; `verdict` judges the scenario's
criteria (bench/criteria.py) against whatever the file holds, and `print_summary` shows the
figures a GNC engineer reads first, the verdict, and the wall time of the whole command.

metrics.json keeps one place for each figure: the loop's own figures at the top level
(rendezvous: final errors, cost, fuel, constraints; attitude: rates, pointing, saturation), the
sense-to-apply latency from the plant's stamps under `end_to_end_latency`, and each report
section under its own key (latency_ms, deadlines, can_bus, ...).
"""
from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path

import numpy as np

from bench.criteria import verdict as judge_criteria
from bench.plant.acceptance import ACCEPTANCE_FILE
from bench.report import canbus
from bench.report.jsonout import write_json
from bench.report.rundata import CAN_LOG_FILE, RunData
from bench.report.run_metrics import trajectory_metrics
from bench.scenario import Scenario

METRICS_FILE = "metrics.json"


def run_metrics(run_dir: Path, scenario: Scenario, processes: dict[str, dict], stats: dict, wall_s: float,
                exit_code: int, end_reason: str | None) -> dict:
    """metrics.json from whatever the run left: a partial run is marked with the reason it ended.
    processes: name -> {"pid", "exit_code"} (or {"host"} for a node on another host)."""
    metrics: dict = {}
    trajectory = load_trajectory(run_dir, scenario)
    if trajectory is not None:
        if scenario.kind == "attitude":
            from bench.report.attitude_metrics import attitude_metrics

            metrics = attitude_metrics(trajectory, scenario)
        else:
            metrics = trajectory_metrics(trajectory["state_m_mps"], trajectory["thrust_n"], scenario.params())
    metrics.update({"scenario": scenario.name, "mode": scenario.run.mode, "wall_time_s": wall_s,
                    "processes": processes, "process_stats": stats})
    if trajectory is not None:
        metrics.update({
            # sensed -> applied: with the plant's one-step hold in real time, not in lock-step
            "end_to_end_latency": {**sense_to_apply_percentiles_ms(trajectory),
                                   "quantity": "sensed -> applied",
                                   "includes_step_hold": scenario.run.mode == "real-time"},
            # sensed -> command at the plant: no hold in either mode, comparable across modes
            "sense_to_plant_latency": {**sense_to_apply_percentiles_ms(trajectory, "plant_received"),
                                       "quantity": "sensed -> command at the plant", "includes_step_hold": False},
            "plant_missed_steps": int(trajectory.get("plant_missed_steps", 0)),
            "plant_late_commands": int(trajectory.get("plant_late_commands", 0)),
        })
    acceptance = _read_json(run_dir / ACCEPTANCE_FILE)
    if acceptance is not None:
        metrics["command_acceptance"] = acceptance
    if getattr(scenario, "can", None) is not None:
        # The bus's figures too, which criteria judge, whether or not a report is written.

        can_log = Path(run_dir) / CAN_LOG_FILE
        _, can_bus, _ = canbus.can_metrics(RunData(Path(run_dir), Path(run_dir).name, scenario, trajectory=trajectory or {},
                                         can_log=can_log if can_log.is_file() else None))
        if can_bus is not None:
            metrics["can_bus"] = can_bus
    metrics["exit_code"] = exit_code
    metrics["partial"] = end_reason is not None
    if end_reason is not None:
        metrics["end_reason"] = end_reason
    metrics["verdict"] = verdict(scenario, metrics)
    write_json(run_dir / METRICS_FILE, metrics)
    return metrics


def verdict(scenario: Scenario, metrics: dict) -> dict:
    return judge_criteria(scenario.criteria, metrics, partial=bool(metrics.get("partial")))


def sense_to_apply_percentiles_ms(trajectory: dict, until: str = "applied") -> dict:
    """Sensing to the plant applying the command of the same step (`until` "plant_received": to the
    command reaching the plant), from the plant's stamps, in ms (steps whose chain is incomplete are
    left out and counted apart)."""
    sensed = trajectory["stamp_sensed_ns"]
    applied = trajectory.get(f"stamp_{until}_ns")
    if applied is None:
        return {"samples": 0, "incomplete": int(len(sensed))}
    ok = (sensed >= 0) & (applied >= 0)
    if not ok.any():
        return {"samples": 0, "incomplete": int(len(sensed))}
    latency_ms = (applied[ok] - sensed[ok]) / 1e6
    return {
        "samples": int(ok.sum()),
        "incomplete": int((~ok).sum()),
        "p50_ms": float(np.percentile(latency_ms, 50)),
        "p90_ms": float(np.percentile(latency_ms, 90)),
        "p99_ms": float(np.percentile(latency_ms, 99)),
        "max_ms": float(latency_ms.max()),
    }


def load_trajectory(run_dir: Path, scenario: Scenario) -> dict | None:
    """The run's trajectory, or None where it is missing, broken or holds no step."""
    try:
        with np.load(run_dir / "trajectory.npz") as data:
            trajectory = {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile):
        return None
    needed = ("att_time_s", "att_q_wxyz") if scenario.kind == "attitude" else ("state_m_mps", "thrust_n")
    if any(k not in trajectory for k in needed) or len(trajectory[needed[-1]]) == 0:
        return None
    return trajectory


def read_metrics(run_dir: Path) -> dict | None:
    value = _read_json(Path(run_dir) / METRICS_FILE)
    return value if isinstance(value, dict) else None


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def command_wall_time_s() -> float | None:
    """How long this process has run, interpreter start and imports included (Linux /proc); None
    elsewhere. The summary's wall time is the command's, not the loop's."""
    try:
        start_ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        uptime_s = float(Path("/proc/uptime").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None
    return uptime_s - start_ticks / os.sysconf("SC_CLK_TCK")


def summary_rows(metrics: dict) -> list[tuple[str, str]]:
    """The figures of the terminal summary, for either loop."""
    if metrics.get("kind") == "attitude":
        from bench.report.attitude_metrics import summary_rows as attitude_rows

        rows = attitude_rows(metrics)
    else:
        rows = _rendezvous_rows(metrics)
    loop = metrics.get("sense_to_plant_latency", {})
    if loop.get("samples"):
        rows.append(("sense -> command at plant p50 / p99 (loop, no hold)", f"{loop['p50_ms']:.2f} / {loop['p99_ms']:.2f} ms"))
    latency = metrics.get("end_to_end_latency", {})
    if latency.get("samples"):
        hold = " (with the plant's step hold)" if latency.get("includes_step_hold") else " (no hold: lock-step)"
        rows.append(("sense -> applied p50 / p99" + hold, f"{latency['p50_ms']:.2f} / {latency['p99_ms']:.2f} ms"))
    rows.append(("plant-side missed steps", str(metrics.get("plant_missed_steps", "-"))))
    rows += _bus_rows(metrics.get("can_bus"))
    return rows


def _rendezvous_rows(metrics: dict) -> list[tuple[str, str]]:
    if "final_position_error_m" not in metrics:
        return []
    return [
        ("position error at the last step", f"{metrics['final_position_error_m']:.1f} m"),
        ("velocity error at the last step", f"{metrics['final_velocity_error_mps']:.3f} m/s"),
        ("input cost J_u", f"{metrics['input_cost']:.3f} N^2"),
        ("fuel (L2)", f"{metrics['fuel_l2']:.1f} N s"),
        ("max |thrust|", f"{metrics['max_abs_thrust_N']:.3f} N"),
        ("constraints satisfied", constraints_text(metrics)),
    ]


def constraints_text(metrics: dict) -> str:
    """'yes', or 'NO: ' and each check that failed with its value and bound."""
    if metrics.get("constraints_satisfied"):
        return "yes"
    failed = [c for c in metrics.get("constraints") or [] if not c["satisfied"]]
    if not failed:
        return "NO"
    return "NO: " + "; ".join(f"{c['name']} {c['value']:.4g} {c['unit']} > {c['bound']:.4g} {c['unit']}" for c in failed)


def _bus_rows(bus: dict | None) -> list[tuple[str, str]]:
    """The magnetorquer bus, where the run had one (the report's CAN section)."""
    if not isinstance(bus, dict):
        return []
    rows = [("CAN frames / peak load", f"{bus.get('frames', 0)} / {100 * bus.get('peak_load', 0.0):.0f} %")]
    if bus.get("authenticated") is False:
        rows.append(("CAN bus authentication", "NONE (e2e profile): anyone on the bus can command the coils"))
    bus_off = (bus.get("bus_off") or {}).get("nodes") or {}
    if bus_off:
        rows.append(("CAN bus-off episodes (recovered)",
                     ", ".join(f"{node} {n['episodes']} ({n['recovered']})" for node, n in bus_off.items())))
    power = bus.get("board_power") or {}
    if power:
        worst = power.get("max_recovery_ms")
        rows.append(("board power losses (operational again)", f"{power['losses']} ({power['recovered']}"
                     + (f", NMT start within {worst / 1e3:.3g} s of the boot, simulated)" if worst is not None else ")")))
    driver = bus.get("driver") or {}
    if driver:
        events = dict(driver.get("events", {}))
        # The driver's own command thread woken late is the host's doing, not a fault: apart.
        overruns = events.pop("host_overrun", 0)
        # The FDIR's detections (kinds fdir_*, from the dynamics) travel with the driver's: apart.
        fdir = {k: events.pop(k) for k in [k for k in events if k.startswith("fdir_")]}
        rows.append(("faults the driver detected", ", ".join(f"{k} {v}" for k, v in sorted(events.items())) or "none"))
        rows.append(("faults the FDIR detected (from the dynamics)",
                     ", ".join(f"{k} {v}" for k, v in sorted(fdir.items())) or "none"))
        if overruns:
            rows.append(("host overruns (flight side late, not a fault)", str(overruns)))
        rows.append(("board healthy at the end", "yes" if driver.get("board_ok_at_end") else "NO"))
    return rows


def verdict_lines(result: dict) -> list[str]:
    """The verdict and one line per criterion (the reasons are in the report and metrics.json)."""
    if result.get("passed") is None:
        return ["verdict: not judged (the scenario declares no criteria)"]
    lines = [f"verdict: {'PASS' if result['passed'] else 'FAIL'}" + (" (partial run)" if result.get("partial_run") else "")]
    for c in result["criteria"]:
        value = c["value"]
        shown = f"{value:.4g}" if isinstance(value, float) else str(value)
        lines.append(f"  {'ok  ' if c['passed'] else 'FAIL'} {c['metric']} {c['bound']}: {shown}")
    return lines


def print_summary(metrics: dict, run_dir: Path, wall_s: float | None) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"{metrics['scenario']} ({metrics['mode']}, {metrics.get('steps', '?')} steps)")
    table.add_column("metric", no_wrap=True)
    table.add_column("value", justify="right")
    rows = summary_rows(metrics)
    if wall_s is not None:
        rows.append(("wall time (the command)", f"{wall_s:.1f} s"))
    for name, value in rows:
        table.add_row(name, value)
    console = Console(stderr=False)
    console.print(table)
    for line in verdict_lines(metrics.get("verdict", {})):
        console.print(line, highlight=False, markup=False)
    console.print(f"run directory: {run_dir}")
