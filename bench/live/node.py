"""Node "live" (`bench run SCENARIO --live [PORT]`): the run as it happens, in Foxglove (issue 48).

A Foxglove WebSocket server (foxglove-sdk) on 127.0.0.1:PORT, in its own process on the project's
session factory, reading the run's topics as the recorder does and checking every tag as every node
does (a sample without a valid, fresh MAC under the run's key is dropped and counted, never shown).
Its channels carry the MCAP's schemas, so the recording's layout and the live one read the same paths:

| Foxglove topic                 | schema                          | from                                      |
|--------------------------------|---------------------------------|-------------------------------------------|
| truth/attitude, estimate/attitude, sense/gyro, sense/mag, sense/star, command/dipole, command/applied, actuator/mtq, event/deadline, event/can, event/fault (attitude); truth, estimate/translation, sense/relpos, sense/range_bearing, command/thrust, command/applied (rendezvous) | the bench's JSON schema (the recorder's) | the topic itself, the payload as published |
| can/<flight>, can/<board>      | bench.CanFrame (the recorder's) | CAN frames decoded with the run's DBC (lock-step on simulated time: canstep/*) |
| /tf                            | foxglove.FrameTransform         | truth/attitude: inertial -> body, inertial -> target; estimate/attitude: inertial -> body_estimate; truth (rendezvous): lvlh -> chaser |
| live/attitude_error            | bench.LiveAttitudeError         | truth/attitude: pointing error to the flight side's target, body rate |
| live/estimate_error            | bench.LiveEstimateError         | estimate/attitude against truth/attitude of the same step |
| /events                        | foxglove.Log                    | event/can (driver and FDIR detections), event/deadline (misses), event/fault (fault windows), injections through the service |
| live/criteria                  | bench.LiveCriteria              | the scenario's criteria as they stand (bench/live/criteria.py) |
| live/status                    | bench.LiveStatus                | what this node forwarded, dropped and refused |

Time: every message's log time is the run's simulated time (its header's, or the newest step's for
what has none: CAN frames, the board's reports, the driver's events, as the recorder does), and the
server's time (`Capability.Time`) is the newest step's simulated time.

No cost when nobody watches: the node subscribes on Zenoh only to what an open channel needs. Always:
the truth and `event/*` (a step's few hundred bytes, for the criteria as they stand); the rest (CAN
frames, sensors, estimates, commands, the board's reports) only while a client is subscribed to a
channel made from it, so publishers send this process nothing more when nobody watches.

Never blocking the loop: Zenoh hands each sample to a callback that only queues it (bounded,
QUEUE_SAMPLES); a full queue drops the sample and counts it (`live/status`, live.json). A reliable
publisher with congestion control BLOCK waits for a subscriber whose callback blocks, so nothing
else happens there. A lock-step run is streamed at its own pace, never throttled: every message
is forwarded as it comes, and a client that reads slower than the run goes loses the oldest of
its backlog (the SDK's per-client queue, `message_backlog_size`, drops the oldest) rather than
slow anything down.

Fault injection: the service `/inject_fault` (JSON request: the `[[can.faults]]` fields, `kind`,
optional `after_s`, `axis` "x"/"y"/"z", and the run's `token` the terminal prints) is forwarded to
canbus on the command channel, signed under the run's key as "live" (bench/bus/fault_command.py);
canbus decides, as for `bench inject`. A call without the token is refused here and counted.

reads:  truth/attitude or truth, event/* always; the other topics while watched
writes: nothing on the bus; control/fault queries (the service)
"""
from __future__ import annotations

import hashlib
import hmac
import json
import math
import queue
import threading
import time
from collections import Counter
from pathlib import Path
from urllib.parse import quote

import msgspec
import numpy as np

from bench.bus import data_auth, keys
from bench.bus import fault_command as fc
from bench.bus.schemas import (
    AttitudeEstimate, AttitudeTruth, BusEvent, DeadlineEvent, DipoleCommand, FaultWindow, GyroSample,
    MagnetometerSample, MalformedMessage, MtqApplied, RangeBearing, RelativePosition, StarTrackerSample,
    ThrustCommand, TranslationEstimate, TruthState, decode,
)
from bench.bus.session import LOOPBACK_HOST, check_port_free, loopback_endpoint
from bench.live.criteria import LiveMetrics

