"""`bench run`, `bench node` and `bench scenarios`: starting the loop as separate processes.

The launcher opens the hub session every node connects to, starts each node as its own OS process
(`bench node NAME ...`), waits until all are alive, follows the plant's progress, and shuts
everything down on success, on Ctrl-C, and when a node dies. Then it writes metrics.json.
"""
from __future__ import annotations

import json
import logging
import os
import queue
import secrets
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import msgspec
import numpy as np
import zenoh

from bench.bus import keys
from bench.bus.schemas import ProcessStats, StepDone, decode, MalformedMessage
from bench.bus.session import SessionConfigError, SessionOptions, free_loopback_port, loopback_endpoint, open_session
from bench.controller.config import PLANNED_LAWS
from bench.report.run_metrics import trajectory_metrics
from bench.runtime.node import NODES, node_options, run_node
from bench.runtime.process import start_node
from bench.scenario import Scenario, ScenarioError, builtin_names, load_scenario

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130
STARTUP_TIMEOUT_S = 60.0
SHUTDOWN_GRACE_S = 5.0
TOKEN_LOSS_GRACE_S = 1.0


class NodeFailed(RuntimeError):
    pass


# ------------------------------------------------------------------------------------------------
# Which processes a scenario needs
# ------------------------------------------------------------------------------------------------
def nodes_for(scenario: Scenario) -> list[str]:
    """In start order; they stop in reverse. The recorder first and last, so it sees everything;
    the CAN bus and board before the flight side and after it, so the driver never sees the board
    vanish at shutdown."""
    names = ["recorder"] if "recorder" in NODES else []
    if scenario.can is not None:
        names += ["canbus", "mtq"]
    names += ["plant", "estimator", "controller"]
    if scenario.kind == "attitude" and scenario.attitude_control.law in PLANNED_LAWS:
        names.append("planner")    # MILQR plans for the controller's tracker (issue 12)
    return names


# ------------------------------------------------------------------------------------------------
# Processes
# ------------------------------------------------------------------------------------------------
@dataclass
class Child:
    name: str
    process: subprocess.Popen
    log_path: Path

    def tail(self, lines: int = 8) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""


def _spawn(name: str, run_id: str, scenario_path: Path, hub: str, run_dir: Path, peers: list[str],
           zenoh_config: str | None) -> Child:
    log_path = run_dir / "logs" / f"{name}.log"
    return Child(name, start_node(name, run_id, scenario_path, hub, run_dir, log_path, peers, zenoh_config), log_path)


def _stop_children(children: list[Child], grace_s: float = SHUTDOWN_GRACE_S) -> None:
    """SIGTERM in reverse start order (recorder last), then SIGKILL whatever is left."""
    for child in reversed(children):
        if child.process.poll() is None:
            child.process.send_signal(signal.SIGTERM)
            try:
                child.process.wait(timeout=grace_s)
            except subprocess.TimeoutExpired:
                pass
    for child in children:
        if child.process.poll() is None:
            child.process.kill()
            child.process.wait()


def _check_children(children: list[Child], allowed_done: set[str]) -> None:
    for child in children:
        code = child.process.poll()
        if code is None:
            continue
        if code != 0 or child.name not in allowed_done:
            raise NodeFailed(
                f"process '{child.name}' (pid {child.process.pid}) exited with code {code}; "
                f"last lines of {child.log_path}:\n{child.tail()}"
            )


def _check_liveliness(children: list[Child], lost: list[tuple[str, float]], grace_s: float = TOKEN_LOSS_GRACE_S) -> None:
    """A node whose token vanished while its process runs on is hung (or cut off from the bus).

    A node that finishes drops its token just before it exits: give it a grace period.
    """
    for name, lost_at_s in lost:
        child = next((c for c in children if c.name == name), None)
        if child is None or time.monotonic() - lost_at_s < grace_s:
            continue
        if child.process.poll() is None:
            raise NodeFailed(
                f"process '{name}' (pid {child.process.pid}) stopped answering on Zenoh: its liveliness "
                f"token expired (hung, or cut off from the bus)"
            )


# ------------------------------------------------------------------------------------------------
# bench run
# ------------------------------------------------------------------------------------------------
def _new_run_id(scenario: Scenario) -> str:
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S")
    return f"{scenario.name}-{stamp}-{secrets.token_hex(2)}"


