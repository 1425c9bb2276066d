"""The recorder node: every sample of a run into runs/<run_id>/recording.mcap.

It subscribes to `bench/<run_id>/**` raw, so it sees whatever is published, known or not. Each
sample is classified by its "type" tag against the bench's message types: a valid message goes to
a JSON channel named after its topic with that type's JSON schema (Foxglove reads it); a CAN frame
of the Zenoh transport (`can/<channel>`) goes raw to its own channel and counts as recorded; a
payload that does not decode goes, byte for byte, to `malformed/<topic>` and is counted. With the
run's data key (bench/bus/data_auth.py), a sample without a valid, fresh MAC goes, byte for byte,
to `unauthentic/<topic>` and is counted per reason (forged, replayed); it is never read as the
message it claims to be (its ProcessStats are not taken). CAN frames carry SecOC, not this MAC.

Anyone on the bus can publish under `bench/<run_id>/**`, so what the recorder keeps is budgeted
(`RecordingBudget`): per topic a message rate and a byte rate, all topics together a byte rate,
a size limit per message and a limit on the number of topics. What is over budget is dropped in
the Zenoh callback, before it is queued, and counted per topic and reason in the counts file.
The budgets are ten times what the bench's own loop publishes in lock-step on this machine, so a
run of the bench never loses a sample to them.

The recording is assembled off the loop's hot path. During the run, Zenoh's callback only copies
each admitted sample's bytes with its arrival time into a queue, and the node's thread moves them
every DRAIN_PERIOD_S into a spool file (an unlinked temporary file in the run directory: memory
stays flat); checking MACs, classifying, encoding JSON and writing the MCAP wait until the spool
holds ASSEMBLE_AT_SAMPLES, and for the stop, in arrival order. In lock-step a recorder that did
that work as each sample came competed with the loop's processes for the two cores at every hop
(benchmarks/bench_loop.py, docs/performance.md). A recorder killed mid-run loses what it had spooled
and not yet written (at most ASSEMBLE_AT_SAMPLES samples).

Time (`SimTimeBase`): a message's MCAP log time is the run's simulated time, so a viewer's timeline
is the mission's (a 48 h rendezvous spans 48 h): the sim_time_s of its header, counted from the
run's t = 0. What has no simulated time of its own (a CAN frame, a malformed payload, the shutdown
ProcessStats, the board's MtqApplied report, which carries 0.0) gets the simulated time of the
newest step seen so far: it happened after that step's messages arrived. The publish time is the
wall clock at which the recorder received the sample (time.time_ns), in arrival order. After the
run, the report build places the CAN frames on their own simulated time and adds the decoded
frames of a lock-step bus on simulated time from can.log (bench/report/recording_can.py).

A CAN frame is recorded as JSON (schema CAN_FRAME_SCHEMA): identifier, data in hex, flags, the
Zenoh channel and the DBC sender and receiver, the sender's timestamp, and the signals decoded
with the run's DBC (bench/bus/can/mtq.dbc through protocol.Protocol), so Foxglove plots them.
The scenario (its SecOC key left out) and, for a run placed by a deployment file, that file go
into the file as MCAP metadata records.

At the end it writes recorder_counts.json: per topic what it recorded, what was malformed, and
what the publishers say they published (their authenticated ProcessStats), so a lost sample shows up as a
difference. It also pings every process's clock (bench/bus/clock_sync.py) during the run and
writes clock_offsets.json.
"""
from __future__ import annotations

import json
import math
import queue
import sys
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Union

import can
import msgspec
from mcap.data_stream import RecordBuilder
from mcap.writer import Writer

from bench.bus import clock_sync, data_auth, keys
from bench.bus.presence import PresenceQuery
from bench.bus.can import protocol as can_protocol
from bench.bus.can import zenoh_wire
from bench.bus.can.zenoh_interface import CAN_TOPIC
from bench.bus.schemas import SCHEMA_VERSION, BusEvent, Message, MtqApplied, ProcessStats, json_schema
from bench.bus.spill import SpilledRecords
from bench.recorder_intake import RecordingBudget, SampleSpool
from bench.bus import plan_message as _plan_message   # noqa: F401  registers AttitudePlanMessage

