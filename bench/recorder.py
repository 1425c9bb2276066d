"""The recorder node: every sample of a run into runs/<run_id>/recording.mcap.

It subscribes to `bench/<run_id>/**` raw, so it sees whatever is published, known or not. Each
sample is classified by its "type" tag against the bench's message types: a valid message goes to
a JSON channel named after its topic with that type's JSON schema (Foxglove reads it); a CAN frame
of the Zenoh transport (`can/<channel>`) goes raw to its own channel and counts as recorded; a
payload that does not decode goes, byte for byte, to `malformed/<topic>` and is counted.

Anyone on the bus can publish under `bench/<run_id>/**`, so what the recorder keeps is budgeted
(`RecordingBudget`): per topic a message rate and a byte rate, all topics together a byte rate,
a size limit per message and a limit on the number of topics. What is over budget is dropped in
the Zenoh callback, before it is queued, and counted per topic and reason in the counts file.
The budgets are ten times what the bench's own loop publishes in lock-step on this machine, so a
run of the bench never loses a sample to them.

Zenoh delivers samples on its own threads; they are queued with their arrival time and written by
the node's thread, because mcap's Writer is not thread-safe and a slow disk must not block Zenoh.

At the end it writes recorder_counts.json: per topic what it recorded, what was malformed, and
what the publishers say they published (their ProcessStats), so a lost sample shows up as a
difference. It also pings every process's clock (bench/bus/clock_sync.py) during the run and
writes clock_offsets.json.
"""
from __future__ import annotations

import json
import queue
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Union

import msgspec
from mcap.writer import Writer

from bench.bus import clock_sync, keys
from bench.bus.can import zenoh_wire
from bench.bus.can.zenoh_interface import CAN_TOPIC
from bench.bus.schemas import SCHEMA_VERSION, Message, ProcessStats, json_schema
from bench.bus import plan_message as _plan_message   # noqa: F401  registers AttitudePlanMessage

RECORDING_FILE = "recording.mcap"
COUNTS_FILE = "recorder_counts.json"
OFFSETS_FILE = "clock_offsets.json"
MALFORMED_PREFIX = "malformed/"
# A chunk reaches the file when full: a recorder killed mid-run loses at most this much (a few
# seconds of a real-time run) instead of mcap's default 1 MiB, the whole of a short run.
CHUNK_SIZE_BYTES = 64 * 1024
CLOCK_SYNC_PERIOD_S = 0.5   # cheap (one query per round); catches short-lived runs
# The writer wakes this often and writes everything queued since, rather than once per sample:
# on a small machine each wake-up of the recorder competes with the loop's processes for a core.
DRAIN_PERIOD_S = 0.2

CAN_FRAME_ENCODING = "application/x-bench-can-frame"    # bench/bus/can/zenoh_wire.py's layout

# Budgets (see the module docstring). The default loop publishes ~1 300 samples/s per topic of
# ~0.5 kB in lock-step (README, loop rate); a saturated 1 Mbit/s CAN bus is ~7 900 frames/s.
MAX_MESSAGE_BYTES = 256 * 1024
MAX_TOPICS = 512
TOPIC_MESSAGES_PER_S, TOPIC_MESSAGE_BURST = 20_000.0, 40_000.0
TOPIC_BYTES_PER_S, TOPIC_BYTE_BURST = 2e6, 8e6
TOTAL_BYTES_PER_S, TOTAL_BYTE_BURST = 8e6, 32e6

MESSAGE_TYPES: tuple[type[Message], ...] = tuple(Message.__subclasses__())
_any_message = msgspec.json.Decoder(Union[MESSAGE_TYPES])  # tagged union: dispatches on "type"


def classify_any(payload: bytes) -> Message | None:
    """The bench message in `payload` (any run), else None."""
    try:
        return _any_message.decode(payload)
    except (msgspec.ValidationError, msgspec.DecodeError):
        return None


def classify(payload: bytes, run_id: str) -> Message | None:
    """The message in `payload` if it is a valid bench message of this run, else None."""
    try:
        message = _any_message.decode(payload)
    except (msgspec.ValidationError, msgspec.DecodeError):
        return None
    header = message.header
    if header.schema_version != SCHEMA_VERSION or header.run_id != run_id:
        return None
    return message


@dataclass
class TokenBucket:
    """Admits `amount` if the bucket holds it; refills at rate_per_s up to burst."""

    rate_per_s: float
    burst: float
    tokens: float = -1.0
    last_s: float | None = None

    def take(self, amount: float, now_s: float) -> bool:
        if self.last_s is None:
            self.tokens, self.last_s = self.burst, now_s
        self.tokens = min(self.burst, self.tokens + (now_s - self.last_s) * self.rate_per_s)
        self.last_s = now_s
        if amount > self.tokens:
            return False
        self.tokens -= amount
        return True


