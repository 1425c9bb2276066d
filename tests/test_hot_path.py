"""Only what the loop waits for on its hot path (issue 49): the plant's sample leaves before the rest
of its step's messages, kept messages wait for `publish_pending`, the recorder's spool gives back
what it took, and the hop trace pairs a sender's stamps with the receiver's."""
from __future__ import annotations

import logging

import numpy as np
import pytest

from bench.bus import keys
from bench.bus.schemas import RangeBearing, RelativePosition, StepDone, TruthState, decode, header
from bench.plant.model import TranslationPlant
from bench.plant.node import _publish_sample
from bench.recorder_intake import SampleSpool
from bench.runtime import hop_trace
from bench.runtime.node import NodeContext
from bench.scenario import load_scenario

RUN_ID = "hot-path-test"
KINDS = {keys.TRUTH: TruthState, keys.SENSE_RELPOS: RelativePosition, keys.SENSE_RANGE_BEARING: RangeBearing,
         keys.STATUS_STEP: StepDone}


class PutLog:
    """A stand-in for the Zenoh session: every put, in order, as (topic, payload)."""

    def __init__(self):
        self.puts: list[tuple[str, bytes]] = []

    def declare_publisher(self, key_expr, **_options):
        session = self

        class Publisher:
            def put(self, payload, attachment=None):
                session.puts.append((key_expr[len(keys.key(RUN_ID, "")):], payload))
        return Publisher()

    def topics(self) -> list[str]:
        return [topic for topic, _ in self.puts]

    def message(self, topic: str):
        return next(decode(payload, KINDS[t]) for t, payload in self.puts if t == topic)


def context(scenario, tmp_path, session) -> NodeContext:
    return NodeContext(name="plant", run_id=RUN_ID, scenario=scenario, session=session, run_dir=tmp_path,
                       log=logging.getLogger("test.hot_path"))


def test_kept_messages_wait_for_publish_pending_and_keep_their_order(tmp_path):
    session = PutLog()
    ctx = context(load_scenario("rendezvous_lqr"), tmp_path, session)
    first, second = (StepDone(header(RUN_ID, k, float(k)), 10) for k in (1, 2))
    ctx.publish_later(keys.STATUS_STEP, first)
    ctx.publish_later(keys.STATUS_STEP, second)
    ctx.publish(keys.TRUTH, TruthState(header(RUN_ID, 3, 3.0), [0.0] * 6, [0.0] * 3))
    assert session.topics() == [keys.TRUTH]
    ctx.publish_pending()
    assert session.topics() == [keys.TRUTH, keys.STATUS_STEP, keys.STATUS_STEP]
    assert [decode(p, StepDone).header.seq for t, p in session.puts[1:]] == [1, 2]
    ctx.publish_pending()      # nothing kept twice
    assert len(session.puts) == 3 and ctx.published[keys.STATUS_STEP] == 2


@pytest.mark.parametrize("consumed", [keys.TRUTH, keys.SENSE_RELPOS, keys.SENSE_RANGE_BEARING])
def test_the_sample_the_estimator_reads_leaves_first_and_every_order_senses_the_same(tmp_path, consumed):
    scenario = load_scenario("rendezvous_smoother")
    reference = PutLog()    # truth first, as a truth-mode estimator reads it
    _publish_sample(context(scenario, tmp_path, reference), TranslationPlant.from_scenario(scenario),
                    np.zeros(3), keys.TRUTH)
    session = PutLog()
    ctx = context(scenario, tmp_path, session)
    ctx.publish_later(keys.STATUS_STEP, StepDone(header(RUN_ID, 0, 0.0), 10))   # the previous step's report
    _publish_sample(ctx, TranslationPlant.from_scenario(scenario), np.zeros(3), consumed)
    others = [t for t in (keys.TRUTH, keys.SENSE_RELPOS, keys.SENSE_RANGE_BEARING) if t != consumed]
    assert session.topics() == [consumed, keys.STATUS_STEP, *others]
    # Each sensor draws from its own generator: the order it is read in changes no value.
    for topic in (keys.TRUTH, keys.SENSE_RELPOS, keys.SENSE_RANGE_BEARING):
        assert without_header(session.message(topic)) == without_header(reference.message(topic))


def without_header(message) -> dict:
    return {field: getattr(message, field) for field in message.__struct_fields__ if field != "header"}


def test_the_recorder_spool_gives_back_each_sample_as_it_took_it(tmp_path):
    samples = [("bench/r/truth", b"\x00payload", b"mac-bytes", 1_700_000_000_000_000_001),
               ("bench/r/can/flight", b"", None, 5),
               ("bench/r/\u00e9v\u00e9nement", bytes(range(256)) * 40, b"", -1)]
    spool = SampleSpool(tmp_path)
    for sample in samples:
        spool.append(sample)
    assert len(spool) == 3
    assert list(spool.take()) == samples
    assert len(spool) == 0 and list(spool.take()) == []     # taken once
    spool.append(samples[1])
    assert list(spool.take()) == [samples[1]]
    spool.close()


def test_a_traced_queue_stamps_the_message_it_hands_over():
    trace = hop_trace.HopTrace()
    q = hop_trace.TracedQueue(trace, keys.TRUTH)
    q.put(TruthState(header(RUN_ID, 7, 7.0), [0.0] * 6, [0.0] * 3))
    assert q.get(timeout=1.0).header.seq == 7
    assert [(topic, seq) for topic, seq, _ in trace.taken] == [(keys.TRUTH, 7)]