def _apply_overrides(scenario: Scenario, args) -> Scenario:
    run = scenario.run
    if args.mode:
        run = msgspec.structs.replace(run, mode=args.mode)
    if args.steps is not None:
        if args.steps < 1:
            raise ScenarioError(f"--steps must be at least 1, got {args.steps}")
        run = msgspec.structs.replace(run, steps=args.steps)
    return msgspec.structs.replace(scenario, run=run)


def _latency_percentiles_ms(trajectory: dict) -> dict:
    """End-to-end sense-to-actuation latency from the plant's stamps, in ms."""
    sensed, received = trajectory["stamp_sensed_ns"], trajectory["stamp_plant_received_ns"]
    ok = (sensed >= 0) & (received >= 0)
    if not ok.any():
        return {"samples": 0}
    latency_ms = (received[ok] - sensed[ok]) / 1e6
    return {
        "samples": int(ok.sum()),
        "p50_ms": float(np.percentile(latency_ms, 50)),
        "p90_ms": float(np.percentile(latency_ms, 90)),
        "p99_ms": float(np.percentile(latency_ms, 99)),
        "max_ms": float(latency_ms.max()),
    }


def write_metrics(run_dir: Path, scenario: Scenario, children: list[Child], stats: dict, wall_s: float) -> dict:
    with np.load(run_dir / "trajectory.npz") as data:
        trajectory = {k: data[k] for k in data.files}
    if scenario.kind == "attitude":
        from bench.report.attitude_metrics import attitude_metrics

        metrics = attitude_metrics(trajectory, scenario)
    else:
        metrics = trajectory_metrics(trajectory["state_m_mps"], trajectory["thrust_n"], scenario.params())
    metrics.update({
        "scenario": scenario.name,
        "mode": scenario.run.mode,
        "wall_time_s": wall_s,
        "end_to_end_latency": _latency_percentiles_ms(trajectory),
        "plant_missed_steps": int(trajectory["plant_missed_steps"]),
        "plant_late_commands": int(trajectory["plant_late_commands"]),
        "processes": {c.name: {"pid": c.process.pid, "exit_code": c.process.returncode} for c in children},
        "process_stats": stats,
    })
    (run_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return metrics


def _print_summary(metrics: dict, run_dir: Path) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"{metrics['scenario']} ({metrics['mode']}, {metrics['steps']} steps)")
    table.add_column("metric")
    table.add_column("value", justify="right")
    latency = metrics["end_to_end_latency"]
    if metrics.get("kind") == "attitude":
        from bench.report.attitude_metrics import summary_rows

        rows = summary_rows(metrics) + [("plant-side missed steps", str(metrics["plant_missed_steps"])),
                                        ("wall time", f"{metrics['wall_time_s']:.1f} s")]
    else:
        rows = _rendezvous_rows(metrics, latency)
    for name, value in rows:
        table.add_row(name, value)
    console = Console(stderr=False)
    console.print(table)
    console.print(f"run directory: {run_dir}")


def _rendezvous_rows(metrics: dict, latency: dict) -> list[tuple[str, str]]:
    return [
        ("final position error", f"{metrics['final_position_error_m']:.1f} m"),
        ("final velocity error", f"{metrics['final_velocity_error_mps']:.3f} m/s"),
        ("input cost J_u", f"{metrics['input_cost']:.3f} N^2"),
        ("fuel (L2)", f"{metrics['fuel_l2']:.1f} N s"),
        ("max |thrust|", f"{metrics['max_abs_thrust_N']:.3f} N"),
        ("constraints satisfied", "yes" if metrics["constraints_satisfied"] else "NO"),
        ("latency p50 / p99", f"{latency.get('p50_ms', float('nan')):.2f} / {latency.get('p99_ms', float('nan')):.2f} ms"),
        ("plant-side missed steps", str(metrics["plant_missed_steps"])),
        ("wall time", f"{metrics['wall_time_s']:.1f} s"),
    ]


