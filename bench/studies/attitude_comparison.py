"""MILQR + TVLQR against the sliding-mode, PD and B-dot laws on one slew, clean and with a bus
fault (issue 12): `bench compare-attitude`.

Every case is the in-process attitude loop (`bench.sim.simulate_attitude_in_process`: the plant,
estimator, controller cycle and planner the processes use, called in line, fault-free bus = the
board's DBC scaling and quantisation) on the same scenario with only `[attitude_control] law`
changed, scored by the report's attitude metrics against the slew's target. Both sit above the
studies layer, so they are looked up by name, as the campaign's in-process runner is.

Scores per case: final pointing error, settling time (the error stays inside 2 deg from then on),
dipole usage (integral of |m| and of |m|^2 over the run, of the dipole the coils applied),
saturation fraction (commands with an axis on the limit), planner wall time (MILQR, summed over
the run's plans) and the controller's cycle time (median and p99, wall clock of the law's eval
inside the deadline monitor). Times are this machine's and move with its load; the other columns
are deterministic (seeded, lock-step semantics).

Bus fault: the faulted variant describes a fault with the CAN fault machinery's own `FaultSpec`
(`bench.bus.can.faults`), with its start in simulated seconds. In process there is no bus, so the
fault's effect on the coils is modelled: command frames lost (drop, corrupt with the E2E CRC left,
error frames) for the fault's window mean no valid command reaches the board, whose command timeout
([can.board] command_timeout_s) then switches the coils off until commands come back. That is what
the process runs of `attitude_fault_commands` show (the board's command timeout puts the coils off).
Other fault kinds act through the board's telemetry or arbitration and are not modelled here.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from bench.bus.can.faults import FaultSpec
from bench.scenario import Scenario, load_scenario, parse_scenario, scenario_to_toml_dict

LAWS = ("tvlqr_plan", "sliding_mode", "pd", "bdot")
LABELS = {"tvlqr_plan": "MILQR + TVLQR", "sliding_mode": "sliding mode", "pd": "PD", "bdot": "B-dot"}
# Above the studies layer (bench.sim, bench.report): looked up by name, as bench.studies.campaign's RUNNERS.
IN_PROCESS_LOOP = "bench.sim:simulate_attitude_in_process"
ATTITUDE_METRICS = "bench.report.attitude_metrics:attitude_metrics"
# Faults on the command frames that keep every valid command from the board while they act.
COMMAND_LOSS_FAULTS = {"drop", "error_frames", "corrupt"}
DEFAULT_FAULT = FaultSpec(name="drop", frames=["MTQ_CMD"], start_s=300.0, duration_s=120.0)


def _by_name(target: str) -> Callable:
    module, _, function = target.partition(":")
    return getattr(importlib.import_module(module), function)


@dataclass(frozen=True)
class CoilsOffWindow:
    """The in-process effect of a command-loss fault: coils off over [off_s, on_s) in simulated time."""
    off_s: float
    on_s: float

    def __call__(self, time_s: float, applied_am2: np.ndarray) -> np.ndarray:
        return np.zeros(3) if self.off_s <= time_s < self.on_s else applied_am2


def coils_off_window(fault: FaultSpec, scenario: Scenario) -> CoilsOffWindow:
    """The window in which `fault` (start_s in simulated seconds) leaves the coils off: from the
    board's command timeout after the first lost frame to the first frame after the fault."""
    if scenario.can is None:
        raise ValueError("compare-attitude: a bus fault needs a scenario with a [can] section")
    if fault.name not in COMMAND_LOSS_FAULTS or fault.target_frames() != ("MTQ_CMD",) or \
            (fault.name == "corrupt" and fault.param("recompute_crc")) or fault.every != 1:
        raise ValueError(f"compare-attitude: fault {fault.name!r} on {list(fault.target_frames())} (every "
                         f"{fault.every}) is not modelled in process; modelled: every MTQ_CMD frame lost "
                         f"({', '.join(sorted(COMMAND_LOSS_FAULTS))}, corrupt without recompute_crc)")
    command_period_s = scenario.can.driver.command_period_s
    if fault.duration_s is not None:
        length_s = fault.duration_s
    elif fault.count > 0:
        length_s = fault.count * command_period_s
    else:
        raise ValueError(f"compare-attitude: fault {fault.name!r} needs duration_s or count (it would never end)")
    timeout_s = scenario.can.board.command_timeout_s
    if length_s <= timeout_s:
        return CoilsOffWindow(fault.start_s, fault.start_s)     # shorter than the timeout: no effect
    return CoilsOffWindow(fault.start_s + timeout_s, fault.start_s + length_s)


