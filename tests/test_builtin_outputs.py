"""Every built-in scenario, in a short form, as processes: what a user reads is right.

Each scenario runs as `bench run` does (its own mode: lock-step, or real time where it is real
time), cut short: a few steps, and where it injects bus faults, the faults moved to the start of
the run and shortened so that each one happens inside it. On the outputs:
- every step's stamp chain runs forward (each stage's stamp at or after the one before), so no
  latency anywhere is negative, in trajectory.npz and in metrics.json's per-hop table;
- every fault window lies inside the run on simulated time, and overlaps the frames the fault
  affected (the bus model's first and last, mapped by the run's own time base);
- every report section of the run's loop is there and holds a table or a figure, the Deadlines
  section counts the controller's cycles;
- the summary, metrics.json and the report carry a pass/fail verdict;
- (issue 46, the fault run in both modes and the runs with a smoother) every CAN frame on the run's
  simulated time in can_frames.parquet, the report's telemetry trace and the MCAP's decoded CAN
  topics; the Estimator section of an attitude run with a smoother; two latency names for two
  quantities.
"""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import msgspec
import numpy as np
import pytest

from bench.bus.schemas import STAGES
from bench.report.timebase import RunClock
from bench.report.rundata import load_run
from bench.scenario import builtin_names, load_scenario
from tests.browser import CHROMIUM, colourful_fraction, images_loaded
from tests.conftest import run_bench_cli

RUN_TIMEOUT_S = 240
ATTITUDE_SHORT_S = 3.0          # real-time attitude runs: 3 s, the faults within it
LOCKSTEP_ATTITUDE_STEPS = 25
RENDEZVOUS_STEPS = 12
SECTIONS = {"rendezvous": ("Summary", "Trajectory", "Latency", "Deadlines", "Recording"),
            "attitude": ("Summary", "Attitude", "Latency", "Deadlines", "CAN bus", "Recording")}


def short_form(name: str, mode: str | None = None) -> dict:
    """The scenario cut short, its faults (if any) moved inside the short run; `mode` another time
    mode than the scenario's own."""
    data = msgspec.to_builtins(load_scenario(name))
    if mode is not None:
        data["run"]["mode"] = mode
    if data.get("kind") == "attitude":
        if data["run"]["mode"] == "real-time":
            data["attitude"]["duration_s"] = ATTITUDE_SHORT_S
            data["run"]["steps"] = None
        else:
            data["run"]["steps"] = LOCKSTEP_ATTITUDE_STEPS
    else:   # real time: 10 steps a second, 3 s for the faults
        data["run"]["steps"] = RENDEZVOUS_STEPS if data["run"]["mode"] == "lock-step" else 30
    faults = (data.get("can") or {}).get("faults") or []
    # Fault times are simulated seconds: in real time, the time factor's worth per wall second.
    scale = data["run"]["time_factor"] if data["run"]["mode"] == "real-time" else 1.0
    for i, fault in enumerate(faults):
        # one after the other from 0.5 s, 0.3 s or 5 frames each: all inside a 3 s run
        fault["start_s"] = (0.5 + 0.4 * i) * scale
        if fault.get("duration_s") is not None:
            fault["duration_s"] = 0.3 * scale
        if fault.get("count") is not None:
            fault["count"] = min(int(fault["count"]), 5)
    return data


def needs_kernel_can(name: str) -> bool:
    can = load_scenario(name).can
    return can is not None and can.transport == "socketcan"


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    directory = tmp_path_factory.mktemp("builtin-runs")
    yield directory
    shutil.rmtree(directory, ignore_errors=True)


def chain_breaks(trajectory: dict) -> list[str]:
    """Steps whose stamps (in loop order, absent ones skipped) go backwards."""
    columns = [np.asarray(trajectory[f"stamp_{s}_ns"], np.int64) for s in STAGES if f"stamp_{s}_ns" in trajectory]
    stamps = np.stack(columns, axis=1)
    broken = []
    for k, row in enumerate(stamps):
        present = [(stage, v) for stage, v in zip(STAGES, row) if v > 0]
        for (a, va), (b, vb) in zip(present, present[1:]):
            if vb < va:
                broken.append(f"step {k}: {b} {(vb - va) / 1e6:.2f} ms before {a}")
    return broken


_done: dict[str, object] = {}


def run_id_of(name: str) -> str:
    return name.replace("@", "_")    # "@" is Zenoh's verbatim-chunk mark: not in a run id


