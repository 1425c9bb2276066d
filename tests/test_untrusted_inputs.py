"""Reports and the recorder trust nothing they read: wrong types, floods, CAN frames, sequences
ahead of the plant and forged process reports are counted, never fatal, never unbounded."""
from __future__ import annotations

import json
import time

import can
import msgspec

from bench.bus import keys
from bench.bus.can import zenoh_wire
from bench.bus.schemas import DeadlineEvent, ProcessStats, StepDone, ThrustCommand, TruthState, encode, header
from bench.cli import main as bench_main
from bench.recorder import COUNTS_FILE, RECORDING_FILE, Recorder, Recording
from bench.recorder_intake import TOPIC_BYTE_BURST, TOPIC_BYTES_PER_S, TOTAL_BYTE_BURST, RecordingBudget, TokenBucket
from recording_helpers import node_context, session_pair
from test_report import N, RUN_ID, make_run

REC_RUN = "untrusted"


def wait_until(condition, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out waiting"
        time.sleep(0.01)


# --- report -------------------------------------------------------------------------------------
def add_to_recording(run_dir, *samples) -> None:
    """Rewrite the synthetic run's recording with extra (topic, payload) samples appended."""
    from bench.report.rundata import read_recording

    messages, _, _ = read_recording(run_dir / RECORDING_FILE)
    recording = Recording(run_dir / RECORDING_FILE, RUN_ID)
    for i, m in enumerate(messages):
        recording.write(m.topic, msgspec.json.encode(m.body), i + 1)
    for j, (topic, payload) in enumerate(samples):
        recording.write(topic, payload, len(messages) + j + 1)
    recording.close()


def test_a_valid_message_of_the_wrong_type_is_counted_not_fatal(tmp_path):
    run_dir = make_run(tmp_path / "run")
    wrong = encode(ThrustCommand(header(RUN_ID, 3, 0.0), [0.0] * 3, True, "x", 0.0))    # not a DeadlineEvent
    stats_on_deadline = encode(ProcessStats(header(RUN_ID, 0, 0.0), "controller", {}, {}))
    add_to_recording(run_dir, (keys.EVENT_DEADLINE, wrong), (keys.EVENT_DEADLINE, stats_on_deadline))
    assert bench_main(["report", str(run_dir)]) == 0
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["recording"]["wrong_type"] == {keys.EVENT_DEADLINE: 2}
    assert metrics["deadlines"]["controller_misses"] == 3          # the synthetic run's, unchanged


def test_messages_for_steps_the_plant_never_reached_are_counted(tmp_path):
    run_dir = make_run(tmp_path / "run")
    ahead = [(keys.TRUTH, encode(TruthState(header(RUN_ID, N + 10 + i, 0.0), [0.0] * 6, [0.0] * 3))) for i in range(3)]
    ahead.append((keys.EVENT_DEADLINE, encode(DeadlineEvent(header(RUN_ID, 10**6, 0.0), "plant", 0.0, 0.1, True, 1))))
    add_to_recording(run_dir, *ahead)
    assert bench_main(["report", str(run_dir)]) == 0
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["recording"]["ahead_of_plant"] == {keys.TRUTH: 3, keys.EVENT_DEADLINE: 1}
    assert "never reached" in (run_dir / "report.md").read_text()


def test_hostile_json_files_do_not_break_the_report(tmp_path):
    run_dir = make_run(tmp_path / "run")
    (run_dir / COUNTS_FILE).write_text('{"topics": {"truth": 5, "x": {"recorded": "many"}}}')
    (run_dir / "metrics.json").write_text("[1, 2")
    assert bench_main(["report", str(run_dir)]) == 0


# --- recorder -----------------------------------------------------------------------------------
def test_token_bucket_admits_burst_then_rate():
    bucket = TokenBucket(rate_per_s=10.0, burst=5.0)
    assert [bucket.take(1.0, 0.0) for _ in range(6)] == [True] * 5 + [False]
    assert bucket.take(1.0, 0.1) and not bucket.take(1.0, 0.1)        # 0.1 s refills one
    assert not bucket.take(6.0, 100.0)                                  # never more than the burst


def test_budget_reasons_and_topic_limit():
    budget = RecordingBudget(max_message_bytes=100, max_topics=2)
    assert budget.admit("a", 10, 0.0) is None
    assert budget.admit("a", 101, 0.0) == "message_too_large"
    assert budget.admit("b", 10, 0.0) is None
    assert budget.admit("c", 10, 0.0) == "too_many_topics"
    assert budget.dropped_counts() == {"a": {"message_too_large": 1}, "c": {"too_many_topics": 1}}


def test_a_flood_is_cut_to_the_budget_and_counted(tmp_path):
    chunk = b'{"type":"flood","pad":"' + b"x" * 100_000 + b'"}'
    n_flood = 400                            # 40 MB: over the 8 MB burst of one topic
    with session_pair() as (recorder_session, rogue_session):
        recorder = Recorder(node_context("recorder", REC_RUN, recorder_session, tmp_path))
        publisher = node_context("plant", REC_RUN, rogue_session, tmp_path)
        publisher.declare_ready([keys.TRUTH])
        started = time.monotonic()
        for k in range(20):
            publisher.publish(keys.TRUTH, TruthState(header(REC_RUN, k, 0.0), [0.0] * 6, [0.0] * 3))
        flood = publisher.declare_publisher("flood")       # blocking: Zenoh itself drops nothing
        for _ in range(n_flood):
            flood.put(chunk)
        flood.put(b"y" * 300_000)     # larger than any message may be
        wait_until(lambda: recorder.arrived == 20 + n_flood + 1)
        elapsed_s = time.monotonic() - started
        counts = recorder.finish()
    flood = counts["topics"]["flood"]
    kept = flood["recorded"] + flood["malformed"]
    assert flood["dropped"] > 0 and flood["dropped_by_reason"]["message_too_large"] == 1
    assert kept + flood["dropped"] == n_flood + 1
    assert kept * len(chunk) <= min(TOPIC_BYTE_BURST + TOPIC_BYTES_PER_S * elapsed_s, TOTAL_BYTE_BURST + 8e6 * elapsed_s)
    assert counts["topics"][keys.TRUTH]["recorded"] == 20     # the loop's own topics unaffected
    assert (tmp_path / RECORDING_FILE).stat().st_size < TOPIC_BYTE_BURST + TOPIC_BYTES_PER_S * elapsed_s + 1e6


def test_can_frames_are_recorded_not_malformed(tmp_path):
    frame = zenoh_wire.encode(can.Message(arbitration_id=0x210, data=bytes(8), is_extended_id=False),
                              timestamp_s=1.0, sender_id=7, sequence=1)
    with session_pair() as (recorder_session, other):
        recorder = Recorder(node_context("recorder", REC_RUN, recorder_session, tmp_path))
        time.sleep(0.2)
        for payload in (frame, frame, b"not a frame"):
            other.put(keys.key(REC_RUN, "can/flight"), payload)
        wait_until(lambda: recorder.arrived == 3)
        counts = recorder.finish()
    assert counts["topics"]["can/flight"] == {"recorded": 2, "malformed": 1, "published": None, "missing": None}


def _stats(process: str, n: int, key: bytes | None = None, run_id: str = REC_RUN) -> bytes:
    from bench.runtime.reports import sign

    message = ProcessStats(header(run_id, 0, 0.0), process, {keys.TRUTH: n}, {})
    return encode(sign(message, key) if key else message)


def test_only_stats_signed_by_the_process_itself_are_taken():
    """A process the launcher started: its stats only with its own key's signature, whenever they
    come; unsigned ones, ones signed with another process's key, a signed one of another run and a
    signed one altered on the way are forged; a replay of the genuine one is not taken again."""
    from bench.launcher import StatsCollector
    from bench.runtime.reports import new_report_key

    plant_key, controller_key = new_report_key(), new_report_key()
    genuine = _stats("plant", 288, plant_key)
    altered = genuine.replace(b'"truth":288', b'"truth":289')
    assert altered != genuine
    with session_pair() as (launcher_session, rogue):
        collector = StatsCollector(launcher_session, REC_RUN, {"plant", "controller"})
        collector.trust("plant", plant_key)
        collector.trust("controller", controller_key)
        key = keys.key(REC_RUN, "status/stats/plant")
        time.sleep(0.2)
        rogue.put(key, _stats("plant", 999))                           # unsigned
        rogue.put(key, _stats("plant", 998, controller_key))           # another process's key
        rogue.put(key, _stats("plant", 997, plant_key, run_id="other"))  # another run: not this run's
        rogue.put(key, altered)                                        # the mac of other contents
        rogue.put(key, _stats("intruder", 5, plant_key))               # not a process of the run
        wait_until(lambda: collector.forged.get("plant") == 3)
        assert collector.stats == {}
        rogue.put(key, genuine)                                        # the plant's own, at its shutdown
        rogue.put(key, genuine)                                        # replayed
        wait_until(lambda: collector.stats.get("plant", {}).get("replayed") == 1)
        collector.undeclare()
    collector.finish()
    assert collector.stats == {"plant": {"published": {keys.TRUTH: 288}, "malformed": {}, "replayed": 1, "forged": 3}}


def test_the_plants_step_reports_count_only_when_it_signed_them():
    from bench.launcher import StatsCollector
    from bench.runtime.reports import new_report_key, sign

    plant_key = new_report_key()
    with session_pair() as (launcher_session, _):
        collector = StatsCollector(launcher_session, REC_RUN, {"plant"})
        collector.trust("plant", plant_key)
        done = StepDone(header(REC_RUN, 19, 0.0), 20, True)
        assert collector.genuine_step(sign(done, plant_key))
        assert not collector.genuine_step(done)
        assert not collector.genuine_step(sign(done, new_report_key()))
        collector.undeclare()
    assert collector.forged == {"plant": 2}


def test_stats_of_a_remote_process_are_taken_in_the_shutdown_window_only():
    """A node on another host has no key of this launcher (access control decides who may publish
    its stats): its first stats in the shutdown window are taken, earlier ones kept aside."""
    from bench.launcher import StatsCollector

    with session_pair() as (launcher_session, rogue):
        collector = StatsCollector(launcher_session, REC_RUN, {"plant", "controller"}, remote={"controller"})
        key = keys.key(REC_RUN, "status/stats/controller")
        time.sleep(0.2)
        rogue.put(key, _stats("controller", 999))      # before the run ends: premature
        wait_until(lambda: collector.premature == 1)
        collector.accept()                             # the launcher starts stopping the nodes
        rogue.put(key, _stats("controller", 288))      # the controller's own, at its shutdown
        wait_until(lambda: "controller" in collector.stats)
        rogue.put(key, _stats("controller", 7))        # a second one after it
        wait_until(lambda: collector.stats["controller"].get("conflicting") == 1)
        collector.undeclare()
    collector.finish()
    assert collector.stats == {"controller": {"published": {keys.TRUTH: 288}, "malformed": {}, "conflicting": 1}}


# --- the attitude estimator process ---------------------------------------------------------------
def test_the_attitude_estimator_counts_and_drops_bad_sensor_messages_and_goes_on(tmp_path):
    """Garbage, wrong types, out-of-range numbers (JSON cannot carry NaN: 1e999 decodes as out of
    range), a non-unit star-tracker quaternion and a tick beyond the run, on each sensor topic: the
    estimator process counts them per topic and keeps estimating from the good samples."""
    import dataclasses
    import threading

    import msgspec as ms

    from bench.bus.schemas import AttitudeEstimate, GyroSample, MagnetometerSample, StarTrackerSample, decode
    from bench.estimator import attitude_node
    from bench.scenario import load_scenario

    run_id = "att-untrusted"
    scenario = load_scenario("attitude_pointing")
    scenario = ms.structs.replace(scenario, can=None, run=ms.structs.replace(scenario.run, mode="real-time", time_factor=1.0))
    gyro_body = b'{"type":"gyro","header":{"schema_version":1,"run_id":"%s","seq":%d,"sim_time_s":%s},"rate_radps":[%s,0,0]}'
    bad = [
        (keys.SENSE_GYRO, b"\xff not json"),
        (keys.SENSE_GYRO, gyro_body % (run_id.encode(), 0, b"0.0", b"1e999")),
        (keys.SENSE_MAG, encode(TruthState(header(run_id, 0, 0.0), [0.0] * 6, [0.0] * 3))),    # wrong type
        (keys.SENSE_STAR, encode(StarTrackerSample(header(run_id, 0, 0.0), [0.5, 0.0, 0.0, 0.0]))),
        (keys.SENSE_GYRO, encode(GyroSample(header(run_id, 10**6, 0.0), [0.0, 0.0, 0.0]))),
    ]
    with session_pair() as (estimator_session, plant_session):
        ctx = dataclasses.replace(node_context("estimator", run_id, estimator_session, tmp_path), scenario=scenario)
        estimates = []
        plant_session.declare_subscriber(keys.key(run_id, keys.ESTIMATE_ATTITUDE),
                                         lambda s: estimates.append(decode(s.payload.to_bytes(), AttitudeEstimate)))
        node = threading.Thread(target=attitude_node.run, args=(ctx,), daemon=True)
        node.start()
        probe = plant_session.declare_publisher(keys.key(run_id, keys.SENSE_GYRO))
        wait_until(lambda: probe.matching_status.matching)          # the estimator's sense/* subscriber
        for topic, payload in bad:
            plant_session.put(keys.key(run_id, topic), payload)
        wait_until(lambda: sum(ctx.malformed.values()) == len(bad))
        q = [1.0, 0.0, 0.0, 0.0]
        for k in range(3):
            t = 0.1 * k
            if k == 0:
                plant_session.put(keys.key(run_id, keys.SENSE_MAG), encode(MagnetometerSample(header(run_id, k, t), [2e-5, 0, 0], [2e-5, 0, 0])))
                plant_session.put(keys.key(run_id, keys.SENSE_STAR), encode(StarTrackerSample(header(run_id, k, t), q)))
            plant_session.put(keys.key(run_id, keys.SENSE_GYRO), encode(GyroSample(header(run_id, k, t), [0.0, 0.0, 0.0])))
        wait_until(lambda: len(estimates) == 3)
        ctx.stop.set()
        node.join(timeout=30)
        assert not node.is_alive()
    assert dict(ctx.malformed) == {keys.SENSE_GYRO: 3, keys.SENSE_MAG: 1, keys.SENSE_STAR: 1}
    assert [e.header.seq for e in estimates] == [0, 1, 2] and all(e.valid for e in estimates)