RECORDING_FILE = "recording.mcap"
COUNTS_FILE = "recorder_counts.json"
OFFSETS_FILE = "clock_offsets.json"
MALFORMED_PREFIX = "malformed/"
UNAUTHENTIC_PREFIX = "unauthentic/"
# mcap's default is 1 MiB: a viewer seeking to a moment of the run decompresses one small chunk.
CHUNK_SIZE_BYTES = 64 * 1024
CLOCK_SYNC_PERIOD_S = 0.5   # cheap (one query per round); catches short-lived runs
# A lock-step run of a few hundred steps can be over (its plant gone) within a second of its start,
# on a loaded host before the first 0.5 s round: ping every 0.1 s over the first seconds.
CLOCK_SYNC_EARLY_PERIOD_S = 0.1
CLOCK_SYNC_EARLY_FOR_S = 3.0
# The node's thread wakes this often and spools everything queued since, rather than once per
# sample: on a small machine each wake-up of the recorder competes with the loop's processes for a core.
DRAIN_PERIOD_S = 0.2
# The spool is recorded (MACs, classification, MCAP) once it holds this many samples, and at the
# stop: a run of up to this many samples (a 2000-step lock-step rendezvous publishes 14 000) is
# recorded only at its stop, a long one in bursts of about 1-2 s of the recorder's CPU, and the
# stop never has more than that left to do within the launcher's grace (5 s, bench/launcher/children.py).
ASSEMBLE_AT_SAMPLES = 50_000

# Messages whose header has no simulated time of the loop: the shutdown counts, the board's
# report (the board sees CAN frames, not steps; its header carries 0.0), and what the driver
# detects on the bus (event/can: its thread sees frames, not steps).
UNSTEPPED_TYPES: tuple[type[Message], ...] = (ProcessStats, MtqApplied, BusEvent)
MAX_LOG_TIME_NS = 2**63 - 1     # MCAP times are uint64; kept in int64 range for every reader
METADATA_SCENARIO = "scenario"
METADATA_DEPLOYMENT = "deployment"
MAX_DEPLOYMENT_BYTES = 64 * 1024
CAN_FRAME_SCHEMA_NAME = "bench.CanFrame"
CAN_FRAME_SCHEMA = {
    "title": CAN_FRAME_SCHEMA_NAME,
    "description": "One CAN frame seen on a Zenoh CAN channel of the run, with its DBC-decoded signals",
    "type": "object",
    "properties": {
        "sim_time_s": {"type": "number", "description": "the run's simulated time of the newest step seen [s]"},
        "timestamp_s": {"type": "number", "description": "the sender's timestamp of the frame (wall clock) [s]"},
        "channel": {"type": "string", "description": "the Zenoh CAN channel (flight or board side of the bus model)"},
        "id": {"type": "integer", "description": "arbitration identifier"},
        "id_hex": {"type": "string"},
        "is_extended_id": {"type": "boolean"},
        "is_fd": {"type": "boolean"},
        "is_error_frame": {"type": "boolean"},
        "is_remote_frame": {"type": "boolean"},
        "dlc": {"type": "integer"},
        "data": {"type": "string", "description": "data bytes in hex"},
        "sender_id": {"type": "integer", "description": "the sending bus instance (zenoh_wire)"},
        "sequence": {"type": "integer", "description": "the sender's frame sequence number"},
        "name": {"type": ["string", "null"], "description": "DBC message name; null for an identifier not in the DBC"},
        "direction": {"type": ["string", "null"], "description": "DBC sender -> receivers, e.g. OBC->MTQ"},
        "decoded": {"type": "boolean", "description": "the frame is a valid frame of the DBC (signals filled)"},
        "crc_ok": {"type": ["boolean", "null"], "description": "E2E CRC check; null for unprotected frames"},
        "signals": {"type": "object", "additionalProperties": {"type": "number"},
                    "description": "DBC signals in physical units"},
    },
    "required": ["sim_time_s", "timestamp_s", "channel", "id", "data", "name", "direction", "signals"],
}

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


