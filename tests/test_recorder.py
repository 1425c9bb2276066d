"""The recorder node: every sample in the MCAP file, malformed ones raw, counts against publishers."""
from __future__ import annotations

import json
import threading
import time

from mcap.reader import make_reader

from bench.bus import keys
from bench.bus.presence import PresenceResponder
from bench.bus.schemas import RelativePosition, StepDone, ThrustCommand, TruthState, encode, header
from bench.recorder import COUNTS_FILE, OFFSETS_FILE, RECORDING_FILE, Recorder, run
from recording_helpers import node_context, session_pair

RUN_ID = "rec-test"
N_STEPS = 20


def wait_until(condition, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out waiting"
        time.sleep(0.01)


def publish_loop_samples(ctx) -> int:
    """What a plant and a controller would publish for N_STEPS steps; returns samples sent."""
    for k in range(N_STEPS):
        hdr = header(RUN_ID, k, 600.0 * k, sensed=1000 + k)
        ctx.publish(keys.TRUTH, TruthState(hdr, [float(k)] * 6, [0.0] * 3))
        ctx.publish(keys.SENSE_RELPOS, RelativePosition(hdr, [1.0, 2.0, 3.0], 10.0))
        ctx.publish(keys.COMMAND_THRUST, ThrustCommand(hdr.stamped("commanded", 2000 + k), [0.1] * 3, True, "solved", 1e-4))
    return 3 * N_STEPS


MALFORMED = {
    keys.COMMAND_THRUST: [b"\x00\x01not json", b'{"type": "thrust", "header": 3}'],
    keys.TRUTH: [encode(TruthState(header("another-run", 0, 0.0), [0.0] * 6, [0.0] * 3))],
    "unknown/topic": [b'{"type": "martian"}'],
}


def read_back(path):
    with open(path, "rb") as f:
        return [(s, c, m) for s, c, m in make_reader(f).iter_messages()]


def test_every_sample_is_recorded_with_json_schemas_and_malformed_raw(tmp_path):
    with session_pair() as (recorder_session, publisher_session):
        recorder = Recorder(node_context("recorder", RUN_ID, recorder_session, tmp_path))
        publisher = node_context("plant", RUN_ID, publisher_session, tmp_path)
        publisher.declare_ready([keys.TRUTH, keys.SENSE_RELPOS, keys.COMMAND_THRUST])
        sent = publish_loop_samples(publisher)
        for topic, payloads in MALFORMED.items():
            for payload in payloads:
                publisher_session.put(keys.key(RUN_ID, topic), payload)
        publisher.publish_stats()
        n_malformed = sum(len(p) for p in MALFORMED.values())
        wait_until(lambda: recorder.arrived == sent + n_malformed + 1)
        recorder.drain(0.0)
        counts = recorder.finish()

    messages = read_back(tmp_path / RECORDING_FILE)
    assert len(messages) == sent + n_malformed + 1
    by_topic: dict[str, list] = {}
    for schema, channel, message in messages:
        by_topic.setdefault(channel.topic, []).append((schema, channel, message))
    for topic, kind in [(keys.TRUTH, "TruthState"), (keys.SENSE_RELPOS, "RelativePosition"), (keys.COMMAND_THRUST, "ThrustCommand")]:
        rows = by_topic[topic]
        assert len(rows) == N_STEPS
        schema, channel, _ = rows[0]
        assert schema.name == kind and schema.encoding == "jsonschema" and channel.message_encoding == "json"
        assert {"type", "header"} <= set(json.loads(schema.data)["properties"])
        assert [json.loads(m.data)["header"]["seq"] for _, _, m in rows] == list(range(N_STEPS))
    # Malformed payloads are kept byte for byte, on their own raw channel.
    for topic, payloads in MALFORMED.items():
        rows = by_topic[f"malformed/{topic}"]
        assert [m.data for _, _, m in rows] == payloads
        assert rows[0][0] is None and rows[0][1].message_encoding == "application/octet-stream"

    topics = counts["topics"]
    for topic in (keys.TRUTH, keys.SENSE_RELPOS, keys.COMMAND_THRUST):
        assert topics[topic]["published"] == N_STEPS
    assert topics[keys.TRUTH] == {"recorded": N_STEPS, "malformed": 1, "published": N_STEPS, "missing": 0}
    assert topics[keys.COMMAND_THRUST]["malformed"] == 2
    assert topics["unknown/topic"] == {"recorded": 0, "malformed": 1, "published": None, "missing": None}
    assert counts["publishers"]["plant"] == {keys.TRUTH: N_STEPS, keys.SENSE_RELPOS: N_STEPS, keys.COMMAND_THRUST: N_STEPS}
    assert json.loads((tmp_path / COUNTS_FILE).read_text()) == counts


def test_recorder_reports_a_sample_the_publisher_sent_but_it_never_saw(tmp_path):
    """A publisher whose stats claim more than arrived shows up as missing, not silently equal."""
    with session_pair() as (recorder_session, publisher_session):
        recorder = Recorder(node_context("recorder", RUN_ID, recorder_session, tmp_path))
        publisher = node_context("plant", RUN_ID, publisher_session, tmp_path)
        publisher.declare_ready([keys.TRUTH])
        publish_loop_samples(publisher)
        publisher.published[keys.TRUTH] += 2     # as if two samples had been lost on the way
        publisher.publish_stats()
        wait_until(lambda: recorder.arrived == 3 * N_STEPS + 1)
        counts = recorder.finish()
    assert counts["topics"][keys.TRUTH]["missing"] == 2
    assert counts["topics"][keys.SENSE_RELPOS]["missing"] == 0


def test_recorder_node_declares_ready_measures_clock_offsets_and_stops(tmp_path):
    with session_pair() as (recorder_session, other_session):
        ctx = node_context("recorder", RUN_ID, recorder_session, tmp_path)
        responder = PresenceResponder(other_session, RUN_ID, "plant", None)
        node = threading.Thread(target=lambda: setattr(ctx, "exit_code", run(ctx)))
        node.start()
        watcher = node_context("launcher", RUN_ID, other_session, tmp_path)
        watcher.wait_for_ready(["recorder"], timeout_s=10.0)
        ctx.stop.set()
        node.join(timeout=15.0)
        responder.undeclare()
    assert not node.is_alive() and ctx.exit_code == 0
    offsets = json.loads((tmp_path / OFFSETS_FILE).read_text())
    plant = offsets["plant"]
    # Same host, same monotonic clock: the true offset is 0, inside the stated uncertainty.
    assert abs(plant["offset_ns"]) <= plant["uncertainty_ns"]
    assert read_back(tmp_path / RECORDING_FILE) == []
    assert json.loads((tmp_path / COUNTS_FILE).read_text())["topics"] == {}


# --- time base, CAN frames, metadata (issue 22) --------------------------------------------------
def test_log_time_is_simulated_time_and_publish_time_the_arrival(tmp_path):
    """Header messages at their sim_time_s; what has none (CAN frame, stats, board report,
    malformed, a forged non-finite time) at the newest step seen; publish time = receive time."""
    import math

    from bench.bus.can import protocol as p
    from bench.bus.can import zenoh_wire
    from bench.bus.schemas import MtqApplied, ProcessStats
    from bench.recorder import Recording

    recording = Recording(tmp_path / RECORDING_FILE, RUN_ID)
    frame = p.Protocol().command([0.25, -0.5, 0.0], counter=3)
    wire = zenoh_wire.encode(frame, timestamp_s=12.5, sender_id=7, sequence=41)
    samples = [
        (keys.TRUTH, encode(TruthState(header(RUN_ID, 0, 0.0), [0.0] * 6, [0.0] * 3))),
        (keys.TRUTH, encode(TruthState(header(RUN_ID, 1, 600.0), [1.0] * 6, [0.0] * 3))),
        ("can/flight", wire),
        (keys.ACTUATOR_MTQ, encode(MtqApplied(header(RUN_ID, 9, 0.0), [0.0] * 3, [0.0] * 3, False))),
        (keys.TRUTH, encode(TruthState(header(RUN_ID, 2, math.nan), [2.0] * 6, [0.0] * 3))),
        (keys.TRUTH, encode(TruthState(header(RUN_ID, 3, -5.0), [3.0] * 6, [0.0] * 3))),
        ("can/flight", b"not a frame"),
        (keys.STATUS_STEP, encode(StepDone(header(RUN_ID, 1, 1200.0), 2))),
        (keys.STATUS_STATS + "/plant", encode(ProcessStats(header(RUN_ID, 0, 0.0), "plant", {}, {}))),
    ]
    for i, (topic, payload) in enumerate(samples):
        recording.write(topic, payload, 1_700_000_000_000_000_000 + i)
    recording.close()
    rows = sorted(read_back(tmp_path / RECORDING_FILE), key=lambda row: row[2].publish_time)
    assert [m.publish_time - 1_700_000_000_000_000_000 for _, _, m in rows] == list(range(len(samples)))
    assert [m.log_time / 1e9 for _, _, m in rows] == [0.0, 600.0, 600.0, 600.0, 600.0, 600.0, 600.0, 1200.0, 1200.0]
    schema, channel, message = rows[2]
    assert channel.topic == "can/flight" and channel.message_encoding == "json" and schema.encoding == "jsonschema"
    body = json.loads(message.data)
    assert body["name"] == "MTQ_CMD" and body["direction"] == "OBC->MTQ" and body["crc_ok"] is True
    assert body["id"] == frame.arbitration_id and body["data"] == bytes(frame.data).hex()
    assert (body["timestamp_s"], body["sender_id"], body["sequence"], body["sim_time_s"]) == (12.5, 7, 41, 600.0)
    assert body["signals"]["DipoleX"] == 0.25 and body["signals"]["DipoleY"] == -0.5 and body["signals"]["AliveCounter"] == 3
    assert set(body) <= set(json.loads(schema.data)["properties"])
    assert rows[6][1].topic == "malformed/can/flight" and rows[6][2].data == b"not a frame"


def test_scenario_and_deployment_are_metadata_records(tmp_path):
    from bench.recorder import Recording, deployment_metadata
    from bench.scenario import load_scenario

    deployment = tmp_path / "lab.toml"
    deployment.write_text('name = "lab"\n[hosts.sim]\nnodes = ["plant", "recorder"]\n')
    scenario = load_scenario("attitude_quick")
    argv = ["bench", "node", "recorder", "--deployment", str(deployment), "--host", "sim"]
    assert deployment_metadata(["bench", "node", "recorder"]) is None
    recording = Recording(tmp_path / RECORDING_FILE, RUN_ID, scenario, deployment_metadata(argv))
    recording.close()
    with open(tmp_path / RECORDING_FILE, "rb") as f:
        metadata = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert metadata["deployment"] == {"path": str(deployment), "host": "sim", "toml": deployment.read_text()}
    assert metadata["scenario"]["name"] == "attitude_quick" and metadata["scenario"]["kind"] == "attitude"
    body = json.loads(metadata["scenario"]["scenario_json"])
    assert body["attitude"]["duration_s"] == scenario.attitude.duration_s
    assert body["can"]["security"]["key_hex"] == "(left out)"


def test_unauthentic_samples_are_counted_apart_and_their_stats_not_taken(tmp_path):
    """A sample that failed the data-topic MAC (the Recorder's verifier says why) goes raw to
    `unauthentic/<topic>`, is counted per reason, and its ProcessStats do not become the publisher's."""
    from bench.bus.data_auth import FORGED, REPLAYED
    from bench.bus.schemas import ProcessStats
    from bench.recorder import UNAUTHENTIC_PREFIX, Recording

    recording = Recording(tmp_path / RECORDING_FILE, RUN_ID)
    stats_topic = keys.STATUS_STATS + "/controller"
    genuine = encode(ProcessStats(header(RUN_ID, 0, 0.0), "controller", {keys.COMMAND_THRUST: 20}, {}))
    forged = encode(ProcessStats(header(RUN_ID, 0, 0.0), "controller", {keys.COMMAND_THRUST: 1}, {}))
    command = encode(ThrustCommand(header(RUN_ID, 0, 0.0), [0.9, -0.9, 0.9], True, "rogue", 0.0))
    recording.write(stats_topic, genuine, 1)
    recording.write(stats_topic, forged, 2, FORGED)
    recording.write(keys.COMMAND_THRUST, command, 3, FORGED)
    recording.write(keys.COMMAND_THRUST, command, 4, REPLAYED)
    recording.close()
    counts = recording.counts()
    assert counts["publishers"] == {"controller": {keys.COMMAND_THRUST: 20}}
    assert counts["topics"][keys.COMMAND_THRUST]["recorded"] == 0
    assert counts["topics"][keys.COMMAND_THRUST]["unauthentic"] == {FORGED: 1, REPLAYED: 1}
    assert counts["topics"][keys.COMMAND_THRUST]["missing"] == 20    # the genuine 20 never came
    assert counts["topics"][stats_topic]["unauthentic"] == {FORGED: 1}
    channels = sorted({channel.topic for _, channel, _ in read_back(tmp_path / RECORDING_FILE)})
    assert channels == [stats_topic, UNAUTHENTIC_PREFIX + keys.COMMAND_THRUST, UNAUTHENTIC_PREFIX + stats_topic]


def test_a_long_run_is_recorded_in_bursts_while_a_short_one_waits_for_the_stop(tmp_path, monkeypatch):
    """The spool is written into the recording once it holds ASSEMBLE_AT_SAMPLES (here 10), so a
    long run never leaves more than that for the stop; below it nothing is written during the run."""
    import bench.recorder as recorder_module

    monkeypatch.setattr(recorder_module, "ASSEMBLE_AT_SAMPLES", 10)
    with session_pair() as (recorder_session, publisher_session):
        recorder = Recorder(node_context("recorder", RUN_ID, recorder_session, tmp_path))
        publisher = node_context("plant", RUN_ID, publisher_session, tmp_path)
        publisher.declare_ready([keys.TRUTH, keys.SENSE_RELPOS, keys.COMMAND_THRUST])
        hdr = header(RUN_ID, 0, 0.0)
        for _ in range(3):
            publisher.publish(keys.TRUTH, TruthState(hdr, [0.0] * 6, [0.0] * 3))
        wait_until(lambda: recorder.arrived == 3)
        recorder.drain(0.0)
        assert sum(recorder.recording.recorded.values()) == 0 and len(recorder.spool) == 3   # waits for the stop
        sent = 3 + publish_loop_samples(publisher)
        wait_until(lambda: recorder.arrived == sent)
        recorder.drain(0.0)
        assert sum(recorder.recording.recorded.values()) == sent and len(recorder.spool) == 0
        counts = recorder.finish()
    assert counts["topics"][keys.TRUTH]["recorded"] == 3 + N_STEPS
    assert len(read_back(tmp_path / RECORDING_FILE)) == sent