@dataclass
class RecordingBudget:
    """What the recorder may keep; `admit` returns None or the reason a sample is dropped."""

    max_message_bytes: int = MAX_MESSAGE_BYTES
    max_topics: int = MAX_TOPICS
    total: TokenBucket = field(default_factory=lambda: TokenBucket(TOTAL_BYTES_PER_S, TOTAL_BYTE_BURST))
    messages: dict = field(default_factory=dict)
    bytes: dict = field(default_factory=dict)
    dropped: dict = field(default_factory=dict)      # topic -> Counter(reason)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def admit(self, topic: str, size: int, now_s: float) -> str | None:
        with self._lock:     # Zenoh calls back on several threads
            reason = self._reason(topic, size, now_s)
            if reason is not None:
                key = topic if (topic in self.messages or len(self.dropped) < self.max_topics) else "<other topics>"
                self.dropped.setdefault(key, Counter())[reason] += 1
            return reason

    def _reason(self, topic: str, size: int, now_s: float) -> str | None:
        if size > self.max_message_bytes:
            return "message_too_large"
        if topic not in self.messages:
            if len(self.messages) >= self.max_topics:
                return "too_many_topics"
            self.messages[topic] = TokenBucket(TOPIC_MESSAGES_PER_S, TOPIC_MESSAGE_BURST)
            self.bytes[topic] = TokenBucket(TOPIC_BYTES_PER_S, TOPIC_BYTE_BURST)
        if not self.messages[topic].take(1.0, now_s):
            return "message_rate"
        if not self.bytes[topic].take(size, now_s):
            return "byte_rate"
        if not self.total.take(size, now_s):
            return "total_byte_rate"
        return None

    def dropped_counts(self) -> dict[str, dict[str, int]]:
        with self._lock:
            return {topic: dict(reasons) for topic, reasons in sorted(self.dropped.items())}


def root_object_schema(kind: type[Message]) -> dict:
    """The message's JSON schema with its object at the root ($defs kept for nested types).

    msgspec puts everything under $defs behind a root $ref; viewers that take the root's
    "properties" for the field list (Foxglove's JSON-schema channels) want the object itself.
    """
    schema = json_schema(kind)
    defs = schema.get("$defs", {})
    root = schema.get("$ref", "").rpartition("/")[2]
    return {**defs[root], "$defs": defs} if root in defs else schema


def topic_of(key_expr: str, run_id: str) -> str:
    """`bench/<run_id>/sense/relpos` -> `sense/relpos`."""
    prefix = keys.key(run_id, "")
    return key_expr[len(prefix):] if key_expr.startswith(prefix) else key_expr


