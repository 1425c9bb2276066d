"""Live fault injection's entry point in canbus (bench/bus/can/live_faults.py), on its own: a request is
taken only signed under the run's key, fresh, in a run that allows it, and as a scripted fault would
be (same schema); what is refused is counted by reason. Also the criteria as they stand
(bench/live/criteria.py) and the fault detections of metrics.json (bench/report/canbus.py).
No processes here: tests/test_live.py runs the whole bench."""
from __future__ import annotations

import json
import logging
import threading
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

import msgspec
import pytest

from bench.bus import data_auth, keys
from bench.bus import fault_command as fc
from bench.bus.can import protocol as p
from bench.bus.can.injector import FaultInjector, Flood, HardwareFault
from bench.bus.can.live_faults import LiveFaults, live_fault_specs
from bench.bus.can.faults import FaultSpec

RUN = "live-unit"
KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))


class Session:
    """What LiveFaults asks of a Zenoh session (no Zenoh here)."""

    def declare_queryable(self, key_expr, handler):
        return SimpleNamespace(undeclare=lambda: None)


def make_ctx(tmp_path: Path, key: bytes | None = KEY):
    published = []
    ctx = SimpleNamespace(name="canbus", run_id=RUN, data_key=key, session=Session(), stop=threading.Event(),
                          unauthentic={}, log=logging.getLogger("test"), published=published)
    ctx.declare_publisher = lambda topic: None
    ctx.publish = lambda topic, message: published.append((topic, message))
    return ctx


def armed_injector(scripted=()) -> FaultInjector:
    injector = FaultInjector(list(scripted), p.Protocol(0x10, "e2e"), seed=3, wall_s_per_sim_s=0.5)
    injector.arm(10_000_000_000)
    return injector


def signed(request: fc.FaultRequest, key: bytes = KEY, sender: str = "inject", counter: int = 1000) -> tuple[bytes, bytes]:
    payload = msgspec.json.encode(request)
    return payload, data_auth.tag(key, fc.key_expr(RUN), payload, sender.encode(), counter)


@pytest.fixture
def live(tmp_path):
    injector = armed_injector([FaultSpec(name="drop", start_s=1.0, count=3)])
    now = [12_000_000_000]        # 2 s of the bus's clock after arming: 4 simulated s at 0.5 wall s per simulated s
    view = LiveFaults(make_ctx(tmp_path), lambda: injector, lambda: now[0], True, tmp_path)
    yield view, injector, now
    view.ctx.stop.set()


def test_a_signed_request_becomes_the_next_fault_as_a_scripted_one_with_its_window_on_simulated_time(live, tmp_path):
    view, injector, _ = live
    reply = view.handle(*signed(fc.new_request(RUN, "corrupt", duration_s=2.0, after_s=0.5, params={"bits": 2})))
    assert reply.accepted and reply.label == "1:corrupt"
    assert reply.start_sim_s == pytest.approx(4.5) and reply.end_sim_s == pytest.approx(6.5)
    fault = injector.faults[1]
    assert fault.label == "1:corrupt" and fault in injector.frame_faults and fault.label in injector.live_labels
    # Its window on the injector's clock, as a scripted fault with start_s 4.5 would have it.
    assert (fault.start_ns, fault.end_ns) == FaultSpec(name="corrupt", start_s=4.5, duration_s=2.0).window_ns(
        10_000_000_000, 0.5)
    summary = injector.summary()
    assert [s["live"] for s in summary] == [False, True]
    record = json.loads((tmp_path / "live_faults.json").read_text())
    assert record["accepted"][0]["label"] == "1:corrupt" and record["accepted"][0]["requested_by"] == "inject"
    assert live_fault_specs(tmp_path.parent / "x") == []
    (tmp_path / "can").mkdir()
    (tmp_path / "can" / "live_faults.json").write_text(json.dumps(record))
    assert live_fault_specs(tmp_path) == [FaultSpec(name="corrupt", start_s=4.5, duration_s=2.0, params={"bits": 2})]
    topic, window = view.ctx.published[-1]
    assert topic == keys.EVENT_FAULT and window.live and window.label == "1:corrupt" and window.requested_by == "inject"


