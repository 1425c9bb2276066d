"""Campaigns (bench/studies/campaign.py): expansion, engines, resume, failures, metrics, report.

Small specs (a few 30-step cases) so that every test is bounded; the seed 001 campaign itself is
`bench campaign seed001` (docs/campaigns.md), not a test.
"""
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bench.studies.campaign import CampaignError, expand, parse_spec, run_campaign
from bench.studies.campaign_engines import run_case
from bench.studies.campaign_results import parts_dir, read_rows
from bench.studies.campaign_metrics import TIMING_COLUMNS, run_metrics, time_to_rendezvous_s
from bench.studies.campaign_report import wilson_interval, write_report

TESTS_DIR = Path(__file__).parent
REPO = TESTS_DIR.parent

SMALL = {
    "name": "small",
    "base_scenario": "rendezvous_lqr",
    "seeds": 2,
    "steps": 30,
    "controllers": {"LQR": {"controller": {"type": "lqr"}}, "MPC": {"controller": {"type": "mpc", "horizon": 10}}},
    "dynamics": {"linear": {"plant": {"dynamics": "cwh"}}},
    "knowledge": {"truth": {"estimator": {"mode": "truth"}}, "noisy": {"estimator": {"mode": "smoother"}}},
    "initial_conditions": {"A": {"plant": {"initial_condition": "A"}, "sample_position_std_m": 500.0,
                                 "sample_velocity_std_mps": 0.005}},
}
# Every column but those that measure the machine.
VOLATILE = set(TIMING_COLUMNS) | {"wall_time_s"}


def _comparable(rows):
    return sorted(({k: v for k, v in r.items() if k not in VOLATILE} for r in rows), key=lambda r: r["case_id"])


def _assert_same_rows(a, b):
    a, b = _comparable(a), _comparable(b)
    assert [r["case_id"] for r in a] == [r["case_id"] for r in b]
    for ra, rb in zip(a, b):
        for key in ra:
            va, vb = ra[key], rb[key]
            if isinstance(va, float) and math.isnan(va):
                assert isinstance(vb, float) and math.isnan(vb), (ra["case_id"], key)
            else:
                assert va == vb, (ra["case_id"], key, va, vb)


@pytest.fixture
def tests_on_path(monkeypatch):
    """Workers (spawned processes, Ray workers, the CLI) import campaign_cases from tests/."""
    path = os.pathsep.join([str(REPO), str(TESTS_DIR), os.environ.get("PYTHONPATH", "")])
    monkeypatch.setenv("PYTHONPATH", path)
    monkeypatch.syspath_prepend(str(TESTS_DIR))


def test_expansion_is_the_grid_times_seeds_with_common_draws_and_named_errors():
    cases = expand(parse_spec(SMALL))
    assert len(cases) == 2 * 1 * 2 * 1 * 1 * 2
    assert cases[0].case_id == "LQR/linear/truth/A/none/seed1"
    by_id = {c.case_id: c for c in cases}
    x_lqr = by_id["LQR/linear/truth/A/none/seed1"].scenario["plant"]["initial_state_m_mps"]
    x_mpc = by_id["MPC/linear/noisy/A/none/seed1"].scenario["plant"]["initial_state_m_mps"]
    x_seed2 = by_id["LQR/linear/truth/A/none/seed2"].scenario["plant"]["initial_state_m_mps"]
    assert x_lqr == x_mpc and x_lqr != x_seed2          # same draw per seed in every cell
    assert by_id["MPC/linear/noisy/A/none/seed2"].scenario["run"]["seed"] == 2
    with pytest.raises(CampaignError, match="plant.dynamics"):
        expand(parse_spec({**SMALL, "dynamics": {"bad": {"plant": {"dynamics": "warp"}}}}))
    with pytest.raises(CampaignError, match="sample_radius_std"):
        expand(parse_spec({**SMALL, "knowledge": {"k": {"sample_radius_std": 0.1}}}))
    with pytest.raises(CampaignError, match="controllers"):
        parse_spec({**SMALL, "controllers": {}})
    with pytest.raises(CampaignError, match="without '/'"):
        parse_spec({**SMALL, "controllers": {"LQR/fast": {"controller": {"type": "lqr"}}}})


def test_a_bad_case_is_named_whole_and_scenario_names_are_unique():
    long_name = "noisy_sensor_and_an_uncertain_orbit_radius"
    spec = {**SMALL, "knowledge": {"truth": {"estimator": {"mode": "truth"}},
                                   long_name: {"estimator": {"mode": "smoother"}, "sample_radius_error_std": 0.01}}}
    cases = expand(parse_spec(spec))
    names = [c.scenario["name"] for c in cases]
    assert len(set(names)) == len(names) and max(map(len, names)) <= 40
    by_id = {c.case_id: c for c in cases}
    assert by_id["LQR/linear/truth/A/none/seed1"].scenario["name"] == "small.LQR.truth.s1"   # varying axes only
    orbit = by_id[f"MPC/linear/{long_name}/A/none/seed2"].scenario
    assert orbit["onboard"]["believed_radius_error"] != 0.0            # the draw is the flight side's belief
    assert f"MPC/linear/{long_name}/A/none/seed2" in orbit["description"]
    # A patch that breaks the scenario: the error names the case in full, not its 40-character name.
    broken = {**spec, "knowledge": {long_name: {"estimator": {"mode": "smoother", "translation": {"warp": 1}}}}}
    with pytest.raises(CampaignError, match=f"case LQR/linear/{long_name}/A/none/seed1: .*warp"):
        expand(parse_spec(broken))


