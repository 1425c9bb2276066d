"""Reports from a synthetic run directory whose stamps, misses and errors are known exactly."""
from __future__ import annotations

import json

import msgspec
import numpy as np
import pytest

from bench.bus import keys
from bench.bus.schemas import (
    STAGES,
    DeadlineEvent,
    MtqApplied,
    ProcessStats,
    ThrustCommand,
    TranslationEstimate,
    TruthState,
    encode,
    header,
)
from bench.cli import main as bench_main
from bench.recorder import COUNTS_FILE, OFFSETS_FILE, RECORDING_FILE, Recording
from bench.report.build import write_report
from bench.report.compare import write_comparison
from bench.report.latency import END_TO_END, correct_clock_offsets, latency, percentiles_ms
from bench.report.rundata import load_run
from bench.scenario import load_scenario, parse_scenario

RUN_ID = "synthetic"
N = 40
BUDGET_S = 0.005
SLOW_CYCLES = {7, 19, 31}           # controller cycles of 60 ms: misses
TRANSPORT_LOST = {12}               # controller on time, command still not at the plant in time
rng = np.random.default_rng(3)

# Hop durations in ns per step (random but fixed by the seed).
HOP_NS = {
    "estimator_received": rng.integers(200_000, 3_000_000, N),
    "estimated": rng.integers(20_000, 100_000, N),
    "controller_received": rng.integers(100_000, 1_000_000, N),
    "commanded": np.where(np.isin(np.arange(N), list(SLOW_CYCLES)), 60_000_000, rng.integers(50_000, 2_000_000, N)),
    "plant_received": rng.integers(100_000, 5_000_000, N),
    "applied": rng.integers(5_000, 30_000, N),
}


def stamps_of(k: int) -> dict[str, int]:
    stamps = {"sensed": 10**12 + k * 100_000_000}
    previous = stamps["sensed"]
    for stage in STAGES[1:]:
        if stage in HOP_NS:
            previous += int(HOP_NS[stage][k])
            stamps[stage] = previous
    return stamps


def scenario_dict(estimator_mode: str = "smoother") -> dict:
    return {"name": "synthetic", "run": {"mode": "real-time", "steps": N},
            "estimator": {"mode": estimator_mode},
            "controller": {"deadline": {"budget_s": BUDGET_S, "fallback": "hold"}}}


def make_run(run_dir, estimator_mode: str = "smoother"):
    """A run directory as the launcher, the plant and the recorder would leave it."""
    run_dir.mkdir(parents=True)
    scenario = parse_scenario(scenario_dict(estimator_mode))
    (run_dir / "scenario.json").write_bytes(msgspec.json.encode(scenario))
    params = scenario.params()
    state = np.cumsum(rng.normal(0, 100, (N + 1, 6)), axis=0)
    thrust = rng.uniform(-0.5, 0.5, (N, 3))
    trajectory = {"t_s": np.arange(N + 1) * params.time_step_s, "state_m_mps": state, "thrust_n": thrust}
    plant_stamps = {stage: np.full(N, -1, dtype=np.int64) for stage in STAGES}
    recording = Recording(run_dir / RECORDING_FILE, RUN_ID)
    t_ns = 0
    for k in range(N):
        stamps = stamps_of(k)
        hdr = header(RUN_ID, k, k * params.time_step_s, sensed=stamps["sensed"])
        recording.write(keys.TRUTH, encode(TruthState(hdr, state[k].tolist(), [0.0] * 3)), t_ns := t_ns + 1)
        est_hdr = header(RUN_ID, k, k * params.time_step_s, **{s: stamps[s] for s in ("sensed", "estimator_received", "estimated")})
        error = np.array([3.0, -2.0, 1.0, 0.01, 0.02, -0.01]) * (1 + k % 3)
        recording.write(keys.ESTIMATE_TRANSLATION, encode(TranslationEstimate(
            est_hdr, (state[k] + error).tolist(), np.diag([100.0] * 3 + [0.01] * 3).ravel().tolist())), t_ns := t_ns + 1)
        cmd_hdr = header(RUN_ID, k, k * params.time_step_s, **{s: stamps[s] for s in STAGES[:5]})
        slow = k in SLOW_CYCLES
        recording.write(keys.COMMAND_THRUST, encode(ThrustCommand(
            cmd_hdr, thrust[k].tolist(), True, "solved", 0.001 * (1 + k % 4), 5, "hold" if slow else None)), t_ns := t_ns + 1)
        if slow:
            recording.write(keys.EVENT_DEADLINE, encode(DeadlineEvent(cmd_hdr, "controller", 0.06, BUDGET_S, True, 1, "hold")), t_ns := t_ns + 1)
        if not (slow or k in TRANSPORT_LOST):
            for stage, value in stamps.items():
                plant_stamps[stage][k] = value
    for counter in range(5):      # the board's chain: its own counter as seq, 0.4 ms decode to coils
        board_hdr = header(RUN_ID, counter, 0.0, board_received=5 * 10**12 + counter, applied=5 * 10**12 + counter + 400_000)
        recording.write(keys.ACTUATOR_MTQ, encode(MtqApplied(board_hdr, [0.1] * 3, [0.0] * 3, False)), t_ns := t_ns + 1)
    recording.write("status/stats/plant", encode(ProcessStats(header(RUN_ID, 0, 0.0), "plant", {keys.TRUTH: N}, {})), t_ns + 1)
    recording.write(keys.COMMAND_THRUST, b"garbage", t_ns + 2)
    recording.close()
    (run_dir / COUNTS_FILE).write_text(json.dumps(recording.counts()))
    (run_dir / OFFSETS_FILE).write_text(json.dumps({"recorder": {"host": "a", "offset_ns": 0, "uncertainty_ns": 10}}))
    trajectory.update({f"stamp_{s}_ns": v for s, v in plant_stamps.items()})
    np.savez(run_dir / "trajectory.npz", **trajectory)
    return run_dir


