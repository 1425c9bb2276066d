"""What the nodes keep per step, per frame or per event stays on disk, not in memory (issue 44).

Deterministic and bounded: the containers of bench/bus/spill.py give back exactly what went in;
the files written through them equal those written from lists; and the plant, the bus model and
the controller's deadline monitor hold no more memory (tracemalloc) after 3N steps, frames or
cycles than after N: with lists they held 240 kB to 3 MB more, now under 100 bytes.
The long real-time soak is benchmarks/bench_soak.py (docs/performance.md, "Long runs").
"""
from __future__ import annotations

import gc
import io
import json
import random
import tracemalloc
from collections import Counter

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from bench.bus.can import protocol as p
from bench.bus.can.busmodel import FLIGHT, BusModel, _percentiles_us
from bench.bus.can.injector import FaultInjector
from bench.bus.spill import (
    SpilledJson, SpilledRecords, SpilledRows, StepColumn, WindowCounter, write_json_with_list,
)
from bench.recorder import spill_chunk_indexes


def test_spilled_rows_give_back_every_row_in_order_across_blocks():
    rows = SpilledRows((3,), block_rows=4)
    expected = np.arange(30, dtype=float).reshape(10, 3) / 7
    for row in expected:
        rows.append(row)
    assert len(rows) == 10 and np.array_equal(rows.array(), expected)
    rows.append([1.0, 2.0, 3.0])               # appending goes on after a read
    assert np.array_equal(np.asarray(rows)[-1], [1.0, 2.0, 3.0]) and len(rows) == 11
    ints = SpilledRows((), np.int64, block_rows=3)
    values = [7, -2, 10**15, 3, 3, 0, 5]
    for v in values:
        ints.append(v)
    assert list(ints) == values and all(type(v) is int for v in ints)
    assert SpilledRows((4,)).array().shape == (0, 4)


def test_latency_percentiles_from_the_spill_equal_those_of_a_list():
    rng = random.Random(4)
    values = [rng.randrange(10**5, 10**7) for _ in range(3001)]
    spilled = SpilledRows((), np.int64, block_rows=128)
    for v in values:
        spilled.append(v)
    assert _percentiles_us(spilled) == _percentiles_us(values)
    assert _percentiles_us(SpilledRows((), np.int64)) == _percentiles_us([]) == {"n": 0}


def test_a_json_list_written_from_the_spill_equals_json_dumps():
    records = [{"counter": k % 16, "dipole_am2": [0.01 * k, -1e-3, 0.0], "applied_ns": 10**12 + k,
                "age_s": None if k % 3 else 0.004} for k in range(2500)]
    spilled = SpilledJson()
    for record in records:
        spilled.append(record)
    head = {"sent": {"MTQ_HEARTBEAT": 3}, "accepted": 2500, "realtime_priority": 0}
    for items in (spilled, records, []):
        path = _tmp_json()
        write_json_with_list(path, head, "applied", items)
        assert path.read_text() == json.dumps({**head, "applied": list(items)})
    assert list(spilled) == records


def _tmp_json():
    import tempfile
    from pathlib import Path
    return Path(tempfile.mkdtemp()) / "board.json"


def test_window_counter_equals_a_counter_with_windows_touched_late():
    counter, windows = Counter(), WindowCounter(keep=2)
    rng = random.Random(2)
    t = 0
    for _ in range(5000):
        t += rng.choice((0, 0, 1, 2))
        window = max(0, t - rng.choice((0, 0, 0, 1, 7)))    # now and then one long closed
        windows[window] += 13
        counter[window] += 13
    assert windows.items() == sorted(counter.items())
    assert max(windows.values()) == max(counter.values())