class SimTimeBase:
    """The MCAP log time of each recorded sample: the run's simulated time, in ns (see the module
    docstring). A header time that is not a number of seconds in [0, MAX_LOG_TIME_NS] (anyone can
    publish) is treated as having none."""

    def __init__(self):
        self.newest_step_ns = 0

    def of_message(self, message: Message) -> int:
        if isinstance(message, UNSTEPPED_TYPES):
            return self.newest_step_ns
        sim_time_s = message.header.sim_time_s
        if not (math.isfinite(sim_time_s) and 0.0 <= sim_time_s <= MAX_LOG_TIME_NS / 1e9):
            return self.newest_step_ns
        log_time_ns = min(int(round(sim_time_s * 1e9)), MAX_LOG_TIME_NS)
        self.newest_step_ns = max(self.newest_step_ns, log_time_ns)
        return log_time_ns

    def of_unstepped(self) -> int:
        return self.newest_step_ns


def can_frame_signals(protocol: can_protocol.Protocol, msg: can.Message) -> dict:
    """What the DBC says of a frame: name, direction (DBC sender -> receivers), whether it decodes
    as a frame of the protocol, its E2E CRC verdict and its signals (physical units)."""
    name = protocol.name_of(msg.arbitration_id) if not msg.is_extended_id else None
    direction = None
    if name is not None:
        message = protocol.db.get_message_by_name(name)
        receivers = sorted({r for signal in message.signals for r in signal.receivers})
        direction = f"{','.join(message.senders)}->{','.join(receivers)}"
    frame = protocol.decode(msg)
    signals = {k: float(v) if isinstance(v, float) else int(v) for k, v in frame.signals.items()} if frame else {}
    return {"name": name, "direction": direction, "decoded": frame is not None,
            "crc_ok": None if frame is None else frame.crc_ok, "signals": signals}


def can_frame_json(protocol: can_protocol.Protocol, msg: can.Message, channel: str, sender_id: int,
                   sequence: int, sim_time_s: float) -> dict:
    """One frame as CAN_FRAME_SCHEMA describes it."""
    return {
        "sim_time_s": sim_time_s, "timestamp_s": float(msg.timestamp), "channel": channel,
        "id": int(msg.arbitration_id), "id_hex": f"0x{msg.arbitration_id:03X}",
        "is_extended_id": bool(msg.is_extended_id), "is_fd": bool(msg.is_fd),
        "is_error_frame": bool(msg.is_error_frame), "is_remote_frame": bool(msg.is_remote_frame),
        "dlc": int(msg.dlc), "data": bytes(msg.data or b"").hex(), "sender_id": int(sender_id),
        "sequence": int(sequence), **can_frame_signals(protocol, msg),
    }


def scenario_metadata(scenario) -> dict[str, str]:
    """The scenario as it ran (scenario.json's content), its SecOC key left out: a recording is
    shared with whoever looks at it, the key is the bus's secret."""
    body = msgspec.to_builtins(scenario)
    security = (body.get("can") or {}).get("security")
    if isinstance(security, dict) and "key_hex" in security:
        security["key_hex"] = "(left out)"
    return {"name": str(getattr(scenario, "name", "")), "kind": str(getattr(scenario, "kind", "")),
            "scenario_json": json.dumps(body, sort_keys=True)}


def deployment_metadata(argv: list[str]) -> dict[str, str] | None:
    """The deployment file this node was started with (`--deployment FILE --host NAME` on its
    command line, as the launcher passes them), None for a run on one host."""
    def value(option: str) -> str | None:
        return argv[argv.index(option) + 1] if option in argv[:-1] else None

    path = value("--deployment")
    if path is None:
        return None
    try:
        with open(path, "rb") as f:
            text = f.read(MAX_DEPLOYMENT_BYTES + 1)
    except OSError as exc:
        return {"path": path, "host": value("--host") or "", "error": f"unreadable: {exc}"}
    if len(text) > MAX_DEPLOYMENT_BYTES:
        return {"path": path, "host": value("--host") or "", "error": f"over {MAX_DEPLOYMENT_BYTES} bytes, not copied"}
    return {"path": path, "host": value("--host") or "", "toml": text.decode("utf-8", errors="replace")}