def local_and_ray_rows(spec, directory: Path, cases: int) -> list[dict]:
    """The campaign run on the local pool and on a local Ray cluster (two workers each), every
    case run and none failed on both, the two tables' rows equal; the local rows."""
    ray = pytest.importorskip("ray")
    local = run_campaign(spec, directory / "local.parquet", engine="local", workers=2, show_progress=False)
    assert local.ran == cases and local.failed == 0
    ray.init(address="local", num_cpus=2, object_store_memory=100 * 1024**2, include_dashboard=False,
             log_to_driver=False)
    try:
        remote = run_campaign(spec, directory / "ray.parquet", engine="ray", workers=2, show_progress=False)
    finally:
        ray.shutdown()
    assert remote.ran == cases and remote.failed == 0
    rows = read_rows(directory / "local.parquet")
    _assert_same_rows(rows, read_rows(directory / "ray.parquet"))
    return rows


def test_local_and_ray_engines_give_identical_results(tmp_path, tests_on_path):
    local_and_ray_rows(parse_spec(SMALL), tmp_path, cases=8)


def test_killed_campaign_resumed_equals_uninterrupted(tmp_path, tests_on_path):
    spec_path = tmp_path / "slow.toml"
    spec_path.write_text(
        'name = "slow"\nbase_scenario = "rendezvous_lqr"\nseeds = 4\nsteps = 30\nmode = "campaign_cases:slow_case"\n'
        '[controllers.LQR]\ncontroller = { type = "lqr" }\n[controllers.MPC]\ncontroller = { type = "mpc", horizon = 10 }\n'
        '[dynamics.linear]\nplant = { dynamics = "cwh" }\n[knowledge.noisy]\nestimator = { mode = "smoother" }\n'
        '[initial_conditions.A]\nplant = { initial_condition = "A" }\nsample_position_std_m = 500.0\n')
    out = tmp_path / "resumed.parquet"
    command = [sys.executable, "-m", "bench.cli", "campaign", str(spec_path), "--out", str(out), "--workers", "1",
               "--flush-every", "1", "--no-progress", "--no-report"]
    process = subprocess.Popen(command, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while len(list(parts_dir(out).glob("part-*.parquet"))) < 2:
            assert process.poll() is None, process.stderr.read().decode()
            assert time.monotonic() < deadline, "no part files after 120 s"
            time.sleep(0.02)
        os.killpg(process.pid, signal.SIGKILL)
    finally:
        process.wait(timeout=30)
    assert not out.exists(), "killed too late: the campaign had finished"
    done_before = len(read_rows(out))
    assert 2 <= done_before < 8
    from bench.studies.campaign import load_spec

    spec = load_spec(spec_path)
    resumed = run_campaign(spec, out, workers=1, show_progress=False)
    assert resumed.skipped == done_before and resumed.ran == 8 - done_before
    assert not parts_dir(out).exists()
    uninterrupted = run_campaign(spec, tmp_path / "straight.parquet", workers=2, show_progress=False)
    assert uninterrupted.ran == 8
    _assert_same_rows(read_rows(out), read_rows(tmp_path / "straight.parquet"))
    again = run_campaign(spec, out, workers=1, show_progress=False)     # nothing left to do
    assert again.ran == 0 and again.skipped == 8


def test_raising_and_timing_out_cases_become_failed_rows(tmp_path, tests_on_path):
    spec = parse_spec({**SMALL, "controllers": {"LQR": {"controller": {"type": "lqr"}}},
                       "knowledge": {"truth": {"estimator": {"mode": "truth"}}}, "seeds": 3,
                       "mode": "campaign_cases:flaky_case", "case_timeout_s": 5.0})
    outcome = run_campaign(spec, tmp_path / "flaky.parquet", workers=2, show_progress=False)
    rows = {r["seed"]: r for r in read_rows(tmp_path / "flaky.parquet")}
    assert outcome.ran == 3 and outcome.failed == 2 and len(rows) == 3
    assert rows[1]["status"] == "ok" and np.isfinite(rows[1]["final_position_error_m"])
    assert rows[2]["status"] == "error" and "injected failure for seed 2" in rows[2]["error"]
    assert rows[2]["final_position_error_m"] is None and rows[2]["scenario_json"]
    assert rows[3]["status"] == "timeout" and "5 s" in rows[3]["error"]
    report = write_report(tmp_path / "flaky.parquet", tmp_path / "report")
    assert "<table>" in (tmp_path / "report" / "report.html").read_text()
    text = report.read_text()
    # 30 steps do not reach the target: 0 of 3, and the two failed runs count in n.
    assert "injected failure" in text and "0 % [0, 56] of 3" in text


def test_a_row_reruns_exactly_from_its_scenario():
    case = expand(parse_spec(SMALL))[5]
    first, second = run_case(case), run_case(case)
    assert first["status"] == "ok"
    import json

    rebuilt = type(case)(**{**case.__dict__, "scenario": json.loads(first["scenario_json"])})
    third = run_case(rebuilt)
    for key in first:
        if key not in VOLATILE:
            assert first[key] == second[key] == third[key] or (
                isinstance(first[key], float) and math.isnan(first[key]) and math.isnan(third[key])), key


def test_run_metrics_fuel_norms_time_to_rendezvous_and_divergence():
    from bench.gnc.cwh import RendezvousParams

    params = RendezvousParams.from_reference()
    dt = params.time_step_s
    u = np.array([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8], [0.0, 0.0, 0.0]])
    x = np.zeros((4, 6))
    x[:, 1] = [5000.0, 300.0, 50.0, 20.0]
    x[:, 4] = [2.0, 2.0, 0.5, 0.1]
    m = run_metrics(x, u, params, [1e-3, 2e-3, 3e-3], [0, 4, 8], [True, True, False])
    assert m["input_cost_n2"] == pytest.approx(2.0)
    assert m["fuel_l2_n_sqrt_s"] == pytest.approx(math.sqrt(dt * 2.0))     # ||u||_L2 of the held thrust
    assert m["fuel_l2_seed003"] == pytest.approx(dt * math.sqrt(2.0))
    assert m["delta_v_mps"] == pytest.approx((1.0 + 1.4) * dt / params.mass_kg)
    assert m["time_to_rendezvous_s"] == 2 * dt and m["rendezvous"]
    assert m["solve_time_p50_ms"] == pytest.approx(2.0) and m["infeasible_cycles"] == 1
    assert m["success"] and not m["diverged"]
    # Leaves the bounds again at the end: no rendezvous; ends farther than it started: diverged.
    x[-1, 1] = 9000.0
    m = run_metrics(x, u, params)
    assert not m["rendezvous"] and math.isnan(m["time_to_rendezvous_s"]) and m["diverged"] and not m["success"]
    assert math.isnan(time_to_rendezvous_s(x, dt, 100.0, 1.0))