LIVE_FILE = "live.json"          # in the run directory: what this node forwarded, dropped and refused
QUEUE_SAMPLES = 4096             # Zenoh -> the forwarding thread; full: dropped and counted
STATUS_PERIOD_S = 1.0            # live/status (wall clock)
CRITERIA_PERIOD_S = 0.25         # live/criteria at most this often (wall clock)
SERVICE_NAME = "/inject_fault"
TOKEN_LABEL = b"orbit-hil-bench live fault service v1"
TF_TOPIC, EVENTS_TOPIC, CRITERIA_TOPIC, STATUS_TOPIC = "/tf", "/events", "live/criteria", "live/status"
ERROR_TOPIC, ESTIMATE_ERROR_TOPIC = "live/attitude_error", "live/estimate_error"
EVENT_WILDCARD = "event/*"
CAN_STEP_TOPICS = (keys.CAN_STEP_FLIGHT, keys.CAN_STEP_BUS)
# Driver events that say the bus is well again (bench.studies.fault_bus.BENIGN_EVENTS): info, not warnings.
BENIGN_EVENTS = frozenset({"heartbeat_resumed", "board_error_reset", "error_active", "bus_restarted", "host_overrun"})
AXES = {"x": 0, "y": 1, "z": 2}

ATTITUDE_TOPICS = {
    keys.TRUTH_ATTITUDE: AttitudeTruth, keys.ESTIMATE_ATTITUDE: AttitudeEstimate, keys.SENSE_GYRO: GyroSample,
    keys.SENSE_MAG: MagnetometerSample, keys.SENSE_STAR: StarTrackerSample, keys.COMMAND_DIPOLE: DipoleCommand,
    keys.COMMAND_APPLIED: DipoleCommand, keys.ACTUATOR_MTQ: MtqApplied,
}
RENDEZVOUS_TOPICS = {
    keys.TRUTH: TruthState, keys.ESTIMATE_TRANSLATION: TranslationEstimate, keys.SENSE_RELPOS: RelativePosition,
    keys.SENSE_RANGE_BEARING: RangeBearing, keys.COMMAND_THRUST: ThrustCommand, keys.COMMAND_APPLIED: ThrustCommand,
    keys.ACTUATOR_MTQ: MtqApplied,
}
EVENT_TOPICS = {keys.EVENT_DEADLINE: DeadlineEvent, keys.EVENT_CAN: BusEvent, keys.EVENT_FAULT: FaultWindow}

_NUM = {"type": "number"}
_NUM_OR_NULL = {"type": ["number", "null"]}
_VEC = {"type": "array", "items": _NUM, "minItems": 3, "maxItems": 3}
ERROR_SCHEMA = {
    "title": "bench.LiveAttitudeError", "type": "object",
    "description": "From truth/attitude at each step: pointing error to the flight side's target and body rate",
    "properties": {"sim_time_s": _NUM, "pointing_error_deg": {**_NUM_OR_NULL, "description": "null for laws without "
                                                                             "a target (B-dot, rate damping)"},
                   "rate_dps": {**_NUM, "description": "|omega| [deg/s]"},
                   "rate_dps_xyz": {**_VEC, "description": "omega per body axis [deg/s]"}},
}
ESTIMATE_ERROR_SCHEMA = {
    "title": "bench.LiveEstimateError", "type": "object",
    "description": "estimate/attitude against truth/attitude of the same step",
    "properties": {"sim_time_s": _NUM, "attitude_error_deg": _NUM,
                   "rate_error_dps_xyz": {**_VEC, "description": "estimated minus true body rate [deg/s]"},
                   "estimated_rate_dps": _NUM, "valid": {"type": "boolean"}},
}
CRITERIA_SCHEMA = {
    "title": "bench.LiveCriteria", "type": "object",
    "description": "The scenario's criteria as they stand (bench/live/criteria.py): a figure computed live, or "
                   "judged at the end",
    "properties": {
        "sim_time_s": _NUM,
        "holds_now": {"type": ["boolean", "null"], "description": "every live criterion holds now (null: none is live)"},
        "criteria": {"type": "array", "items": {"type": "object", "properties": {
            "metric": {"type": "string"}, "bound": {"type": "string"}, "why": {"type": "string"},
            "value": {}, "state": {"type": "string", "enum": ["holds now", "does not hold now", "judged at the end"]},
            "live": {"type": "boolean"}, "passed": {"type": "boolean"}}}},
    },
}
STATUS_SCHEMA = {
    "title": "bench.LiveStatus", "type": "object",
    "description": "What the live view did: forwarded, dropped (its queue full), refused (no valid tag), malformed",
    "properties": {"sim_time_s": _NUM, "forwarded": {"type": "object"}, "dropped": {"type": "object"},
                   "unauthentic": {"type": "object"}, "malformed": {"type": "object"}, "watched": {"type": "object"},
                   "zenoh_subscriptions": {"type": "array", "items": {"type": "string"}},
                   "faults_allowed": {"type": "boolean"}, "service_calls": {"type": "object"}},
}
REQUEST_SCHEMA = {
    "title": "bench.InjectFaultRequest", "type": "object",
    "description": "A fault to inject now, as a [[can.faults]] entry (`bench faults` lists the kinds), with the run's "
                   "token the terminal printed",
    "properties": {
        "token": {"type": "string", "description": "printed by `bench run --live --allow-live-faults`"},
        "kind": {"type": "string", "description": "a [[can.faults]] name, e.g. drop, corrupt, coil_gain"},
        "duration_s": {**_NUM, "description": "simulated seconds (window faults and board_power_loss need it)"},
        "after_s": {**_NUM, "description": "simulated seconds from now to its start (default 0)"},
        "axis": {"type": "string", "enum": ["x", "y", "z"], "description": "coil faults: the body axis"},
        "frames": {"type": "array", "items": {"type": "string"}, "description": "DBC frame names (frame faults)"},
        "count": {"type": "integer"}, "every": {"type": "integer"},
        "params": {"type": "object", "description": "the kind's own parameters (`bench faults`)"},
    },
    "required": ["token", "kind"],
}
REPLY_SCHEMA = {
    "title": "bench.InjectFaultReply", "type": "object",
    "properties": {"accepted": {"type": "boolean"}, "reason": {"type": "string"}, "detail": {"type": "string"},
                   "label": {"type": "string"}, "start_sim_s": _NUM_OR_NULL, "end_sim_s": _NUM_OR_NULL,
                   "authentic": {"type": "boolean", "description": "the answer is signed by canbus under the run's key"}},
}