def expected_hop_ms(start: str, end: str, steps) -> np.ndarray:
    return np.array([(stamps_of(k)[end] - stamps_of(k)[start]) / 1e6 for k in steps])


def test_latency_per_hop_matches_the_stamps(tmp_path):
    run = load_run(make_run(tmp_path / "run"))
    result = latency(run)
    all_steps = range(N)
    applied_steps = [k for k in all_steps if k not in SLOW_CYCLES | TRANSPORT_LOST]
    expected = {
        "plant → estimator": expected_hop_ms("sensed", "estimator_received", all_steps),
        "controller compute": expected_hop_ms("controller_received", "commanded", all_steps),
        "controller → plant": expected_hop_ms("commanded", "plant_received", applied_steps),
        END_TO_END.name: expected_hop_ms("sensed", "applied", applied_steps),
    }
    for hop, values_ms in expected.items():
        got = result.summary[hop]
        assert got["n"] == len(values_ms)
        for p in (50, 90, 99):
            assert got[f"p{p}_ms"] == pytest.approx(np.percentile(values_ms, p), rel=1e-12)
        assert got["max_ms"] == pytest.approx(values_ms.max())
    assert "CAN → board" not in result.summary     # no CAN stamps, no CAN hop
    # The board's chain is its own: its stamps never leak into the loop's steps of the same seq.
    assert result.summary["board decode → coils set (CAN)"]["p50_ms"] == pytest.approx(0.4)


def test_clock_offsets_are_removed_only_for_other_hosts():
    stamps = {0: {"sensed": 1_000, "estimator_received": 5_000, "commanded": 9_000}}
    offsets = {"recorder": {"host": "a", "offset_ns": 0}, "plant": {"host": "a", "offset_ns": 400},
               "estimator": {"host": "b", "offset_ns": 3_000}}
    corrected = correct_clock_offsets(stamps, offsets)[0]
    assert corrected == {"sensed": 1_000, "estimator_received": 2_000, "commanded": 9_000}


def test_percentiles_of_nothing_say_so():
    assert percentiles_ms(np.array([])) == {"n": 0}