class Recording:
    """An MCAP file with one JSON channel per (topic, message type) and raw malformed channels."""

    def __init__(self, path: Path, run_id: str):
        self.run_id = run_id
        self._file = open(path, "wb")
        self._writer = Writer(self._file, chunk_size=CHUNK_SIZE_BYTES)
        self._writer.start(profile="", library="orbit-hil-bench recorder")
        self._schemas: dict[type, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence = 0
        self.recorded: Counter = Counter()
        self.malformed: Counter = Counter()
        self.dropped: dict[str, dict[str, int]] = {}    # filled from the budget at the end
        self.published_by: dict[str, dict[str, int]] = {}

    def write(self, topic: str, payload: bytes, log_time_ns: int) -> Message | None:
        """Record one sample; returns the decoded message, None if it was malformed or a CAN frame."""
        if topic.startswith(CAN_TOPIC + "/"):
            return self._write_can_frame(topic, payload, log_time_ns)
        message = classify(payload, self.run_id)
        if message is None:
            self.malformed[topic] += 1
            channel_id = self._channel(MALFORMED_PREFIX + topic, None)
        else:
            self.recorded[topic] += 1
            channel_id = self._channel(topic, type(message))
            if isinstance(message, ProcessStats):
                self.published_by[message.process] = dict(message.published)
        self._sequence += 1
        self._writer.add_message(channel_id, log_time=log_time_ns, data=payload,
                                 publish_time=log_time_ns, sequence=self._sequence)
        return message

    def _write_can_frame(self, topic: str, payload: bytes, log_time_ns: int) -> None:
        try:
            zenoh_wire.decode(payload, topic.rpartition("/")[2])
        except zenoh_wire.MalformedFrame:
            self.malformed[topic] += 1
            channel_id = self._channel(MALFORMED_PREFIX + topic, None)
        else:
            self.recorded[topic] += 1
            channel_id = self._channel(topic, None, CAN_FRAME_ENCODING)
        self._sequence += 1
        self._writer.add_message(channel_id, log_time=log_time_ns, data=payload, publish_time=log_time_ns,
                                 sequence=self._sequence)
        return None

    def _channel(self, topic: str, kind: type[Message] | None, encoding: str = "application/octet-stream") -> int:
        name = topic if kind is None else f"{topic}#{kind.__name__}"
        channel_id = self._channels.get(name)
        if channel_id is None:
            if kind is None:
                # Schemaless and not JSON: the bytes as they came, for whoever debugs the sender.
                channel_id = self._writer.register_channel(topic, encoding, 0)
            else:
                channel_id = self._writer.register_channel(topic, "json", self._schema(kind))
            self._channels[name] = channel_id
        return channel_id

    def _schema(self, kind: type[Message]) -> int:
        if kind not in self._schemas:
            data = json.dumps(root_object_schema(kind)).encode()
            self._schemas[kind] = self._writer.register_schema(kind.__name__, "jsonschema", data)
        return self._schemas[kind]

    def close(self) -> None:
        self._writer.finish()
        self._file.close()

    def counts(self) -> dict:
        """Recorded and malformed per topic, beside what the publishers reported publishing."""
        published: Counter = Counter()
        for topics in self.published_by.values():
            published.update(topics)
        topics = {}
        for topic in sorted(set(self.recorded) | set(self.malformed) | set(published) | set(self.dropped)):
            dropped = sum(self.dropped.get(topic, {}).values())
            seen = self.recorded[topic] + self.malformed[topic] + dropped
            reported = published.get(topic)
            topics[topic] = {
                "recorded": self.recorded[topic],
                "malformed": self.malformed[topic],
                "published": reported,
                "missing": None if reported is None else max(0, reported - seen),
            }
            if dropped:
                topics[topic]["dropped"] = dropped
                topics[topic]["dropped_by_reason"] = dict(self.dropped[topic])
        return {"run_id": self.run_id, "topics": topics, "publishers": self.published_by}


class ClockSyncThread(threading.Thread):
    """Re-estimates clock offsets every few seconds, keeping each process's best reading."""

    def __init__(self, ctx):
        super().__init__(name="clock-sync", daemon=True)
        self.ctx = ctx
        self.offsets: dict[str, clock_sync.ClockOffset] = {}

    def run(self) -> None:
        while not self.ctx.stop.wait(CLOCK_SYNC_PERIOD_S):
            try:
                self.offsets = clock_sync.estimate_offsets(self.ctx.session, self.ctx.run_id, rounds=3,
                                                           known=self.offsets)
            except Exception as exc:   # a closed session at shutdown is not worth a crash
                self.ctx.log.warning("clock sync failed: %s", exc)
                return
        if not self.offsets:
            # A run shorter than the first period still gets one reading of each live process.
            try:
                self.offsets = clock_sync.estimate_offsets(self.ctx.session, self.ctx.run_id, rounds=3)
            except Exception as exc:
                self.ctx.log.warning("clock sync failed: %s", exc)


class Recorder:
    """Subscription, queue and recording of one run; `run(ctx)` drives it until ctx.stop."""

    def __init__(self, ctx):
        self.ctx = ctx
        self.recording = Recording(ctx.run_dir / RECORDING_FILE, ctx.run_id)
        self.samples: queue.SimpleQueue = queue.SimpleQueue()
        self.budget = RecordingBudget()
        self.arrived = 0     # samples handed over by Zenoh so far, kept or dropped (tests wait on it)
        self.subscriber = ctx.session.declare_subscriber(keys.all_topics(ctx.run_id), self._on_sample)

    def _on_sample(self, sample) -> None:
        key_expr = str(sample.key_expr)
        payload = sample.payload
        if self.budget.admit(topic_of(key_expr, self.ctx.run_id), len(payload), time.monotonic()) is None:
            self.samples.put((key_expr, payload.to_bytes(), time.time_ns()))
        self.arrived += 1

    def drain(self, timeout_s: float) -> None:
        """Write every queued sample, waiting up to timeout_s for the first one."""
        try:
            item = self.samples.get(timeout=timeout_s) if timeout_s > 0 else self.samples.get_nowait()
        except queue.Empty:
            return
        while True:
            key_expr, payload, log_time_ns = item
            self.recording.write(topic_of(key_expr, self.ctx.run_id), payload, log_time_ns)
            try:
                item = self.samples.get_nowait()
            except queue.Empty:
                return

    def finish(self) -> dict:
        """Stop listening, write what is still queued, close the file; the counts."""
        self.subscriber.undeclare()
        self.drain(0.0)
        self.recording.dropped = self.budget.dropped_counts()
        self.recording.close()
        counts = self.recording.counts()
        _write_json(self.ctx.run_dir / COUNTS_FILE, counts)
        return counts


def run(ctx) -> int:
    """Node entry point: record until ctx.stop is set, then flush and write the counts."""
    recorder = Recorder(ctx)
    ctx.declare_ready([])   # subscribed: the plant may start publishing
    clock = ClockSyncThread(ctx)
    clock.start()
    try:
        while not ctx.stop.wait(DRAIN_PERIOD_S):
            recorder.drain(0.0)
    finally:
        recorder.finish()
        ctx.malformed.update(recorder.recording.malformed)
        clock.join(timeout=3.0)
        _write_json(ctx.run_dir / OFFSETS_FILE, {p: o.to_dict() for p, o in sorted(clock.offsets.items())})
    ctx.log.info("recorded %s; malformed %s", dict(recorder.recording.recorded), dict(recorder.recording.malformed))
    return 0


def _write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=2, sort_keys=True))