def _record_bytes(record) -> bytes:
    builder = RecordBuilder()
    record.write(builder)
    return builder.end()


def spill_chunk_indexes(writer: Writer, directory: Path) -> None:
    """Keep the writer's chunk indexes on disk until finish() writes them into the summary.

    mcap's Writer holds a ChunkIndex per chunk (with a message-index offset per channel) for the
    whole run: with 64 KiB chunks, ~2 a second in a real-time attitude run, that was the recorder's
    ~20 MiB/h of growth (issue 44). The file written is the same. Relies on the Writer's private
    list (mcap 1.x: appended once per chunk, iterated once in finish()); a Writer without it keeps
    its own list, as before."""
    name = "_Writer__chunk_indices"
    if isinstance(getattr(writer, name, None), list) and not getattr(writer, name):
        setattr(writer, name, SpilledRecords(_record_bytes, directory))


class Recording:
    """An MCAP file with one JSON channel per (topic, message type), CAN channels as JSON with their
    decoded signals, raw malformed channels, and the scenario and deployment as metadata."""

    def __init__(self, path: Path, run_id: str, scenario=None, deployment: dict[str, str] | None = None):
        self.run_id = run_id
        self._file = open(path, "wb")
        self._writer = Writer(self._file, chunk_size=CHUNK_SIZE_BYTES)
        spill_chunk_indexes(self._writer, path.parent)
        self._writer.start(profile="", library="orbit-hil-bench recorder")
        if scenario is not None:
            self._writer.add_metadata(METADATA_SCENARIO, scenario_metadata(scenario))
        if deployment is not None:
            self._writer.add_metadata(METADATA_DEPLOYMENT, deployment)
        can_config = getattr(scenario, "can", None)
        # No key: the recorder only reads frames (it cannot and need not check a MAC).
        self._can_protocol = (can_protocol.Protocol(can_config.node_id, can_config.security.profile)
                              if can_config is not None else can_protocol.Protocol())
        self.sim_time = SimTimeBase()
        self._schemas: dict[type | str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence = 0
        self.recorded: Counter = Counter()
        self.malformed: Counter = Counter()
        self.dropped: dict[str, dict[str, int]] = {}    # filled from the budget at the end
        self.published_by: dict[str, dict[str, int]] = {}
        # sender -> topic -> messages recorded with that sender's valid tag: what each process put on
        # which key, whatever it says of itself (an outside node publishes no stats).
        self.signed_by: dict[str, Counter] = {}
        self.unauthentic: dict[str, Counter] = {}      # reason (forged, replayed) -> topic -> count

    def write(self, topic: str, payload: bytes, received_ns: int, unauthentic: str | None = None,
              sender: str | None = None) -> Message | None:
        """Record one sample received at received_ns (wall clock): its log time is its simulated
        time, its publish time received_ns. Returns the decoded message, None if it was malformed,
        unauthentic (the reason its MAC failed, data_auth.FORGED or REPLAYED) or a CAN frame."""
        if unauthentic is not None:
            self.unauthentic.setdefault(unauthentic, Counter())[topic] += 1
            self._add(self._channel(UNAUTHENTIC_PREFIX + topic, None), self.sim_time.of_unstepped(), payload, received_ns)
            return None
        if topic.startswith(CAN_TOPIC + "/"):
            return self._write_can_frame(topic, payload, received_ns)
        if sender is not None:
            self.signed_by.setdefault(sender, Counter())[topic] += 1
        message = classify(payload, self.run_id)
        if message is None:
            self.malformed[topic] += 1
            channel_id = self._channel(MALFORMED_PREFIX + topic, None)
            log_time_ns = self.sim_time.of_unstepped()
        else:
            self.recorded[topic] += 1
            channel_id = self._channel(topic, type(message))
            log_time_ns = self.sim_time.of_message(message)
            if isinstance(message, ProcessStats):
                self.published_by[message.process] = dict(message.published)
        self._add(channel_id, log_time_ns, payload, received_ns)
        return message

    def _add(self, channel_id: int, log_time_ns: int, data: bytes, received_ns: int) -> None:
        self._sequence += 1
        self._writer.add_message(channel_id, log_time=log_time_ns, data=data, publish_time=max(0, received_ns),
                                 sequence=self._sequence)

    def _write_can_frame(self, topic: str, payload: bytes, received_ns: int) -> None:
        log_time_ns = self.sim_time.of_unstepped()
        channel = topic.rpartition("/")[2]
        try:
            msg, sender_id, sequence = zenoh_wire.decode(payload, channel)
        except zenoh_wire.MalformedFrame:
            self.malformed[topic] += 1
            self._add(self._channel(MALFORMED_PREFIX + topic, None), log_time_ns, payload, received_ns)
            return None
        self.recorded[topic] += 1
        body = can_frame_json(self._can_protocol, msg, channel, sender_id, sequence, log_time_ns / 1e9)
        self._add(self._can_channel(topic), log_time_ns, json.dumps(body).encode(), received_ns)
        return None

    def _can_channel(self, topic: str) -> int:
        channel_id = self._channels.get(topic)
        if channel_id is None:
            if CAN_FRAME_SCHEMA_NAME not in self._schemas:
                self._schemas[CAN_FRAME_SCHEMA_NAME] = self._writer.register_schema(
                    CAN_FRAME_SCHEMA_NAME, "jsonschema", json.dumps(CAN_FRAME_SCHEMA).encode())
            channel_id = self._writer.register_channel(topic, "json", self._schemas[CAN_FRAME_SCHEMA_NAME])
            self._channels[topic] = channel_id
        return channel_id

    def _channel(self, topic: str, kind: type[Message] | None) -> int:
        name = topic if kind is None else f"{topic}#{kind.__name__}"
        channel_id = self._channels.get(name)
        if channel_id is None:
            if kind is None:
                # Schemaless and not JSON: the bytes as they came, for whoever debugs the sender.
                channel_id = self._writer.register_channel(topic, "application/octet-stream", 0)
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
        unauthentic_topics = {t for counts in self.unauthentic.values() for t in counts}
        for topic in sorted(set(self.recorded) | set(self.malformed) | set(published) | set(self.dropped)
                            | unauthentic_topics):
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
            if topic in unauthentic_topics:
                topics[topic]["unauthentic"] = {reason: counts[topic] for reason, counts in sorted(self.unauthentic.items())
                                                if counts[topic]}
        return {"run_id": self.run_id, "topics": topics, "publishers": self.published_by,
                "signed_by": {sender: dict(sorted(counts.items())) for sender, counts in sorted(self.signed_by.items())}}


class ClockSyncThread(threading.Thread):
    """Re-estimates clock offsets every few seconds, keeping each process's best reading."""

    def __init__(self, ctx):
        super().__init__(name="clock-sync", daemon=True)
        self.ctx = ctx
        self.offsets: dict[str, clock_sync.ClockOffset] = {}
        # Only readings signed under the run's key (bench/bus/presence.py): a forged reply cannot
        # move a process's clock, and so no latency of the report.
        self.query = PresenceQuery(ctx.session, ctx.run_id, ctx.data_key)

    def run(self) -> None:
        early_until = time.monotonic() + CLOCK_SYNC_EARLY_FOR_S
        while not self.ctx.stop.wait(CLOCK_SYNC_EARLY_PERIOD_S if time.monotonic() < early_until
                                     else CLOCK_SYNC_PERIOD_S):
            try:
                self.offsets = clock_sync.estimate_offsets(self.query, rounds=3, known=self.offsets)
            except Exception as exc:   # a closed session at shutdown is not worth a crash
                self.ctx.log.warning("clock sync failed: %s", exc)
                return
        if not self.offsets:
            # A run shorter than the first period still gets one reading of each live process.
            try:
                self.offsets = clock_sync.estimate_offsets(self.query, rounds=3)
            except Exception as exc:
                self.ctx.log.warning("clock sync failed: %s", exc)


class Recorder:
    """Subscription, spool and recording of one run; `run(ctx)` drives it until ctx.stop."""

    def __init__(self, ctx):
        self.ctx = ctx
        self.recording = Recording(ctx.run_dir / RECORDING_FILE, ctx.run_id, ctx.scenario,
                                   deployment_metadata(sys.argv))
        self.samples: queue.SimpleQueue = queue.SimpleQueue()
        self.spool = SampleSpool(ctx.run_dir)
        self.budget = RecordingBudget()
        self.arrived = 0     # samples handed over by Zenoh so far, kept or dropped (tests wait on it)
        self.closing = False    # set at the stop: what arrives later is not the run's
        key = getattr(ctx, "data_key", None)
        self.verifier = data_auth.Verifier(key) if key is not None else None
        self.subscriber = ctx.session.declare_subscriber(keys.all_topics(ctx.run_id), self._on_sample)

    def _on_sample(self, sample) -> None:
        """Zenoh's thread: the budget's verdict and a copy of the bytes, nothing more (the hot path)."""
        if self.closing:
            return
        payload = sample.payload
        key_expr = str(sample.key_expr)
        if self.budget.admit(topic_of(key_expr, self.ctx.run_id), len(payload), time.monotonic()) is None:
            self.samples.put((key_expr, payload.to_bytes(), data_auth.attachment_bytes(sample), time.time_ns()))
        self.arrived += 1

    def drain(self, timeout_s: float) -> None:
        """Spool every queued sample, waiting up to timeout_s for the first one; record the spool
        once it holds ASSEMBLE_AT_SAMPLES."""
        try:
            item = self.samples.get(timeout=timeout_s) if timeout_s > 0 else self.samples.get_nowait()
        except queue.Empty:
            return
        while True:
            self.spool.append(item)
            try:
                item = self.samples.get_nowait()
            except queue.Empty:
                break
        if len(self.spool) >= ASSEMBLE_AT_SAMPLES:
            self._assemble()

    def _assemble(self) -> None:
        """The spooled samples into the MCAP, in arrival order: MACs checked (a replay is a counter
        seen before, so the order matters), samples classified and written."""
        for key_expr, payload, attachment, received_ns in self.spool.take():
            topic = topic_of(key_expr, self.ctx.run_id)
            unauthentic = sender = None
            if self.verifier is not None and not topic.startswith(CAN_TOPIC + "/"):
                unauthentic = self.verifier.check(key_expr, payload, attachment)
                sender = data_auth.sender_of(attachment) if unauthentic is None else None
            self.recording.write(topic, payload, received_ns, unauthentic, sender)

    def finish(self) -> dict:
        """Stop taking samples, spool what is still queued, assemble and close the file, write the
        counts; the subscription is undeclared after that, so that the recording is whole even if
        Zenoh's undeclare (which waits for callbacks in flight) is slow to return."""
        self.closing = True
        self.drain(0.0)
        self._assemble()
        self.spool.close()
        self.recording.dropped = self.budget.dropped_counts()
        self.recording.close()
        counts = self.recording.counts()
        _write_json(self.ctx.run_dir / COUNTS_FILE, counts)
        self.subscriber.undeclare()
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
        for reason, counts in recorder.recording.unauthentic.items():
            ctx.unauthentic.setdefault(reason, Counter()).update(counts)
        clock.join(timeout=3.0)
        _write_json(ctx.run_dir / OFFSETS_FILE, {p: o.to_dict() for p, o in sorted(clock.offsets.items())})
    ctx.log.info("recorded %s; malformed %s", dict(recorder.recording.recorded), dict(recorder.recording.malformed))
    return 0


def _write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=2, sort_keys=True))