# --- what the launcher needs (imported there: keep this module's imports light) -------------------
def check_live_port(port: int) -> None:
    """SessionConfigError (exit 2, nothing started) if the live view's port on loopback is taken."""
    check_port_free(loopback_endpoint(port))


def live_urls(port: int) -> tuple[str, str]:
    """The WebSocket URL to open in Foxglove, and the Foxglove app URL that opens it."""
    ws = f"ws://{LOOPBACK_HOST}:{port}"
    return ws, f"https://app.foxglove.dev/?ds=foxglove-websocket&ds.url={quote(ws, safe='')}"


def service_token(key: bytes | None) -> str:
    """The token a service call must carry: from the run's key, so whoever can read bus.key (the run's
    user) or sees the terminal of `bench run` can call it, nobody else reaching the loopback port."""
    if key is None:
        return ""
    return hmac.new(key, TOKEN_LABEL, hashlib.sha256).hexdigest()[:24]


def topics_for(scenario) -> dict:
    """Bench topic -> its message type, for the scenario's loop."""
    kinds = dict(ATTITUDE_TOPICS if scenario.kind == "attitude" else RENDEZVOUS_TOPICS)
    if scenario.can is None:
        kinds.pop(keys.ACTUATOR_MTQ, None)
    return {**kinds, **EVENT_TOPICS}


def _ns(sim_s: float) -> int:
    return max(0, int(round(sim_s * 1e9))) if math.isfinite(sim_s) else 0


def _json_schema(name: str, schema: dict):
    import foxglove

    return foxglove.Schema(name=name, encoding="jsonschema", data=json.dumps(schema).encode())