def test_window_and_hardware_kinds_join_their_lists(live):
    view, injector, _ = live
    assert view.handle(*signed(fc.new_request(RUN, "flood", duration_s=1.0), counter=1)).accepted
    assert view.handle(*signed(fc.new_request(RUN, "coil_reversed", duration_s=1.0, params={"axis": 2}),
                              counter=2)).accepted
    assert isinstance(injector.faults[1], Flood) and injector.faults[1] in injector.floods
    assert isinstance(injector.faults[2], HardwareFault)
    assert [(i, s.name) for i, s in injector.hardware.faults] == [(2, "coil_reversed")]
    assert len(injector.hardware.windows) == 1 and injector.hardware.axis_faults(12.1)[2][0] == "coil_reversed"   # 10 s + 4 simulated s x 0.5


@pytest.mark.parametrize("make, reason", [
    (lambda r: (msgspec.json.encode(r), None), fc.FORGED),                               # no tag: no key
    (lambda r: signed(r, key=OTHER_KEY), fc.FORGED),                                     # another key
    (lambda r: (msgspec.json.encode(r) + b" ", signed(r)[1]), fc.FORGED),                # altered after signing
])
def test_a_request_without_a_valid_tag_is_refused_and_counted(live, make, reason):
    view, injector, _ = live
    reply = view.handle(*make(fc.new_request(RUN, "drop", duration_s=1.0)))
    assert not reply.accepted and reply.reason == reason
    assert len(injector.faults) == 1
    assert view.refused == {reason: 1} and view.ctx.unauthentic[reason][keys.CONTROL_FAULT] == 1


def test_a_replayed_request_is_refused_and_counted(live):
    view, injector, _ = live
    payload, tag = signed(fc.new_request(RUN, "drop", duration_s=1.0))
    assert view.handle(payload, tag).accepted
    again = view.handle(payload, tag)
    assert not again.accepted and again.reason == fc.REPLAYED
    assert len(injector.faults) == 2 and view.refused == {fc.REPLAYED: 1}


def test_a_run_without_allow_live_faults_refuses_every_request(tmp_path):
    injector = armed_injector()
    view = LiveFaults(make_ctx(tmp_path), lambda: injector, lambda: 12_000_000_000, False, tmp_path)
    for i, kind in enumerate(("drop", "board_power_loss", "coil_open")):
        reply = view.handle(*signed(fc.new_request(RUN, kind, duration_s=1.0), counter=i + 1))
        assert not reply.accepted and reply.reason == fc.NOT_ALLOWED
    assert injector.faults == [] and view.refused == {fc.NOT_ALLOWED: 3}
    view.ctx.stop.set()


@pytest.mark.parametrize("fields, problem", [
    ({"kind": "nope"}, "unknown fault 'nope'"),
    ({"kind": "flood"}, "give duration_s"),                           # the scenario loader's own checks
    ({"kind": "coil_gain", "duration_s": 1.0, "params": {"gain": 2.0}}, "out of range"),
    ({"kind": "drop", "duration_s": -1.0}, "duration_s"),
    ({"kind": "board_death", "duration_s": 1.0}, "use 'board_power_loss'"),
])
def test_a_fault_scripted_faults_could_not_have_is_refused_naming_the_problem(live, fields, problem):
    view, injector, _ = live
    reply = view.handle(*signed(fc.new_request(RUN, **fields)))
    assert not reply.accepted and reply.reason == fc.INVALID and problem in reply.detail
    assert len(injector.faults) == 1


def test_before_the_first_command_frame_a_request_is_refused(tmp_path):
    injector = FaultInjector([], p.Protocol(0x10, "e2e"))
    view = LiveFaults(make_ctx(tmp_path), lambda: injector, lambda: 1, True, tmp_path)
    reply = view.handle(*signed(fc.new_request(RUN, "drop", duration_s=1.0)))
    assert not reply.accepted and reply.reason == fc.NOT_ARMED
    view.ctx.stop.set()


def test_scripted_faults_are_announced_on_event_fault_once_armed(tmp_path):
    injector = FaultInjector([FaultSpec(name="drop", start_s=1.0, duration_s=2.0)], p.Protocol(0x10, "e2e"))
    view = LiveFaults(make_ctx(tmp_path), lambda: injector, lambda: 1, True, tmp_path)
    injector.arm(5)
    view._announcer.join(timeout=5.0)
    (topic, window), = view.ctx.published
    assert topic == keys.EVENT_FAULT and not window.live and window.label == "0:drop" and window.end_sim_s == 3.0
    assert window.header.sim_time_s == 1.0