def case_scenario(base: Scenario, law: str, steps: int | None = None, estimator: str | None = None) -> Scenario:
    """The base scenario with another law (and optionally fewer steps or another estimator mode)."""
    data = scenario_to_toml_dict(base)
    data["attitude_control"]["law"] = law
    if steps is not None:
        data["run"]["steps"] = steps
    if estimator is not None:
        data["estimator"]["mode"] = estimator
    return parse_scenario(data, f"{base.name} with law {law!r}")


@dataclass
class CaseResult:
    law: str
    bus: str                        # "clean" or the fault's description
    final_error_deg: float
    settling_time_s: float | None
    dipole_integral_am2s: float     # integral of |m| dt
    dipole_energy_a2m4s: float      # integral of |m|^2 dt
    saturation_fraction: float
    planner_wall_s: float | None    # summed over the run's plans; None for laws without a planner
    plans: int
    cycle_p50_ms: float
    cycle_p99_ms: float
    error_deg: np.ndarray           # per step (plots)
    time_s: np.ndarray
    dipole_applied_am2: np.ndarray


def score(trajectory: dict, scored_against: Scenario, law: str, bus: str) -> CaseResult:
    """Scores of one run; `scored_against` gives the target, limit and board (B-dot has no target
    of its own: it is scored against the slew's)."""
    metrics = _by_name(ATTITUDE_METRICS)(trajectory, scored_against)
    from bench.gnc import quaternion as qt

    target = np.asarray(scored_against.attitude_control.target.q_wxyz, float)
    error_deg = np.rad2deg([qt.angle_between_rad(target, q) for q in trajectory["att_q_wxyz"]])
    dt_s = scored_against.step_s
    applied = trajectory["att_dipole_applied_am2"]
    cycle_ms = 1e3 * trajectory["att_control_cycle_time_s"]
    cycle_ms = cycle_ms[np.isfinite(cycle_ms)]
    planning = trajectory["planner_wall_time_s"]
    return CaseResult(
        law=law, bus=bus, final_error_deg=float(metrics["final_pointing_error_deg"]),
        settling_time_s=metrics["settling_time_s"],
        dipole_integral_am2s=float(np.linalg.norm(applied, axis=1).sum() * dt_s),
        dipole_energy_a2m4s=float((applied ** 2).sum() * dt_s),
        saturation_fraction=float(metrics["saturation_fraction"]),
        planner_wall_s=float(planning.sum()) if len(planning) else None, plans=len(planning),
        cycle_p50_ms=float(np.percentile(cycle_ms, 50)) if len(cycle_ms) else float("nan"),
        cycle_p99_ms=float(np.percentile(cycle_ms, 99)) if len(cycle_ms) else float("nan"),
        error_deg=error_deg, time_s=np.asarray(trajectory["att_time_s"]), dipole_applied_am2=applied)


def run_comparison(base: Scenario, laws=LAWS, fault: FaultSpec | None = DEFAULT_FAULT, steps: int | None = None,
                   estimator: str | None = None, progress: Callable[[str], None] = lambda _: None) -> list[CaseResult]:
    """Every law on the base scenario, clean and (fault given) with the fault; in process."""
    simulate = _by_name(IN_PROCESS_LOOP)
    scored_against = case_scenario(base, base.attitude_control.law, steps, estimator)
    coil_fault = coils_off_window(fault, scored_against) if fault is not None else None
    variants = [("clean", None)]
    if coil_fault is not None:
        variants.append((f"{fault.name} {'+'.join(fault.target_frames())} "
                         f"{fault.start_s:g}-{coil_fault.on_s:g} s", coil_fault))
    results = []
    for law in laws:
        scenario = case_scenario(base, law, steps, estimator)
        for bus, model in variants:
            progress(f"{LABELS.get(law, law)}, {bus}")
            results.append(score(simulate(scenario, coil_fault=model), scored_against, law, bus))
    return results


