"""What a run leaves when it ends, however it ends: metrics.json, the report and the summary on
the terminal (the report's modules imported while the run goes on)."""
from __future__ import annotations

import sys
import threading
from pathlib import Path

from bench.launcher.children import Child
from bench.launcher.endings import RunEnding
from bench.launcher.stats import unauthentic_drops
from bench.scenario import Scenario


def _import_report_meanwhile() -> None:
    """Import the report's modules (matplotlib, ~0.5 s) on a thread while the run goes on, not
    after it, where the user waits for them; the launcher's own thread only follows the run."""
    def load() -> None:
        import bench.report.build  # noqa: F401
        import bench.report.summary  # noqa: F401

    threading.Thread(target=load, name="import-report", daemon=True).start()


def _finish(run_dir: Path, scenario: Scenario, children: list[Child], stats: dict, wall_s: float,
            ending: RunEnding, write_report: bool, remote: dict[str, str] | None = None) -> None:
    """metrics.json, the report and the summary from whatever the run left (bench.report.summary);
    none of them may turn an ending into a crash."""
    from bench.report import summary

    processes = {c.name: {"pid": c.process.pid, "exit_code": c.process.returncode} for c in children}
    for name, host in (remote or {}).items():   # started on their own hosts: no pid of ours
        processes[name] = {"host": host, "pid": None, "exit_code": None}
    try:
        metrics = summary.run_metrics(run_dir, scenario, processes, stats, wall_s, ending.code, ending.reason)
    except Exception as exc:     # noqa: BLE001 - a broken file must not hide how the run ended
        print(f"bench: could not write metrics.json: {exc}", file=sys.stderr)
        return
    html = None
    if write_report:
        print("bench: building the report", file=sys.stderr)
        try:
            from bench.report.build import write_report as build_report

            _, html = build_report(run_dir)
            metrics = summary.read_metrics(run_dir) or metrics
        except Exception as exc:     # noqa: BLE001
            print(f"bench: could not build the report ({exc}); `bench report {run_dir}` retries", file=sys.stderr)
    if ending.reason is None:
        summary.print_summary(metrics, run_dir, summary.command_wall_time_s())
    else:
        for line in unauthentic_drops(stats, run_dir):     # often why a loop with an outside node stalls
            print(f"bench: {line}", file=sys.stderr)
        print(f"bench: partial run ({ending.reason}); metrics: {run_dir / 'metrics.json'}", file=sys.stderr)
    if html is not None:
        print(f"report: {html}")