# --- the criteria as they stand -----------------------------------------------------------------
def test_live_criteria_judge_what_the_messages_give_and_leave_the_rest_to_the_end():
    from bench.live.criteria import AT_END, FAILS, HOLDS, LiveMetrics
    from bench.scenario import load_scenario

    scenario = load_scenario("attitude_fault_commands")     # final_rate_dps, two event counts, board_ok_at_end
    live = LiveMetrics(scenario)
    live.on_attitude_truth(0.1, [1.0, 0.0, 0.0, 0.0], [0.1, 0.0, 0.0])       # 5.7 deg/s
    states = {c["metric"]: c["state"] for c in live.judged()}
    assert states == {"final_rate_dps": FAILS, "can_bus.driver.events.board_command_timeout": FAILS,
                      "can_bus.driver.events.command_rejected": FAILS, "can_bus.driver.board_ok_at_end": AT_END}
    live.on_attitude_truth(0.2, [1.0, 0.0, 0.0, 0.0], [0.05, 0.0, 0.0])      # 2.9 deg/s
    live.on_bus_event("board_command_timeout", 0.11)
    judged = {c["metric"]: c for c in live.judged()}
    assert judged["final_rate_dps"]["state"] == HOLDS and judged["final_rate_dps"]["value"] == pytest.approx(2.8648, 1e-3)
    assert judged["can_bus.driver.events.board_command_timeout"]["state"] == HOLDS
    assert judged["can_bus.driver.events.command_rejected"]["state"] == FAILS
    assert judged["can_bus.driver.board_ok_at_end"]["value"] is None


def test_live_pointing_error_is_the_reports():
    import numpy as np

    from bench.live.criteria import LiveMetrics
    from bench.report.attitude_metrics import pointing_error_deg
    from bench.scenario import load_scenario

    scenario = load_scenario("attitude_pointing_rt")
    q = np.array([0.999657325, 0.0178988407, -0.0119325605, 0.0149157006])
    live = LiveMetrics(scenario)
    live.on_attitude_truth(1.0, q, [0.0, 0.0, 0.0])
    expected = pointing_error_deg({"att_time_s": [1.0], "att_q_wxyz": [q]}, scenario)[0]
    assert live.metrics["max_pointing_error_deg"] == pytest.approx(expected, abs=1e-12)
    (criterion,) = [c for c in live.judged() if c["metric"] == "max_pointing_error_deg"]
    assert criterion["state"] == "holds now"


# --- metrics.json: what detected each fault -----------------------------------------------------
def test_each_fault_gets_the_first_alarm_after_its_start_and_before_the_next(tmp_path):
    from bench.report.canbus import fault_detections

    events = [{"kind": "host_overrun", "detected_ns": 1_500_000_000, "latency_s": 0.0},        # not an alarm
              {"kind": "command_rejected", "detected_ns": 2_200_000_000, "latency_s": 0.01},
              {"kind": "heartbeat_timeout", "detected_ns": 5_300_000_000, "latency_s": 0.2},
              {"kind": "fdir_reversed", "detected_ns": 5_900_000_000, "latency_s": 1.0}]
    (tmp_path / "can").mkdir()
    (tmp_path / "can" / "driver.json").write_text(json.dumps({"events": events, "health": {"ok": True}}))
    clock = SimpleNamespace(sim_s=lambda ns: ns / 1e9)          # monotonic ns = simulated ns, for the test
    found = fault_detections(tmp_path, [("drop", 1.0, 3.0), ("board_power_loss (live)", 5.0, 6.0), ("coil_open", 7.0, 8.0)],
                             clock)
    assert [(f["first_detection"], f["detected_by"]) for f in found] == [
        ("command_rejected", "board"), ("heartbeat_timeout", "driver"), (None, None)]
    assert found[0]["detection_latency_s"] == pytest.approx(1.2) and found[1]["detection_latency_s"] == pytest.approx(0.3)
    assert not found[2]["detected"]
