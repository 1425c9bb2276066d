"""The report's estimator section: RMS after convergence (the first sample does not dominate),
median error, NIS per step plotted with its chi-square band, gate rejections counted."""
from __future__ import annotations

import msgspec
import numpy as np
import pytest

from bench.bus import keys
from bench.bus.schemas import TranslationEstimate, TruthState, header
from bench.report.build import estimation_section
from bench.report.estimation import CONVERGENCE_SAMPLES
from bench.report.rundata import Recorded, RunData
from bench.scenario import parse_scenario


def _run(tmp_path, n: int = 60) -> RunData:
    rng = np.random.default_rng(2)
    messages = []
    for k in range(n):
        truth = np.zeros(6)
        # A 5 m/s velocity error on the first estimate (the 10 m/s prior), 1 mm/s later on.
        error = np.concatenate([rng.normal(0.0, 3.0, 3), np.full(3, 5.0 if k == 0 else 1e-3)])
        hdr = header("r", k, 600.0 * k)
        messages.append(Recorded(keys.TRUTH, k, msgspec.to_builtins(TruthState(hdr, truth.tolist(), [0.0] * 3))))
        estimate = TranslationEstimate(hdr, (truth + error).tolist(), np.diag([100.0] * 3 + [1e-4] * 3).ravel().tolist(),
                                       None, nis=None if k == 0 else 50.0 if k == 30 else 3.0, nis_dof=0 if k == 0 else 3,
                                       measurement_rejected=k == 30)
        messages.append(Recorded(keys.ESTIMATE_TRANSLATION, k, msgspec.to_builtins(estimate)))
    scenario = parse_scenario({"name": "t", "estimator": {"mode": "smoother"}})
    return RunData(tmp_path, "r", scenario=scenario, messages=messages)


def test_velocity_rms_is_not_the_first_samples(tmp_path):
    section, metrics = estimation_section(_run(tmp_path), tmp_path)
    # Over all samples the one 5 m/s sample makes the RMS 0.65 m/s; after convergence it is 1 mm/s.
    assert metrics["rms_error"]["vx"] == pytest.approx(np.sqrt((25.0 + 59e-6) / 60))
    assert metrics["rms_error_converged"]["vx"] == pytest.approx(1e-3)
    assert metrics["median_abs_error"]["vx"] == pytest.approx(1e-3)
    assert metrics["converged_after_samples"] == CONVERGENCE_SAMPLES
    assert metrics["mean_nis"] == pytest.approx((58 * 3.0 + 50.0) / 59)
    assert metrics["nis_dof"] == 3 and metrics["rejected_measurements"] == 1
    assert any(f.path.name == "nis.png" for f in section.figures)
    assert (tmp_path / "nis.png").stat().st_size > 10_000


def test_rejection_runs_and_reacquisitions_are_counted(tmp_path):
    # Rejected at 30 (one), 40-49 (ten in a row, then a used fix: a re-acquisition at the default
    # 8) and 55-56 with a step without a measurement between (still one run of two).
    run = _run(tmp_path)
    rejected_steps = {30, *range(40, 50), 55, 57}
    for m in run.messages:
        if m.topic == keys.ESTIMATE_TRANSLATION and m.seq > 0:
            m.body["measurement_rejected"] = m.seq in rejected_steps
            m.body["nis"] = None if m.seq == 56 else 50.0 if m.seq in rejected_steps else 3.0
    _, metrics = estimation_section(run, tmp_path)
    assert metrics["rejected_measurements"] == 13
    assert metrics["rejection_runs"] == 3 and metrics["longest_rejection_run"] == 10
    assert metrics["reacquisitions"] == 1
    assert metrics["mean_nis_accepted"] == pytest.approx(3.0)
