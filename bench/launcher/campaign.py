"""One campaign case as a full multi-process run (`bench campaign`, mode "processes"), in a
scratch directory."""
from __future__ import annotations

import os
from pathlib import Path

from bench.bus import keys
from bench.launcher.run import run_bench
from bench.scenario import Scenario


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