def short_run(runs, name: str):
    """`bench run` of the scenario's short form, once per test session; the finished process."""
    if name not in _done:   # "<scenario>@<mode>": the scenario in the other time mode
        scenario_file = runs / f"{run_id_of(name)}.json"
        base, _, mode = name.partition("@")
        scenario_file.write_text(json.dumps(short_form(base, mode or None)))
        _done[name] = run_bench_cli("run", str(scenario_file), "--run-id", run_id_of(name), "--runs-dir", str(runs), "--no-progress",
                                    timeout_s=RUN_TIMEOUT_S)
    return _done[name]


@pytest.mark.parametrize("name", builtin_names())
def test_a_short_run_of_every_builtin_scenario_reads_right(runs, name):
    if needs_kernel_can(name) and not Path("/sys/class/net/vcan0").exists():
        pytest.skip("needs the kernel's SocketCAN (vcan); its loop is run in user-mode Linux by tests/test_kernel_can_uml.py")
    result = short_run(runs, name)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "verdict: PASS" in result.stdout or "verdict: FAIL" in result.stdout
    run = load_run(runs / name)
    metrics = json.loads((runs / name / "metrics.json").read_text())

    # stamp chains forward, no negative latency
    assert chain_breaks(run.trajectory) == []
    for hop, figures in metrics["latency_ms"].items():
        if figures.get("n"):
            assert figures["p50_ms"] >= 0 and figures["mean_ms"] >= 0, (hop, figures)
    assert metrics["end_to_end_latency"]["samples"] > 0

    # fault windows inside the run, on simulated time, over the frames they affected
    clock = RunClock.from_run(run.trajectory, run.scenario)
    faults = metrics["can_bus"]["faults"] if metrics.get("can_bus") else []
    assert len(faults) == len(getattr(run.scenario.can, "faults", None) or [])
    if faults:
        model = json.loads((runs / name / "can" / "busmodel.json").read_text())
        frame_s = run.scenario.can.driver.command_period_s
        for window, affected in zip(faults, model["faults"]):
            start, end = window["start_sim_s"], window["end_sim_s"]
            assert clock.start_sim_s <= start <= end <= clock.end_sim_s, window
            assert math.isfinite(end)
            if affected["affected"] and affected["first_ns"] is not None:
                first, last = clock.sim_s(affected["first_ns"]), clock.sim_s(affected["last_ns"])
                assert start - frame_s <= first and last <= end + frame_s, (window, first, last)

    # every section of the loop's report there and not empty
    report = (runs / name / "report.md").read_text()
    kind = run.scenario.kind
    sections = {part.split("\n", 1)[0].strip(): part for part in report.split("\n## ")[1:]}
    for section in SECTIONS[kind]:
        if section == "CAN bus" and run.scenario.can is None:
            continue
        assert section in sections, f"no {section} section"
        assert "| ---" in sections[section] or "![" in sections[section], f"{section} is empty"
    assert metrics["deadlines"]["controller_cycles"] > 0
    assert "left out of every analysis" not in report

    # a verdict everywhere
    assert isinstance(metrics["verdict"]["passed"], bool) and metrics["verdict"]["criteria"]
    assert "Verdict: **PASS**" in report or "Verdict: **FAIL**" in report


@pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (tools/install-system-deps.sh)")
@pytest.mark.parametrize("name", ["attitude_fault_all", "attitude_pointing_rt", "rendezvous_card"])
def test_each_loops_report_renders_in_a_browser_with_no_empty_plot(runs, tmp_path, name):
    """The attitude loop with bus faults, with the smoother (its Estimator section), and the
    rendezvous card, as Chromium shows them: every figure loads, and no plot is empty (each holds
    coloured lines or fills)."""
    assert short_run(runs, name).returncode == 0
    page = runs / name / "report.html"
    n_figures = page.read_text().count("<img ")
    assert n_figures >= 5
    assert images_loaded(tmp_path, page) == (n_figures, n_figures)
    for plot in sorted((runs / name / "plots").glob("*.png")):
        assert colourful_fraction(plot) > 1e-4, f"{plot.name} is empty"    # a dozen points: 3.5e-4


# --- issue 46: one time base for CAN, decoded CAN in the MCAP, latencies named by what they measure
# Both modes of the fault run (the bus on simulated time in lock-step, on the wall clock in real
# time), and the two attitude runs with a smoother (real time, lock-step with MILQR).
TIME_BASE_RUNS = ["attitude_fault_all", "attitude_fault_all@lock-step", "attitude_pointing_rt", "attitude_slew_milqr"]


def _span_s(steps) -> tuple[float, float]:
    t = steps["t_s"].to_numpy()
    return float(t[0]), float(t[-1] + (t[-1] - t[-2]))