def test_nees_of_a_run_against_an_explicit_inverse_and_a_monte_carlo_draw():
    from bench.studies.campaign_metrics import estimate_consistency

    rng = np.random.default_rng(3)
    steps = 4000
    root = rng.normal(size=(steps, 6, 6))
    covariance = root @ root.transpose(0, 2, 1) + 0.1 * np.eye(6)
    truth = rng.normal(size=(steps, 6)) * 100.0
    # Errors drawn from each step's covariance: the time-averaged NEES of a consistent estimate is 6.
    error = np.einsum("kij,kj->ki", np.linalg.cholesky(covariance), rng.standard_normal((steps, 6)))
    m = estimate_consistency(truth - error, covariance, truth)
    explicit = np.mean([e @ np.linalg.inv(p) @ e for e, p in zip(error, covariance)])
    assert m["nees_mean"] == pytest.approx(explicit, rel=1e-9)
    assert 6 * (1 - 4 * math.sqrt(2 / (6 * steps))) < m["nees_mean"] < 6 * (1 + 4 * math.sqrt(2 / (6 * steps)))
    assert m["nees_steps"] == steps and m["estimate_position_error_final_m"] == pytest.approx(np.linalg.norm(error[-1, :3]))
    # An estimate that believes itself 4x tighter than it is: NEES 4x larger.
    assert estimate_consistency(truth - error, covariance / 4, truth)["nees_mean"] == pytest.approx(4 * explicit)
    # Full state knowledge has no covariance: no NEES.
    none = estimate_consistency(truth, np.full((steps, 6, 6), np.nan), truth)
    assert math.isnan(none["nees_mean"]) and none["nees_steps"] == 0


def test_nees_bounds_against_a_published_value():
    from bench.studies.campaign_report import nees_bounds

    # Bar-Shalom, Li, Kirubarajan (2001), 5.4.2: 2 states, 50 runs -> [1.5, 2.6].
    low, high = nees_bounds(50, dof=2)
    assert round(low, 1) == 1.5 and round(high, 1) == 2.6
    low, high = nees_bounds(30)
    assert low < 6 < high


def test_wilson_interval_against_a_published_value():
    # Newcombe (1998), Statistics in Medicine 17, table I: 81 of 263 -> 0.2553 to 0.3662 (Wilson).
    low, high = wilson_interval(81, 263)
    assert low == pytest.approx(0.2553, abs=5e-5) and high == pytest.approx(0.3662, abs=5e-5)
    # and 0 of 10 -> 0 to 0.2775
    low, high = wilson_interval(0, 10)
    assert low == 0.0 and high == pytest.approx(0.2775, abs=5e-5)
    low, high = wilson_interval(30, 30)
    assert high == pytest.approx(1.0) and low == pytest.approx(0.8865, abs=5e-4)