def test_report_files_tables_and_metrics(tmp_path):
    run_dir = make_run(tmp_path / "run")
    assert bench_main(["report", str(run_dir)]) == 0
    md = (run_dir / "report.md").read_text()
    page = (run_dir / "report.html").read_text()
    for name in ("trajectory", "latency_cdf", "latency_hist", "cycle_time", "solve_time", "estimator_error"):
        png = run_dir / "plots" / f"{name}.png"
        assert png.stat().st_size > 10_000, name
        assert f"plots/{name}.png" in md and f"plots/{name}.png" in page
    metrics = json.loads((run_dir / "metrics.json").read_text())
    deadlines = metrics["deadlines"]
    assert deadlines["controller_misses"] == len(SLOW_CYCLES)
    assert deadlines["fallbacks_applied"] == {"hold": len(SLOW_CYCLES)}
    assert deadlines["plant_missed_steps"] == len(SLOW_CYCLES | TRANSPORT_LOST)
    assert deadlines["plant_misses_controller_slow"] == len(SLOW_CYCLES)
    assert deadlines["plant_misses_transport_slow"] == len(TRANSPORT_LOST)
    assert deadlines["worst_cycle_time_s"] == pytest.approx(0.06)
    assert metrics["recording"] == {"recorded": 3 * N + len(SLOW_CYCLES) + 6, "malformed": 1, "missing": 0, "truncated": False,
                                    "dropped": 0, "wrong_type": {}, "ahead_of_plant": {}}
    assert metrics["estimator_error"]["fraction_within_3sigma"] == 1.0   # |error| <= 9 m, 3 sigma = 30 m
    assert metrics["estimator_error"]["rms_error"]["x"] == pytest.approx(np.sqrt(np.mean((3.0 * (1 + np.arange(N) % 3)) ** 2)))
    assert metrics["latency_ms"][END_TO_END.name]["n"] == N - len(SLOW_CYCLES | TRANSPORT_LOST)
    assert "final_position_error_m" in metrics and "| truth | 40 | 40 | 0 | 0 |" in md


def test_truth_estimator_has_no_estimator_section(tmp_path):
    run_dir = make_run(tmp_path / "run", estimator_mode="truth")
    write_report(run_dir)
    assert "## Estimator" not in (run_dir / "report.md").read_text()
    assert json.loads((run_dir / "metrics.json").read_text())["estimator_error"] is None


def test_compare_puts_runs_side_by_side(tmp_path):
    a, b = make_run(tmp_path / "a"), make_run(tmp_path / "b", estimator_mode="truth")
    md, page = write_comparison([a, b], tmp_path / "cmp")
    text = md.read_text()
    assert "| controller deadline misses | 3 | 3 |" in text
    assert "| estimator | smoother | truth |" in text
    for name in ("trajectories", "latency_cdf", "solve_time"):
        assert (tmp_path / "cmp" / "plots" / f"{name}.png").stat().st_size > 10_000