def _follow_run(session, run_id: str, children: list[Child], n_steps: int, show_progress: bool) -> None:
    """Block until the plant finishes; raise NodeFailed if any process dies first."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    steps: queue.Queue[int] = queue.Queue()

    def on_step(sample) -> None:
        try:
            steps.put(decode(sample.payload.to_bytes(), StepDone).header.seq)
        except MalformedMessage:
            pass   # garbage on the status topic must not stop the launcher

    subscriber = session.declare_subscriber(keys.key(run_id, keys.STATUS_STEP), on_step)
    lost: list[tuple[str, float]] = []

    def on_token(sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            lost.append((str(sample.key_expr).rsplit("/", 1)[-1], time.monotonic()))

    tokens = session.liveliness().declare_subscriber(keys.key(run_id, f"{keys.ALIVE}/*"), on_token)
    plant = next(c for c in children if c.name == "plant")
    columns = [TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn()]
    with Progress(*columns, disable=not show_progress, transient=False) as progress:
        task = progress.add_task("steps", total=n_steps)
        done = 0
        while plant.process.poll() is None:
            try:
                _check_children(children, allowed_done=set())
            except NodeFailed:
                # A peer that noticed a hung node first may exit before the grace period is
                # over; the hung one is the cause to name.
                _check_liveliness(children, lost, grace_s=0.0)
                raise
            _check_liveliness(children, lost)
            try:
                done = max(done, steps.get(timeout=0.1) + 1)
                progress.update(task, completed=done)
            except queue.Empty:
                pass
        progress.update(task, completed=done)
    subscriber.undeclare()
    tokens.undeclare()
    if plant.process.returncode != 0:
        _check_liveliness(children, lost, grace_s=0.0)
        _check_children([plant], allowed_done=set())


def _collect_stats(session, run_id: str) -> tuple[dict, object]:
    stats: dict = {}

    def on_stats(sample) -> None:
        try:
            message = decode(sample.payload.to_bytes(), ProcessStats)
        except MalformedMessage:
            return
        stats[message.process] = {"published": message.published, "malformed": message.malformed}

    return stats, session.declare_subscriber(keys.key(run_id, f"{keys.STATUS_STATS}/*"), on_stats)


def _wait_alive(session, run_id: str, children: list[Child]) -> None:
    names = {c.name for c in children}
    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while True:
        _check_children(children, allowed_done=set())
        alive = set()
        for reply in session.liveliness().get(keys.key(run_id, f"{keys.ALIVE}/*"), timeout=0.5):
            if reply.ok is not None:
                alive.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
        if names <= alive:
            return
        if time.monotonic() > deadline:
            raise NodeFailed(f"processes not alive after {STARTUP_TIMEOUT_S} s: {', '.join(sorted(names - alive))}")
        time.sleep(0.05)


def run_bench(scenario: Scenario, run_id: str, runs_dir: Path, port: int | None, show_progress: bool = True,
              zenoh_config: str | None = None, write_report: bool = True) -> tuple[int, Path]:
    """Run a scenario as separate processes. Returns (exit code, run directory)."""
    hub = loopback_endpoint(port or free_loopback_port())
    # The session first: a taken port must fail before anything is written or started.
    session = open_session(SessionOptions(listen=(hub,), config_file=Path(zenoh_config) if zenoh_config else None))
    run_dir = runs_dir / run_id
    (run_dir / "logs").mkdir(parents=True, exist_ok=True)
    scenario_path = run_dir / "scenario.json"
    scenario_path.write_bytes(msgspec.json.format(msgspec.json.encode(scenario)))
    children: list[Child] = []
    started = time.monotonic()
    stats, stats_subscriber = _collect_stats(session, run_id)
    try:
        names = nodes_for(scenario)
        loop_peers = [n for n in names if n != "plant"]
        for name in names:
            peers = loop_peers if name == "plant" else []
            children.append(_spawn(name, run_id, scenario_path, hub, run_dir, peers, zenoh_config))
        _wait_alive(session, run_id, children)
        _follow_run(session, run_id, children, scenario.n_steps, show_progress)
        wall_s = time.monotonic() - started
        _stop_children(children)
        time.sleep(0.1)   # the last stats samples are on their way
        _check_children(children, allowed_done={c.name for c in children})
        metrics = write_metrics(run_dir, scenario, children, stats, wall_s)
        _print_summary(metrics, run_dir)
        if write_report:
            from bench.report.build import write_report as build_report

            _, html = build_report(run_dir)
            print(f"report: {html}")
        return 0, run_dir
    except NodeFailed as exc:
        print(f"bench: error: {exc}", file=sys.stderr)
        return 1, run_dir
    except KeyboardInterrupt:
        print("bench: interrupted; stopping all processes", file=sys.stderr)
        return EXIT_INTERRUPTED, run_dir
    finally:
        _stop_children(children)
        stats_subscriber.undeclare()
        session.close()


def campaign_case(scenario: Scenario) -> dict:
    """One campaign row's metrics from a full multi-process run in a scratch directory
    (`bench campaign`, mode "processes"); a run that does not finish raises, naming the logs."""
    import contextlib
    import io
    import tempfile
    import zlib

    from bench.report.rundata import load_run
    from bench.studies.campaign_metrics import run_metrics

    run_id = keys.check_run_id(f"campaign-{zlib.crc32(scenario.name.encode()):08x}-{os.getpid()}")
    with tempfile.TemporaryDirectory(prefix="bench-campaign-") as runs_dir:
        with contextlib.redirect_stdout(io.StringIO()):           # the run's summary table
            code, run_dir = run_bench(scenario, run_id, Path(runs_dir), None, show_progress=False, write_report=False)
        if code != 0:
            logs = sorted((run_dir / "logs").glob("*.log"))
            tail = " | ".join(f"{p.stem}: {p.read_text().strip().splitlines()[-1:]}" for p in logs if p.stat().st_size)
            raise RuntimeError(f"bench run exited with {code}: {tail}")
        run = load_run(run_dir)
        commands = [m.body for m in run.on(keys.COMMAND_THRUST) if not m.body.get("fallback")]
        return run_metrics(run.trajectory["state_m_mps"], run.trajectory["thrust_n"], scenario.params(),
                           [c["solve_time_s"] for c in commands], [c.get("iterations", 0) for c in commands],
                           [c["ctrl_feasible"] for c in commands])


def cmd_run(args) -> int:
    try:
        scenario = _apply_overrides(load_scenario(args.scenario), args)
        run_id = keys.check_run_id(args.run_id or _new_run_id(scenario))
        if args.port is not None and not 0 < args.port < 65536:
            raise ScenarioError(f"--port must be between 1 and 65535, got {args.port}")
        code, _ = run_bench(scenario, run_id, Path(args.runs_dir), args.port, not args.no_progress, args.zenoh_config,
                            write_report=not args.no_report)
        return code
    except (ScenarioError, SessionConfigError, ValueError) as exc:
        print(f"bench: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT


# ------------------------------------------------------------------------------------------------
# bench node / bench scenarios
# ------------------------------------------------------------------------------------------------
def cmd_node(args) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s", stream=sys.stdout)
    try:
        scenario = load_scenario(args.scenario)
        run_id = keys.check_run_id(args.run_id)
        run_dir = Path(args.run_dir or Path("runs") / run_id)
        run_dir.mkdir(parents=True, exist_ok=True)
        peers = [p for p in (args.wait_for or "").split(",") if p]
        return run_node(args.name, run_id, scenario, node_options(args), run_dir, peers)
    except (ScenarioError, SessionConfigError, ValueError) as exc:
        print(f"bench node: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT


def cmd_scenarios(_args) -> int:
    for name in builtin_names():
        print(f"{name:28s} {load_scenario(name).description}")
    return 0


def add_commands(subparsers) -> None:
    run = subparsers.add_parser("run", help="run a scenario: plant, estimator and controller as processes")
    run.add_argument("scenario", nargs="?", help="built-in name or TOML file (default: rendezvous_lqr)")
    run.add_argument("--run-id", help="name of the run (default: scenario name and time)")
    run.add_argument("--runs-dir", default="runs", help="where run directories go (default: runs)")
    run.add_argument("--port", type=int, help="loopback TCP port of the hub session (default: a free one)")
    run.add_argument("--mode", choices=["lock-step", "real-time"], help="override the scenario's run.mode")
    run.add_argument("--steps", type=int, help="override the scenario's run.steps")
    run.add_argument("--zenoh-config", help="JSON5 Zenoh configuration applied under the bench's own settings")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    run.add_argument("--no-report", action="store_true", help="skip report.html/report.md (bench report RUN_DIR later)")
    run.set_defaults(func=cmd_run)

    node = subparsers.add_parser("node", help="run one bench process (the launcher uses this; also for other hosts)")
    node.add_argument("name", choices=sorted(NODES), help="which process")
    node.add_argument("--run-id", required=True)
    node.add_argument("--scenario", help="built-in name, TOML or the run directory's scenario.json")
    node.add_argument("--listen", action="append", help="endpoint to listen on (default: an ephemeral loopback port)")
    node.add_argument("--connect", action="append", help="endpoint of the hub, a router or a peer (repeatable)")
    node.add_argument("--run-dir", help="run directory (default: runs/RUN_ID)")
    node.add_argument("--wait-for", help="comma-separated nodes whose ready token to await before starting")
    node.add_argument("--zenoh-config", help="JSON5 Zenoh configuration")
    node.set_defaults(func=cmd_node)

    scenarios = subparsers.add_parser("scenarios", help="list the built-in scenarios")
    scenarios.set_defaults(func=cmd_scenarios)