def test_a_step_column_equals_a_preallocated_array_with_late_and_repeated_writes():
    rng = random.Random(5)
    for n, shape, dtype, fill in [(4000, (3,), np.float64, np.nan), (4000, (), np.int64, -1), (3000, (), bool, False),
                                  (7, (3,), np.float64, np.nan), (0, (), np.int64, -1)]:
        expected = np.full((n, *shape), fill, dtype=dtype)
        column = StepColumn(n, shape, dtype, fill, window=64)
        for k in range(n):
            # this step's row, and now and then a recent one (a chain closed late) or a long-gone one
            for j in (k, max(0, k - rng.choice((0, 1, 2, 5, 100, 3000)))):
                if rng.random() < 0.7:
                    value = rng.random() if dtype is np.float64 else rng.randrange(100) if dtype is np.int64 \
                        else rng.random() < 0.5
                    column[j] = value
                    expected[j] = value
            m = rng.randrange(n)
            assert np.array_equal(np.asarray(column[m]), expected[m], equal_nan=dtype is np.float64)
        assert np.asarray(column).dtype == expected.dtype
        assert np.array_equal(np.asarray(column), expected, equal_nan=dtype is np.float64)
        assert np.array_equal(column[:n // 2], expected[:n // 2], equal_nan=dtype is np.float64)
    with pytest.raises(IndexError):
        StepColumn(3, (), np.int64, -1)[3] = 1


def _write_mcap(spill: bool) -> bytes:
    buffer = io.BytesIO()
    writer = Writer(buffer, chunk_size=512)
    if spill:
        spill_chunk_indexes(writer, None)
        assert isinstance(writer._Writer__chunk_indices, SpilledRecords)   # mcap's private list: still there
    writer.start(profile="", library="test")
    schema = writer.register_schema("s", "jsonschema", b"{}")
    channels = [writer.register_channel(f"topic/{i}", "json", schema) for i in range(3)]
    for k in range(2000):
        writer.add_message(channels[k % 3], log_time=k * 1000, publish_time=k, sequence=k,
                           data=json.dumps({"k": k}).encode())
    writer.finish()
    return buffer.getvalue()


def test_a_recording_with_its_chunk_indexes_spilled_is_the_same_file():
    spilled, plain = _write_mcap(True), _write_mcap(False)
    assert spilled == plain
    summary = make_reader(io.BytesIO(spilled)).get_summary()
    assert len(summary.chunk_indexes) > 100
    assert sum(1 for _ in make_reader(io.BytesIO(spilled)).iter_messages()) == 2000


# --- retained memory: N against 3N ------------------------------------------------------------
RETAINED_LIMIT_BYTES = 32 * 1024     # measured: < 100 B; with per-step lists 240 kB to 3 MB


@pytest.fixture
def traced():
    """Python's allocated bytes now (after a collection), tracemalloc running for the test."""
    tracemalloc.start()
    try:
        yield lambda: (gc.collect(), tracemalloc.get_traced_memory()[0])[1]
    finally:
        tracemalloc.stop()


def test_the_attitude_plant_holds_no_more_memory_after_more_steps(traced):
    from bench.plant.attitude_plant import AttitudePlant
    from bench.scenario import load_scenario

    scenario = load_scenario("attitude_pointing_rt")
    n = 1500
    plant = AttitudePlant(scenario.attitude, 4 * n, seed=1)
    dipole = np.array([1e-3, -2e-3, 0.5e-3])
    counts = []
    for phase in (n, 2 * n):
        for _ in range(phase):
            plant.sense()
            plant.apply(dipole)
        counts.append(traced())
    # a list per logged quantity held ~1 kB per step: 3 MB more over these 3000 steps
    assert counts[1] - counts[0] < RETAINED_LIMIT_BYTES, counts
    assert plant.trajectory()["att_q_wxyz"].shape == (3 * n, 4)


def test_the_bus_model_holds_no_more_memory_after_more_frames(traced):
    protocol = p.Protocol()
    bus = BusModel(FaultInjector([], protocol, seed=1), protocol, 10**12)
    t = 10**12
    counts = []
    for phase in (3000, 6000):
        for k in range(phase):
            t += 10_000_000
            # distinct payloads: the bit-timing caches fill (bounded) and then stay full
            bus.submit(FLIGHT, protocol.command([1e-3 * (k % 97), 0.0, -1e-3], counter=k % 16), t)
            bus.run_until(t + 1_000_000)
        counts.append(traced())
    assert counts[1] - counts[0] < RETAINED_LIMIT_BYTES, counts
    report = bus.report()
    assert report["command_latency_us"]["without_flood"]["n"] == 9000
    assert len(report["load_timeline_pct"]) > 800


def test_the_deadline_monitor_holds_no_more_memory_after_more_cycles(traced):
    from bench.config.controller import DeadlineConfig
    from bench.controller.deadline import DeadlineMonitor

    monitor = DeadlineMonitor(DeadlineConfig(budget_s=1.0), n_inputs=3)
    law = lambda x: (np.zeros(3), {"ctrl_feas": True, "status": "solved", "solve_time": 0.0, "iterations": 1})
    counts = []
    for phase in (3000, 6000):
        for _ in range(phase):
            monitor.run_cycle(np.zeros(6), law)
        counts.append(traced())
    assert counts[1] - counts[0] < RETAINED_LIMIT_BYTES, counts
    assert monitor.summary()["cycles"] == 9000


def test_the_attitude_plant_per_step_logs_do_not_take_memory_for_the_whole_run_up_front(traced):
    from bench.plant.board_dipole import AppliedLog
    from bench.plant.mtq_chain import CommandChains

    before = traced()
    logs = AppliedLog(10**6), CommandChains(10**6, 0.16)    # a day at 10 Hz is 864 000 steps
    # preallocated, these were ~190 MB (17 columns of a million rows); now 1024 recent rows each
    assert traced() - before < 2 * 1024 * 1024
    assert len(logs[0].commanded) == 10**6
