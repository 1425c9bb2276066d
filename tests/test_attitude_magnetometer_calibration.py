"""Issue 46: the magnetometer calibration in the attitude report's Estimator section.

`bench run` of a short lock-step attitude hold with the smoother (the processes: the calibration
leaves the estimator process only in its `estimate/attitude` messages), once with
`estimate_magnetometer_calibration = true` and a magnetometer whose true bias is not zero, once
without. The truth the test holds the estimate to is the scenario's own sensor bias (what the
plant adds to the field), never a number the estimator or the report produced: the final bias
estimate must be nearer to it than the smoother's belief before the run (zero, its prior mean).
Without the calibration the section, its figure and its metrics are as they were.
"""
from __future__ import annotations

import json
import struct

import msgspec
import numpy as np
import pytest

from bench.bus import keys
from bench.report.rundata import load_run
from bench.scenario import load_scenario
from conftest import run_bench_cli

RUN_TIMEOUT_S = 600     # a loaded 2-core machine starts the processes slowly
STEPS = 30              # 30 s at 1 Hz: 30 magnetometer samples and star-tracker fixes
TRUE_MAGNETOMETER_BIAS_T = [3.0e-6, -2.0e-6, 1.5e-6]   # body axes; a few % of the ~40 uT field

pytestmark = pytest.mark.timeout(3 * RUN_TIMEOUT_S)


def scenario(calibrate: bool) -> dict:
    """attitude_pointing (the smoother in the loop) cut to STEPS steps at 1 Hz, its magnetometer
    biased; without the CAN bus (not what this is about: fewer processes on a busy machine)."""
    data = msgspec.to_builtins(load_scenario("attitude_pointing"))
    data["name"] = "attitude_magnetometer_calibration"
    data["run"]["steps"] = STEPS
    data["attitude"]["sensors"]["gyro_rate_hz"] = 1.0
    data["attitude"]["sensors"]["magnetometer_bias_t"] = TRUE_MAGNETOMETER_BIAS_T
    data["estimator"]["attitude"]["estimate_magnetometer_calibration"] = calibrate
    data.pop("can", None)
    data["criteria"] = []
    return data


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """run id -> (run directory, metrics.json, report.md's Estimator section)."""
    directory = tmp_path_factory.mktemp("magnetometer_calibration")
    out = {}
    for run_id, calibrate in (("calibrated", True), ("uncalibrated", False)):
        path = directory / f"{run_id}.json"
        path.write_text(json.dumps(scenario(calibrate)))
        result = run_bench_cli("run", str(path), "--run-id", run_id, "--runs-dir", str(directory), "--no-progress",
                               timeout_s=RUN_TIMEOUT_S)
        assert result.returncode == 0, result.stderr[-3000:] + result.stdout[-2000:]
        run_dir = directory / run_id
        metrics = json.loads((run_dir / "metrics.json").read_text())
        assert all(p["exit_code"] == 0 for p in metrics["processes"].values())
        report = (run_dir / "report.md").read_text()
        assert "\n## Estimator\n" in report
        section = report.split("\n## Estimator\n", 1)[1].split("\n## ", 1)[0]
        out[run_id] = (run_dir, metrics, section)
    return out


def png_height_px(path) -> int:
    with open(path, "rb") as f:
        header = f.read(24)
    return struct.unpack(">I", header[20:24])[0]


def test_the_estimator_section_shows_the_magnetometer_calibration_against_the_truth(runs):
    run_dir, metrics, section = runs["calibrated"]
    true_ut = np.array(TRUE_MAGNETOMETER_BIAS_T) * 1e6
    prior_ut = np.zeros(3)                  # the smoother's default belief: no bias, scale 1

    # the estimator process published it: every valid estimate carries a calibration
    estimates = [m.body for m in load_run(run_dir).on(keys.ESTIMATE_ATTITUDE) if m.body["valid"]]
    assert len(estimates) > STEPS // 2
    assert all(e["magnetometer_bias_t"] is not None and e["magnetometer_scale"] is not None for e in estimates)

    cal = metrics["estimator_error"]["magnetometer_calibration"]
    np.testing.assert_allclose(cal["bias_true_ut"], true_ut, rtol=1e-12)
    assert cal["scale_true"] == 1.0 and cal["scale_prior"] == 1.0
    final_ut = np.array(cal["bias_estimated_final_ut"])
    last = max(estimates, key=lambda e: e["header"]["seq"])
    np.testing.assert_allclose(final_ut, np.array(last["magnetometer_bias_t"]) * 1e6, rtol=1e-12)
    np.testing.assert_allclose(cal["bias_error_final_ut"], final_ut - true_ut, rtol=1e-9, atol=1e-12)
    # the estimate learnt: nearer to the plant's bias than the belief it started from (3.9 uT off)
    error_ut = np.linalg.norm(final_ut - true_ut)
    assert error_ut < 0.5 * np.linalg.norm(prior_ut - true_ut), (final_ut, true_ut)
    assert cal["bias_prior_error_norm_ut"] == pytest.approx(np.linalg.norm(prior_ut - true_ut))
    assert abs(cal["scale_estimated_final"] - 1.0) < 0.05

    # the rows, beside the section's own
    for row in ("| magnetometer bias estimated at the end [µT] (x, y, z) |",
                "| magnetometer bias true, the plant's [µT] (x, y, z) | 3, -2, 1.5 |",
                "| magnetometer bias error at the end [µT] (x, y, z); norm |",
                "| magnetometer scale estimated at the end / true / error |",
                "NEES", "gyro bias"):
        assert row in section, row
    # the figure: two panels more (bias, scale) than without the calibration
    plot = run_dir / "plots" / "attitude_estimator.png"
    assert "magnetometer bias and scale" in section
    assert png_height_px(plot) > png_height_px(runs["uncalibrated"][0] / "plots" / "attitude_estimator.png")


def test_without_the_calibration_the_section_is_as_before(runs):
    run_dir, metrics, section = runs["uncalibrated"]
    estimates = [m.body for m in load_run(run_dir).on(keys.ESTIMATE_ATTITUDE)]
    assert estimates and all(e["magnetometer_bias_t"] is None and e["magnetometer_scale"] is None for e in estimates)
    assert "magnetometer_calibration" not in metrics["estimator_error"]
    assert metrics["estimator_error"]["mean_nees"] is not None
    assert "magnetometer" not in section
    assert png_height_px(run_dir / "plots" / "attitude_estimator.png") == 12 * 90    # the five panels, as before


def test_the_law_gets_the_field_with_the_believed_calibration_undone():
    """measured = scale * B_body + bias: the estimate's field_body_t is (measured - bias) / scale,
    with the smoother's belief before it estimates anything (here: no estimation at all)."""
    from bench.estimator.attitude_frontend import AttitudeEstimator
    from bench.scenario import parse_scenario

    data = scenario(calibrate=False)
    data["estimator"]["attitude"]["magnetometer_bias_t"] = TRUE_MAGNETOMETER_BIAS_T
    data["estimator"]["attitude"]["magnetometer_scale"] = 1.05
    estimator = AttitudeEstimator(parse_scenario(data, "test"))
    field_body_t = np.array([20e-6, -15e-6, 30e-6])
    measured_t = 1.05 * field_body_t + np.array(TRUE_MAGNETOMETER_BIAS_T)
    out = estimator.step(0, 0.0, np.zeros(3), measured_t, np.array([0.0, 0.0, 4e-5]), None)
    np.testing.assert_allclose(out.field_body_t, field_body_t, rtol=0, atol=1e-15)