@pytest.mark.parametrize("name", TIME_BASE_RUNS)
def test_can_frames_telemetry_and_latencies_on_one_time_base(runs, name):
    import pandas as pd
    import pyarrow.parquet as pq
    from mcap.reader import make_reader

    from bench.report.attitude import board_telemetry_am2
    from bench.report.latency import END_TO_END, SENSE_TO_PLANT
    from bench.report.tables import METADATA_KEY

    result = short_run(runs, name)
    assert result.returncode == 0, result.stderr[-3000:]
    run_dir = runs / run_id_of(name)
    run = load_run(run_dir)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    steps = pd.read_parquet(run_dir / "steps.parquet")
    start, end = _span_s(steps)
    mode = run.scenario.run.mode
    assert ("@lock-step" in name) <= (mode == "lock-step")

    if run.scenario.can is not None:
        # can_frames.parquet: simulated time beside the wall clock, named, monotone, joins the steps
        table = pq.read_table(run_dir / "can_frames.parquet")
        meta = json.loads(table.schema.metadata[METADATA_KEY])
        assert {"sim_time_s", "wall_time_s", "timestamp_s", "step"} <= set(meta["time_columns"])
        frames = table.to_pandas()
        sim = frames["sim_time_s"].to_numpy()
        assert len(sim) > 20 and np.all(np.diff(sim) >= 0)
        assert start <= sim.min() and sim.max() <= end + 1e-9
        assert sim.max() - sim.min() > 0.5 * (end - start)        # spread over the run, not at one instant
        joined = frames[frames["in_run"]].merge(steps[["t_s"]], left_on="step", right_index=True)
        assert len(joined) == frames["in_run"].sum() > 0
        assert (joined["t_s"] <= joined["sim_time_s"] + 1e-9).all()
        # the board's telemetry trace of the report spans the run on simulated time, where the board
        # reports on it: a bus on simulated time (lock-step with faults), or real time. (A fault-free
        # lock-step bus keeps the wall clock: the board's periodic telemetry comes per wall second,
        # a handful over a run faster than real time.)
        sim_bus = json.loads((run_dir / "can" / "busmodel.json").read_text()).get("clock") == "simulated"
        telemetry = board_telemetry_am2(run)
        assert telemetry is not None
        if sim_bus or mode == "real-time":
            assert len(np.unique(np.round(telemetry[0], 3))) > 5, telemetry[0]
            assert telemetry[0].max() - telemetry[0].min() > 0.5 * (end - start), (telemetry[0].min(), telemetry[0].max())
        assert sim_bus == ("@lock-step" in name)
        # the MCAP: decoded CAN topics, on simulated time
        with open(run_dir / "recording.mcap", "rb") as f:
            can_messages = [(c.topic, m.log_time, json.loads(m.data)) for _, c, m in make_reader(f).iter_messages()
                            if c.topic in ("can/flight", "can/board")]
        assert {t for t, _, _ in can_messages} == {"can/flight", "can/board"}
        assert any(body["decoded"] and body["signals"] for _, _, body in can_messages)
        log_s = np.array([t for _, t, _ in can_messages]) / 1e9
        assert start <= log_s.min() and log_s.max() <= end + 1e-9
        assert log_s.max() - log_s.min() > 0.5 * (end - start)

    # an attitude run with a smoother: its Estimator section, with a plot that is not empty
    if run.scenario.kind == "attitude" and run.scenario.estimator.mode != "truth":
        report = (run_dir / "report.md").read_text()
        assert "\n## Estimator\n" in report
        section = report.split("\n## Estimator\n", 1)[1].split("\n## ", 1)[0]
        assert "±3σ" in section and "NEES" in section and "gyro bias" in section
        plot = run_dir / "plots" / "attitude_estimator.png"
        assert f"]({plot.relative_to(run_dir)})" in section
        assert plot.is_file() and colourful_fraction(plot) > 1e-3
        assert metrics["estimator_error"]["samples"] > 0 and metrics["estimator_error"]["mean_nees"] is not None

    # latency: two names for two quantities; the hold only in real time
    assert SENSE_TO_PLANT.name != END_TO_END.name
    assert metrics["latency_ms"][SENSE_TO_PLANT.name]["n"] > 0 and metrics["latency_ms"][END_TO_END.name]["n"] > 0
    assert metrics["end_to_end_latency"]["includes_step_hold"] == (mode == "real-time")
    assert metrics["sense_to_plant_latency"]["includes_step_hold"] is False
    assert metrics["sense_to_plant_latency"]["samples"] > 0
    if mode == "real-time":
        assert metrics["end_to_end_latency"]["p50_ms"] > metrics["sense_to_plant_latency"]["p50_ms"]
