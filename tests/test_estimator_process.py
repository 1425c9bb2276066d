"""A process run (plant, estimator, controller over Zenoh) with the range/bearing sensor: the plant
publishes it, the estimator uses it, every estimate carries its NIS."""
from __future__ import annotations

import numpy as np
from conftest import run_bench_cli

from bench.bus import keys
from bench.report.rundata import load_run

SCENARIO = '''name = "range_bearing_process"
[run]
steps = 20
[estimator]
mode = "smoother"
translation.sensor = "range_bearing"
translation.gate_probability = 0.9999
'''


def test_a_process_run_flies_on_range_and_bearing(tmp_path, runs_dir):
    path = tmp_path / "rb.toml"
    path.write_text(SCENARIO)
    result = run_bench_cli("run", str(path), "--run-id", "rb-process", "--runs-dir", str(runs_dir), "--no-progress",
                           "--no-report", timeout_s=300)
    assert result.returncode == 0, result.stderr[-2000:]
    run = load_run(runs_dir / "rb-process")
    sensed = run.on(keys.SENSE_RANGE_BEARING)
    estimates = run.on(keys.ESTIMATE_TRANSLATION)
    assert len(sensed) == 20 and len(estimates) == 20
    nis = [m.body["nis"] for m in estimates[1:]]
    assert all(v is not None and np.isfinite(v) for v in nis)
    assert all(m.body["nis_dof"] == 3 for m in estimates[1:])
    truth = {m.seq: np.array(m.body["state_m_mps"]) for m in run.on(keys.TRUTH)}
    errors = [np.linalg.norm(np.array(m.body["state_m_mps"][:3]) - truth[m.seq][:3]) for m in estimates[5:]]
    assert np.median(errors) < 100.0