def markdown_table(results: list[CaseResult], base: Scenario) -> str:
    def num(value, fmt):
        return "-" if value is None or not np.isfinite(value) else format(value, fmt)

    lines = ["| law | bus | final error [deg] | settling (< 2 deg) [s] | int \\|m\\| dt [A m^2 s] | "
             "int \\|m\\|^2 dt [A^2 m^4 s] | saturated | planner wall [s] (plans) | cycle p50 / p99 [ms] |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in results:
        planner = "-" if r.planner_wall_s is None else f"{r.planner_wall_s:.1f} ({r.plans})"
        lines.append(f"| {LABELS.get(r.law, r.law)} | {r.bus} | {r.final_error_deg:.2f} | "
                     f"{num(r.settling_time_s, '.0f')} | {r.dipole_integral_am2s:.3g} | {r.dipole_energy_a2m4s:.3g} | "
                     f"{r.saturation_fraction:.1%} | {planner} | {num(r.cycle_p50_ms, '.2f')} / "
                     f"{num(r.cycle_p99_ms, '.2f')} |")
    return "\n".join(lines) + "\n"


def plot(results: list[CaseResult], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    buses = list(dict.fromkeys(r.bus for r in results))
    fig, axes = plt.subplots(1, len(buses), figsize=(6 * len(buses), 4), sharey=True, squeeze=False)
    for ax, bus in zip(axes[0], buses):
        for r in results:
            if r.bus == bus:
                ax.plot(r.time_s, r.error_deg, label=LABELS.get(r.law, r.law))
        ax.set_title(bus)
        ax.set_xlabel("time [s]")
        ax.grid(True)
    axes[0][0].set_ylabel("pointing error [deg]")
    axes[0][0].legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# --- the command ------------------------------------------------------------------------------
def add_commands(subparsers) -> None:
    p = subparsers.add_parser("compare-attitude", help="MILQR + TVLQR against sliding mode, PD and B-dot on one "
                                                       "slew, clean and with a bus fault (in process)")
    p.add_argument("--scenario", default="attitude_slew_milqr", help="the slew (default attitude_slew_milqr)")
    p.add_argument("--laws", nargs="+", default=list(LAWS), choices=list(LAWS))
    p.add_argument("--steps", type=int, default=None, help="steps per run (default the scenario's)")
    p.add_argument("--estimator", choices=["smoother", "truth"], default=None, help="default the scenario's")
    p.add_argument("--fault", default="drop", help="fault kind on MTQ_CMD (drop, corrupt, error_frames) or 'none'")
    p.add_argument("--fault-start-s", type=float, default=DEFAULT_FAULT.start_s, help="simulated seconds")
    p.add_argument("--fault-duration-s", type=float, default=DEFAULT_FAULT.duration_s)
    p.add_argument("--out", type=Path, default=None, help="also write the markdown table here")
    p.add_argument("--plot", type=Path, default=None, help="pointing error against time (PNG)")
    p.set_defaults(func=_main)


def _main(args) -> int:
    import sys

    try:
        base = load_scenario(args.scenario)
        fault = None if args.fault == "none" else FaultSpec(name=args.fault, frames=["MTQ_CMD"],
                                                             start_s=args.fault_start_s,
                                                             duration_s=args.fault_duration_s)
        if args.steps is not None and args.steps < 1:
            raise ValueError(f"--steps must be >= 1, got {args.steps}")
        results = run_comparison(base, args.laws, fault, args.steps, args.estimator,
                                 progress=lambda what: print(f"running {what}", file=sys.stderr, flush=True))
    except ValueError as exc:
        print(f"bench compare-attitude: {exc}", file=sys.stderr)
        return 2
    table = markdown_table(results, base)
    print(table, end="")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(table)
    if args.plot is not None:
        args.plot.parent.mkdir(parents=True, exist_ok=True)
        plot(results, args.plot)
    return 0