class LiveView:
    """The server, its channels, the Zenoh subscriptions they need, and the thread that forwards."""

    def __init__(self, ctx, port: int):
        import foxglove
        from foxglove.channels import FrameTransformChannel, LogChannel
        from foxglove.websocket import Capability

        from bench.bus.can import protocol as can_protocol
        from bench.bus.can.sim_window import bus_on_simulated_time
        from bench.recorder import CAN_FRAME_SCHEMA, CAN_FRAME_SCHEMA_NAME, SimTimeBase, root_object_schema

        self.ctx = ctx
        self.scenario = scenario = ctx.scenario
        self.port = port
        self.prefix = keys.key(ctx.run_id, "")
        self.kinds = topics_for(scenario)
        self.sim = SimTimeBase()
        self.metrics = LiveMetrics(scenario)
        self.verifier = data_auth.Verifier(ctx.data_key) if ctx.data_key is not None else None
        self.signer = data_auth.Signer(ctx.data_key, ctx.name) if ctx.data_key is not None else None
        self.token = service_token(ctx.data_key)
        self.inbox: queue.Queue = queue.Queue(maxsize=QUEUE_SAMPLES)
        self.forwarded: Counter = Counter()
        self.dropped: Counter = Counter()
        self.service_calls: Counter = Counter()
        self.watched: Counter = Counter()          # Foxglove topic -> subscribed clients
        self._lock = threading.Lock()
        self._truth_by_seq: dict[int, AttitudeTruth] = {}
        self._estimate_by_seq: dict[int, tuple[AttitudeEstimate, int]] = {}
        self._broadcast_ns = -1
        self._criteria_due_s = 0.0
        self.criteria_now: dict | None = None
        self._status_due_s = 0.0
        self.context = foxglove.Context()
        self._fg = foxglove
        schema = lambda kind: foxglove.Schema(name=kind.__name__, encoding="jsonschema",     # noqa: E731
                                              data=json.dumps(root_object_schema(kind)).encode())
        self.channels = {topic: foxglove.Channel(topic, schema=schema(kind), message_encoding="json", context=self.context)
                         for topic, kind in self.kinds.items()}
        # The CAN channels: frames of the Zenoh transport, or (lock-step on simulated time) of the
        # step windows, decoded with the DBC as the recorder does.
        self.can_protocol = None
        self.can_channels: dict[str, object] = {}
        self.can_step = scenario.can is not None and bus_on_simulated_time(scenario)
        if scenario.can is not None:
            self.can_protocol = can_protocol.Protocol(scenario.can.node_id, scenario.can.security.profile)
            can_schema = _json_schema(CAN_FRAME_SCHEMA_NAME, CAN_FRAME_SCHEMA)
            names = [scenario.can.flight_channel] + ([] if self.can_step else [scenario.can.board_channel])
            for name in names:
                self.can_channels[f"can/{name}"] = foxglove.Channel(f"can/{name}", schema=can_schema,
                                                                    message_encoding="json", context=self.context)
        self._can_frame_json = None
        self.tf = FrameTransformChannel(TF_TOPIC, context=self.context)
        self.log = LogChannel(EVENTS_TOPIC, context=self.context)
        attitude = scenario.kind == "attitude"
        self.derived = {CRITERIA_TOPIC: foxglove.Channel(CRITERIA_TOPIC, schema=_json_schema("bench.LiveCriteria", CRITERIA_SCHEMA),
                                                         message_encoding="json", context=self.context),
                        STATUS_TOPIC: foxglove.Channel(STATUS_TOPIC, schema=_json_schema("bench.LiveStatus", STATUS_SCHEMA),
                                                       message_encoding="json", context=self.context)}
        if attitude:
            self.derived[ERROR_TOPIC] = foxglove.Channel(ERROR_TOPIC, schema=_json_schema("bench.LiveAttitudeError", ERROR_SCHEMA),
                                                         message_encoding="json", context=self.context)
            self.derived[ESTIMATE_ERROR_TOPIC] = foxglove.Channel(
                ESTIMATE_ERROR_TOPIC, schema=_json_schema("bench.LiveEstimateError", ESTIMATE_ERROR_SCHEMA),
                message_encoding="json", context=self.context)
        # What each Foxglove topic needs on Zenoh (bench topics under bench/<run_id>/).
        truth = keys.TRUTH_ATTITUDE if attitude else keys.TRUTH
        estimate = keys.ESTIMATE_ATTITUDE if attitude else keys.ESTIMATE_TRANSLATION
        self.needs: dict[str, tuple[str, ...]] = {topic: (topic,) for topic in self.kinds if topic not in EVENT_TOPICS}
        for topic in EVENT_TOPICS:
            self.needs[topic] = (EVENT_WILDCARD,)
        for topic in self.can_channels:
            self.needs[topic] = CAN_STEP_TOPICS if self.can_step else (topic,)
        self.needs[TF_TOPIC] = (truth, estimate)
        self.needs[ERROR_TOPIC] = (truth,)
        self.needs[ESTIMATE_ERROR_TOPIC] = (truth, estimate)
        self.needs[EVENTS_TOPIC] = (EVENT_WILDCARD,)
        self.always = (truth, EVENT_WILDCARD)      # the criteria as they stand need these from the start
        self._subscribers: dict[str, object] = {}
        self._demand: Counter = Counter()
        for source in self.always:
            self._need(source, +1)
        service = foxglove.Service(
            name=SERVICE_NAME,
            schema=foxglove.ServiceSchema(
                name="bench.InjectFault",
                request=foxglove.MessageSchema(encoding="json", schema=_json_schema("bench.InjectFaultRequest", REQUEST_SCHEMA)),
                response=foxglove.MessageSchema(encoding="json", schema=_json_schema("bench.InjectFaultReply", REPLY_SCHEMA))),
            handler=self._service)
        self.server = foxglove.start_server(
            name=f"orbit-hil-bench {ctx.run_id}", host=LOOPBACK_HOST, port=port,
            capabilities=[Capability.Time, Capability.Services], server_listener=_Listener(self),
            supported_encodings=["json"], services=[service], context=self.context)
        self._worker = threading.Thread(target=self._work, name="live-forward", daemon=True)
        self._worker.start()

    # --- Zenoh subscriptions on demand -------------------------------------------------------
    def watch(self, topic: str, delta: int) -> None:
        """A client subscribed (+1) to, or left (-1), a Foxglove topic (the SDK's thread)."""
        with self._lock:
            self.watched[topic] = max(0, self.watched[topic] + delta)
            for source in self.needs.get(topic, ()):
                self._need(source, delta)

    def _need(self, source: str, delta: int) -> None:
        self._demand[source] = max(0, self._demand[source] + delta)
        if self._demand[source] > 0 and source not in self._subscribers:
            self._subscribers[source] = self.ctx.session.declare_subscriber(keys.key(self.ctx.run_id, source),
                                                                            self._on_sample)
        elif self._demand[source] == 0 and source in self._subscribers:
            try:
                self._subscribers.pop(source).undeclare()
            except Exception:   # noqa: BLE001 - the session is closing
                pass

    def _on_sample(self, sample) -> None:
        """Zenoh's thread: queue it and return at once (a blocked callback would hold up the publisher)."""
        key_expr = str(sample.key_expr)
        try:
            self.inbox.put_nowait((key_expr, sample.payload.to_bytes(), data_auth.attachment_bytes(sample)))
        except queue.Full:
            with self._lock:
                self.dropped[key_expr[len(self.prefix):]] += 1

    # --- forwarding -----------------------------------------------------------------------
    def _work(self) -> None:
        while not self.ctx.stop.is_set():
            try:
                item = self.inbox.get(timeout=0.1)
            except queue.Empty:
                self._tick()
                continue
            for _ in range(256):       # a batch, then the clock and the criteria
                try:
                    self._handle(*item)
                except Exception as exc:   # noqa: BLE001 - one bad sample must not end the view
                    self.ctx.log.warning("live view: a sample on %s not shown: %s", item[0], exc)
                try:
                    item = self.inbox.get_nowait()
                except queue.Empty:
                    break
            self._tick()

    def _handle(self, key_expr: str, payload: bytes, attachment: bytes | None) -> None:
        topic = key_expr[len(self.prefix):] if key_expr.startswith(self.prefix) else key_expr
        if topic in self.can_channels and not self.can_step:
            self._can_frame(topic, payload)
            return
        if self.verifier is not None:
            reason = self.verifier.check(key_expr, payload, attachment)
            if reason is not None:
                self.ctx.unauthentic.setdefault(reason, Counter())[topic] += 1
                return
        if topic in CAN_STEP_TOPICS:
            self._can_window(topic, payload)
            return
        kind = self.kinds.get(topic)
        try:
            if kind is None:
                raise MalformedMessage(f"no message is expected on {topic}")
            message = decode(payload, kind)
        except MalformedMessage:
            self.ctx.malformed[topic] += 1
            return
        if message.header.run_id != self.ctx.run_id:
            self.ctx.malformed[topic] += 1
            return
        log_ns = self.sim.of_message(message)
        channel = self.channels.get(topic)
        if channel is not None and channel.has_sinks():
            channel.log(payload, log_time=log_ns)
            self.forwarded[topic] += 1
        if isinstance(message, AttitudeTruth):
            self._attitude_truth(message, log_ns)
        elif isinstance(message, AttitudeEstimate):
            self._attitude_estimate(message, log_ns)
        elif isinstance(message, TruthState):
            self.metrics.on_translation_truth(message.state_m_mps)
            self._transform(log_ns, "lvlh", "chaser", message.state_m_mps[:3], [1.0, 0.0, 0.0, 0.0])
        elif isinstance(message, BusEvent):
            self.metrics.on_bus_event(message.kind, message.latency_s)
            level = "Info" if message.kind in BENIGN_EVENTS else "Warning"
            self._log(log_ns, level, message.source, f"{message.kind} after {message.latency_s * 1e3:.1f} ms"
                                                     f"{' (' + message.frame + ')' if message.frame else ''}"
                                                     f"{': ' + message.detail if message.detail else ''}")
        elif isinstance(message, DeadlineEvent) and message.missed:
            self._log(log_ns, "Warning", "deadline",
                      f"{message.process} missed its deadline: {message.cycle_time_s * 1e3:.2f} ms for a "
                      f"{message.budget_s * 1e3:.2f} ms budget ({message.consecutive_misses} in a row"
                      f"{', fallback ' + message.fallback if message.fallback else ''})")
        elif isinstance(message, FaultWindow):
            spec = message.fault
            until = f" to {message.end_sim_s:.3f} s" if message.end_sim_s is not None else ""
            origin = f"injected live by {message.requested_by!r}" if message.live else "scripted"
            self._log(log_ns, "Warning" if message.live else "Info", "fault",
                      f"fault {message.label} ({origin}): {spec.name} from {spec.start_s:.3f} s{until} (simulated)"
                      f"{' ' + json.dumps(spec.params) if spec.params else ''}")

    def _attitude_truth(self, message: AttitudeTruth, log_ns: int) -> None:
        t_s = message.header.sim_time_s
        figures = self.metrics.on_attitude_truth(t_s, message.q_wxyz, message.omega_radps)
        self._truth_by_seq[message.header.seq] = message
        if len(self._truth_by_seq) > 64:
            self._truth_by_seq.pop(next(iter(self._truth_by_seq)))
        self._transform(log_ns, "inertial", "body", [0.0, 0.0, 0.0], message.q_wxyz)
        target = self.metrics.target_q(t_s)
        if target is not None:
            self._transform(log_ns, "inertial", "target", [0.0, 0.0, 0.0], target)
        waiting = self._estimate_by_seq.pop(message.header.seq, None)
        if waiting is not None:
            self._attitude_estimate(*waiting)
        channel = self.derived.get(ERROR_TOPIC)
        if channel is not None and channel.has_sinks():
            channel.log({"sim_time_s": t_s, "pointing_error_deg": figures["pointing_error_deg"],
                         "rate_dps": figures["rate_dps"], "rate_dps_xyz": np.degrees(message.omega_radps).tolist()},
                        log_time=log_ns)
            self.forwarded[ERROR_TOPIC] += 1

    def _attitude_estimate(self, message: AttitudeEstimate, log_ns: int) -> None:
        self._transform(log_ns, "inertial", "body_estimate", [0.0, 0.0, 0.0], message.q_wxyz)
        truth = self._truth_by_seq.get(message.header.seq)
        if truth is None:      # the estimate of a step can come before its truth: compared when the truth comes
            self._estimate_by_seq[message.header.seq] = (message, log_ns)
            if len(self._estimate_by_seq) > 64:
                self._estimate_by_seq.pop(next(iter(self._estimate_by_seq)))
            return
        channel = self.derived.get(ESTIMATE_ERROR_TOPIC)
        if channel is None or not channel.has_sinks():
            return
        from bench.gnc import quaternion as qt

        error = math.degrees(qt.angle_between_rad(np.asarray(truth.q_wxyz, float), np.asarray(message.q_wxyz, float)))
        rate_error = np.degrees(np.subtract(message.omega_radps, truth.omega_radps)).tolist()
        channel.log({"sim_time_s": message.header.sim_time_s, "attitude_error_deg": error,
                     "rate_error_dps_xyz": rate_error, "valid": message.valid,
                     "estimated_rate_dps": math.degrees(float(np.linalg.norm(message.omega_radps)))}, log_time=log_ns)
        self.forwarded[ESTIMATE_ERROR_TOPIC] += 1

    def _transform(self, log_ns: int, parent: str, child: str, translation, q_wxyz) -> None:
        if not self.tf.has_sinks():
            return
        from foxglove.messages import FrameTransform, Quaternion, Timestamp, Vector3

        w, x, y, z = (float(v) for v in q_wxyz)
        self.tf.log(FrameTransform(timestamp=Timestamp(log_ns // 1_000_000_000, log_ns % 1_000_000_000),
                                   parent_frame_id=parent, child_frame_id=child,
                                   translation=Vector3(x=float(translation[0]), y=float(translation[1]), z=float(translation[2])),
                                   rotation=Quaternion(x=x, y=y, z=z, w=w)), log_time=log_ns)
        self.forwarded[TF_TOPIC] += 1

    def _log(self, log_ns: int, level: str, name: str, text: str) -> None:
        if not self.log.has_sinks():
            return
        from foxglove.messages import Log, LogLevel, Timestamp

        self.log.log(Log(timestamp=Timestamp(log_ns // 1_000_000_000, log_ns % 1_000_000_000),
                         level=getattr(LogLevel, level), message=text, name=name), log_time=log_ns)
        self.forwarded[EVENTS_TOPIC] += 1

    def _frame_json(self):
        if self._can_frame_json is None:
            from bench.recorder import can_frame_json

            self._can_frame_json = can_frame_json
        return self._can_frame_json

    def _can_frame(self, topic: str, payload: bytes) -> None:
        from bench.bus.can import zenoh_wire

        channel = self.can_channels[topic]
        if not channel.has_sinks():
            return
        name = topic.rpartition("/")[2]
        try:
            msg, sender_id, sequence = zenoh_wire.decode(payload, name)
        except zenoh_wire.MalformedFrame:
            self.ctx.malformed[topic] += 1
            return
        log_ns = self.sim.of_unstepped()
        body = self._frame_json()(self.can_protocol, msg, name, sender_id, sequence, log_ns / 1e9)
        channel.log(json.dumps(body).encode(), log_time=log_ns)
        self.forwarded[topic] += 1

    def _can_window(self, topic: str, payload: bytes) -> None:
        """Lock-step on simulated time: a step's frames, each at its own simulated time."""
        from bench.bus.can.sim_window import CanWindow, mission_s, to_can_message

        try:
            window = decode(payload, CanWindow)
        except MalformedMessage:
            self.ctx.malformed[topic] += 1
            return
        self.sim.of_message(window)
        name = self.scenario.can.flight_channel
        channel = self.can_channels.get(f"can/{name}")
        if channel is None or not channel.has_sinks():
            return
        sender = 0 if topic == keys.CAN_STEP_FLIGHT else 1      # the driver's frames, or those it heard
        for i, frame in enumerate(window.frames):
            t_s = mission_s(frame.t_ns)
            body = self._frame_json()(self.can_protocol, to_can_message(frame), name, sender, i, t_s)
            channel.log(json.dumps(body).encode(), log_time=_ns(t_s))
            self.forwarded[f"can/{name}"] += 1

    # --- the clock, the criteria, the status ------------------------------------------------
    def _tick(self) -> None:
        newest = self.sim.newest_step_ns
        if newest != self._broadcast_ns:
            self.server.broadcast_time(newest)
            self._broadcast_ns = newest
        now = time.monotonic()
        if now >= self._criteria_due_s:
            self._criteria_due_s = now + CRITERIA_PERIOD_S
            self.publish_criteria()
        if now >= self._status_due_s:
            self._status_due_s = now + STATUS_PERIOD_S
            self.publish_status()

    def publish_criteria(self) -> None:
        channel = self.derived[CRITERIA_TOPIC]
        judged = self.metrics.judged()
        live = [c for c in judged if c["live"]]
        body = {"sim_time_s": self.sim.newest_step_ns / 1e9, "holds_now": all(c["passed"] for c in live) if live else None,
                "criteria": judged}
        if channel.has_sinks():     # every period, changed or not: a client that came late sees them at once
            channel.log(body, log_time=self.sim.newest_step_ns)
            self.forwarded[CRITERIA_TOPIC] += 1
        self.criteria_now = body

    def status(self) -> dict:
        with self._lock:
            dropped = dict(self.dropped)
            watched = {t: n for t, n in self.watched.items() if n}
            subscriptions = sorted(self._subscribers)
        return {"sim_time_s": self.sim.newest_step_ns / 1e9, "forwarded": dict(self.forwarded), "dropped": dropped,
                "unauthentic": {r: dict(c) for r, c in self.ctx.unauthentic.items()},
                "malformed": dict(self.ctx.malformed), "watched": watched, "zenoh_subscriptions": subscriptions,
                "faults_allowed": bool(self.ctx.allow_live_faults), "service_calls": dict(self.service_calls)}

    def publish_status(self) -> None:
        channel = self.derived[STATUS_TOPIC]
        if channel.has_sinks():
            channel.log(self.status(), log_time=self.sim.newest_step_ns)
            self.forwarded[STATUS_TOPIC] += 1

    # --- the fault-injection service --------------------------------------------------------
    def _service(self, request) -> bytes:
        """`/inject_fault` (the SDK's thread): checked here for the token, decided by canbus."""
        reply = self.inject(request.payload)
        return json.dumps(reply).encode()

    def inject(self, payload: bytes) -> dict:
        try:
            data = json.loads(payload)
            if not isinstance(data, dict):
                raise ValueError("the request is a JSON object")
        except ValueError as exc:
            self.service_calls[fc.INVALID] += 1
            return {"accepted": False, "reason": fc.INVALID, "detail": f"not a JSON object: {exc}", "authentic": False}
        token = data.pop("token", None)
        if self.token and not (isinstance(token, str) and hmac.compare_digest(token, self.token)):
            self.service_calls[fc.FORGED] += 1
            self.ctx.unauthentic.setdefault(fc.FORGED, Counter())["service" + SERVICE_NAME] += 1
            self.ctx.log.warning("fault-injection call without the run's token refused (%d so far)",
                                 self.service_calls[fc.FORGED])
            self._log(self.sim.newest_step_ns, "Error", "injector", "a fault-injection call without the run's token: refused")
            return {"accepted": False, "reason": fc.FORGED, "detail": "no valid token (the one `bench run` printed)",
                    "authentic": False}
        fields = {}
        try:
            kind = data.pop("kind")
            axis = data.pop("axis", None)
            params = dict(data.pop("params", None) or {})
            if axis is not None:
                if axis not in AXES:
                    raise ValueError(f"axis must be x, y or z, not {axis!r}")
                params["axis"] = AXES[axis]
            for name in ("duration_s", "after_s", "frames", "count", "every"):
                if name in data:
                    fields[name] = data.pop(name)
            if data:
                raise ValueError(f"unknown field(s): {', '.join(sorted(data))}")
            request = msgspec.convert({"run_id": self.ctx.run_id, "kind": kind, "nonce": fc.new_request("x", "x").nonce,
                                       "params": params, **fields}, fc.FaultRequest)
        except (KeyError, ValueError, TypeError, msgspec.ValidationError) as exc:
            self.service_calls[fc.INVALID] += 1
            return {"accepted": False, "reason": fc.INVALID, "detail": str(exc), "authentic": False}
        answer, authentic = fc.request_fault(self.ctx.session, request, self.ctx.data_key, self.ctx.name,
                                             signer=self.signer)
        if answer is None:
            self.service_calls["unanswered"] += 1
            return {"accepted": False, "reason": "unanswered", "detail": "no canbus answered (a run without a CAN bus "
                                                                         "has no fault injector)", "authentic": False}
        self.service_calls["accepted" if answer.accepted and authentic else answer.reason or "refused"] += 1
        if not answer.accepted:
            self._log(self.sim.newest_step_ns, "Error", "injector",
                      f"fault {request.kind} refused by canbus ({answer.reason}): {answer.detail}")
        return {**msgspec.to_builtins(answer), "authentic": authentic}

    # --- the end ------------------------------------------------------------------------------
    def close(self) -> dict:
        self._worker.join(timeout=2.0)
        summary = self.status()
        try:
            self.server.stop()
        except Exception:   # noqa: BLE001 - stopping anyway
            pass
        return summary


class _Listener:
    """The SDK's server listener: which channels the clients watch."""

    def __init__(self, view: LiveView):
        self.view = view

    def on_subscribe(self, client, channel) -> None:
        self.view.watch(channel.topic, +1)

    def on_unsubscribe(self, client, channel) -> None:
        self.view.watch(channel.topic, -1)


def run(ctx) -> int:
    """Node entry point: serve until the run stops, then write live.json."""
    port = ctx.live_port
    if port is None:
        ctx.log.error("node live needs --live-port PORT (`bench run SCENARIO --live [PORT]`)")
        return 2
    # No lower priority (os.nice) for the forwarding thread: it shares the GIL with Zenoh's receive
    # threads, and a thread the scheduler starves while it holds the GIL would stall the callback
    # that must never wait (seen once with the view at nice 10: a lock-step run stalled 10 s at load 30).
    view = LiveView(ctx, port)
    ws_url, app_url = live_urls(view.server.port)
    ctx.log.info("live view on %s (%s); fault injection %s", ws_url, app_url,
                 "allowed" if ctx.allow_live_faults else "refused (no --allow-live-faults)")
    ctx.declare_ready([])
    try:
        while not ctx.stop.wait(0.2):
            pass
    finally:
        view.publish_criteria()
        summary = view.close()
        summary["criteria_at_end"] = view.criteria_now
        (Path(ctx.run_dir) / LIVE_FILE).write_text(json.dumps(summary, indent=1))
        ctx.log.info("live view: forwarded %s, dropped %s", summary["forwarded"], summary["dropped"])
    return 0
