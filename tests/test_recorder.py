"""The recorder node: every sample in the MCAP file, malformed ones raw, counts against publishers."""
from __future__ import annotations

import json
import threading
import time

from mcap.reader import make_reader

from bench.bus import keys
from bench.bus.clock_sync import declare_clock_responder
from bench.bus.schemas import RelativePosition, ThrustCommand, TruthState, encode, header
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
        responder = declare_clock_responder(other_session, RUN_ID, "plant")
        node = threading.Thread(target=lambda: setattr(ctx, "exit_code", run(ctx)))
        node.start()
        watcher = node_context("launcher", RUN_ID, other_session, tmp_path)
        watcher.wait_for_tokens(keys.READY, ["recorder"], timeout_s=10.0)
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