def test_compare_refuses_runs_of_different_loops_and_a_reference_not_compared(tmp_path, capsys):
    a = make_run(tmp_path / "a")
    attitude = tmp_path / "att"
    attitude.mkdir()
    (attitude / "scenario.json").write_bytes(msgspec.json.encode(load_scenario("attitude_quick")))
    assert bench_main(["compare", str(a), str(attitude), "--out", str(tmp_path / "cmp")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "different loops" in err[0] and "attitude" in err[0] and "rendezvous" in err[0]
    b = make_run(tmp_path / "b")
    assert bench_main(["compare", str(a), str(b), "--reference", str(tmp_path / "nope"), "--out", str(tmp_path / "c2")]) == 2
    assert "not a run directory" in capsys.readouterr().err


def test_report_of_a_directory_that_is_not_a_run_is_a_clear_error(tmp_path, capsys):
    assert bench_main(["report", str(tmp_path)]) == 2
    assert "not a run directory" in capsys.readouterr().err


def test_can_bus_load_and_fault_timeline_on_simulated_time(tmp_path):
    """100 frames 10 ms apart at 1 Mbit/s: each 100 ms window holds 10 frames' bits. The run is real
    time at 6000x (600 s steps every 100 ms, sensed at 1000 s + k * 0.1 s on the monotonic clock),
    so every time of the CAN section lands on simulated time: the injector armed at step 1, a fault
    0.2 s after that for 0.3 s is 1800-3600 s, a fault limited by a count ends at its last frame."""
    import can

    from bench.bus.can.bittiming import frame_bits

    run_dir = make_run(tmp_path / "run")
    data = parse_scenario({**scenario_dict(), "can": {"faults": [
        {"name": "drop", "start_s": 0.2, "duration_s": 0.3},
        {"name": "corrupt", "start_s": 0.5, "count": 2}]}})
    (run_dir / "scenario.json").write_bytes(msgspec.json.encode(data))
    frame = can.Message(arbitration_id=0x101, data=bytes(range(8)), is_extended_id=False)
    writer = can.Logger(str(run_dir / "can.log"))
    for i in range(100):
        writer.on_message_received(can.Message(timestamp=1000.0 + 0.01 * i + 0.001, arbitration_id=0x101,
                                               data=bytes(range(8)), is_extended_id=False, channel="bus"))
    writer.stop()
    (run_dir / "can").mkdir()
    armed_ns = 10**12 + 100_000_000
    (run_dir / "can" / "busmodel.json").write_text(json.dumps({
        "t0_ns": 10**12 - 3 * 10**9, "faults_t0_ns": armed_ns, "wall_offset_s": 0.0,
        "faults": [{"fault": "0:drop", "affected": 3, "first_ns": armed_ns + 210_000_000, "last_ns": armed_ns + 490_000_000},
                   {"fault": "1:corrupt", "affected": 2, "first_ns": armed_ns + 500_000_000,
                    "last_ns": armed_ns + 650_000_000}]}))
    (run_dir / "can" / "injections.jsonl").write_text("\n".join(
        json.dumps({"t_ns": armed_ns + t_ms * 1_000_000, "fault": "0:drop", "action": "dropped",
                    "frame_id": 0x101, "data": "00"}) for t_ms in (210, 250, 490)))
    write_report(run_dir)
    bus = json.loads((run_dir / "metrics.json").read_text())["can_bus"]
    assert bus["frames"] == 100
    assert bus["mean_load"] == pytest.approx(10 * frame_bits(frame) / (1e6 * 0.1))
    assert bus["peak_load"] == pytest.approx(bus["mean_load"])      # every window alike
    windows = [{k: f[k] for k in ("name", "start_sim_s", "end_sim_s", "live")} for f in bus["faults"]]
    assert windows == [{"name": "drop", "start_sim_s": pytest.approx(1800.0), "end_sim_s": pytest.approx(3600.0), "live": False},
                       {"name": "corrupt", "start_sim_s": pytest.approx(3600.0), "end_sim_s": pytest.approx(4500.0), "live": False}]
    assert [f["detected"] for f in bus["faults"]] == [False, False]     # no can/driver.json: nothing detected
    assert bus["injections"] == {"0:drop dropped": 3}
    assert (run_dir / "plots" / "bus_load.png").stat().st_size > 10_000
    report = (run_dir / "report.md").read_text()
    assert "## CAN bus" in report and "inf" not in report.split("## CAN bus")[1].split("##")[0]


def test_can_section_lists_bus_off_episodes_and_their_recoveries(tmp_path):
    """A bus-off and its recovery, from the bus model's own report to metrics.json, the report and
    the summary. On a bus model with a listener beside the two ends, the board (TEC 248,
    error-passive) loses one collision at 1000.5 s on the monotonic clock and goes bus-off when the
    winning frame ends; the bus then idle, it is back 128 x 11 = 1408 bit times later: 1.408 ms at
    1 Mbit/s. The run is real time at 6000x (as above), so 1000.5 s is simulated 3000 s and the
    1.408 ms off the bus are 8.448 simulated seconds."""
    import can

    from bench.bus.can import protocol as p
    from bench.bus.can.busmodel import BOARD, FLIGHT, BusModel
    from bench.bus.can.injector import FaultInjector
    from bench.report.summary import summary_rows

    run_dir = make_run(tmp_path / "run")
    writer = can.Logger(str(run_dir / "can.log"))
    for i in range(10):
        writer.on_message_received(can.Message(timestamp=1000.0 + 0.1 * i, arbitration_id=0x101, data=bytes(8),
                                               is_extended_id=False, channel="bus"))
    writer.stop()
    t_ns = 10**12 + 500_000_000
    bus = BusModel(FaultInjector([], p.Protocol()), p.Protocol(), 10**12, nodes=(FLIGHT, BOARD, "listener"))
    bus.counters[BOARD].tec = 248
    bus.submit(FLIGHT, can.Message(arbitration_id=0x555, data=b"\x00", is_extended_id=False), t_ns)
    bus.submit(BOARD, can.Message(arbitration_id=0x555, data=b"\x80", is_extended_id=False), t_ns)
    bus.run_until(t_ns + 10_000_000)
    model = bus.report()
    (run_dir / "can").mkdir()
    (run_dir / "can" / "busmodel.json").write_text(json.dumps({**model, "t0_ns": 10**12, "wall_offset_s": 0.0}))
    write_report(run_dir)

    bus_off = json.loads((run_dir / "metrics.json").read_text())["can_bus"]["bus_off"]
    assert bus_off["nodes"] == {"board": {"episodes": 1, "recovered": 1, "longest_ms": pytest.approx(1.408),
                                          "total_ms": pytest.approx(1.408)}}
    [episode] = bus_off["episodes"]
    assert episode["node"] == "board" and episode["off_ms"] == pytest.approx(1.408)
    assert 3000.0 < episode["bus_off_s"] < 3000.0 + 6000 * 100e-6          # the collision took < 100 us
    assert episode["recovered_s"] - episode["bus_off_s"] == pytest.approx(6000 * 1.408e-3)
    section = (run_dir / "report.md").read_text().split("## CAN bus")[1].split("\n## ")[0]
    assert "| bus-off board | 1 times, 1 recovered (each after 128 x 11 recessive bits" in section
    assert "longest 1.41 ms" in section
    assert f"| bus-off board at {episode['bus_off_s']:.7g} s (simulated) | recovered at" in section
    assert "(1.41 ms off the bus)" in section
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert ("CAN bus-off episodes (recovered)", "board 1 (1)") in summary_rows(metrics)


def test_a_recording_cut_short_is_read_up_to_its_last_whole_chunk(tmp_path):
    """A recorder killed before finishing its file: the report keeps what was written and says so."""
    run_dir = make_run(tmp_path / "run")
    path = run_dir / RECORDING_FILE
    recording = Recording(path, RUN_ID)
    for k in range(2000):      # ~0.5 MB: several chunks
        hdr = header(RUN_ID, k, 0.0, sensed=k)
        recording.write(keys.TRUTH, encode(TruthState(hdr, [float(k)] * 6, [0.0] * 3)), k + 1)
    recording.close()
    size = path.stat().st_size
    with open(path, "r+b") as f:
        f.truncate(size // 2)
    run = load_run(run_dir)
    assert run.recording_truncated
    seqs = [m.seq for m in run.messages]
    assert 0 < len(seqs) < 2000 and seqs == list(range(len(seqs)))
    write_report(run_dir)
    assert "ends early" in (run_dir / "report.md").read_text()


def test_latency_histograms_put_every_hop_in_its_row_with_its_percentiles(tmp_path, monkeypatch):
    """One row per hop in the given order (top first), each row's p50 and p99 marks at the hop's
    own percentiles, on a log axis that takes a latency of zero without failing."""
    import matplotlib.pyplot as plt
    from bench.report import plots

    rng = np.random.default_rng(5)
    hops = {"plant → estimator": rng.lognormal(np.log(3e-4), 0.3, 200),
            "controller compute": np.concatenate([[0.0], rng.lognormal(np.log(5e-5), 0.5, 99)]),
            "CAN → board": rng.lognormal(np.log(2e-3), 0.2, 50)}
    figures = []
    monkeypatch.setattr(plt, "close", figures.append)    # keep the figure to read it
    plots.latency_histograms(hops, tmp_path / "hist.png")
    assert (tmp_path / "hist.png").stat().st_size > 10_000
    (ax,) = figures[0].axes
    assert ax.get_xscale() == "log"
    labels = [t.get_text() for t in ax.get_yticklabels()]
    assert labels == ["CAN → board (n=50)", "controller compute (n=100)", "plant → estimator (n=200)"]
    marks = [line.get_xdata()[0] for line in ax.get_lines()]
    expected = [np.percentile(ms * 1e3, q) for ms in hops.values() for q in (50, 99)]
    np.testing.assert_allclose(marks, expected)


def test_the_summary_tells_the_fdir_detections_apart_from_the_drivers():
    from bench.report.summary import summary_rows

    metrics = {"scenario": {"kind": "attitude"}, "can_bus": {"driver": {
        "events": {"actuator_mismatch": 2, "fdir_reversed": 1, "fdir_pointing": 1, "host_overrun": 3},
        "board_ok_at_end": True}}}
    rows = dict(summary_rows(metrics))
    assert rows["faults the driver detected"] == "actuator_mismatch 2"
    assert rows["faults the FDIR detected (from the dynamics)"] == "fdir_pointing 1, fdir_reversed 1"
    assert rows["host overruns (flight side late, not a fault)"] == "3"
