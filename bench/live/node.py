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

The parts: the live view's own topics and schemas (channels.py), what each sample becomes there
(forwarding.py), the fault-injection service (fault_service.py).

reads:  truth/attitude or truth, event/* always; the other topics while watched
writes: nothing on the bus; control/fault queries (the service)
"""
from __future__ import annotations

import json
import queue
import threading
import time
from collections import Counter
from pathlib import Path
from urllib.parse import quote

from bench.bus import data_auth, keys
from bench.bus.schemas import (
    AttitudeEstimate, AttitudeTruth, BusEvent, DeadlineEvent, DipoleCommand, FaultWindow, GyroSample,
    MagnetometerSample, MtqApplied, RangeBearing, RelativePosition, StarTrackerSample,
    ThrustCommand, TranslationEstimate, TruthState,
)
from bench.bus.session import LOOPBACK_HOST, check_port_free, loopback_endpoint
from bench.live.channels import (
    CRITERIA_SCHEMA, CRITERIA_TOPIC, ERROR_SCHEMA, ERROR_TOPIC, ESTIMATE_ERROR_SCHEMA, ESTIMATE_ERROR_TOPIC,
    EVENTS_TOPIC, REPLY_SCHEMA, REQUEST_SCHEMA, STATUS_SCHEMA, STATUS_TOPIC, TF_TOPIC, json_schema,
)
from bench.live.criteria import LiveMetrics
from bench.live.fault_service import SERVICE_NAME, FaultService, service_token
from bench.live.forwarding import CAN_STEP_TOPICS, Forwarding

LIVE_FILE = "live.json"          # in the run directory: what this node forwarded, dropped and refused
QUEUE_SAMPLES = 4096             # Zenoh -> the forwarding thread; full: dropped and counted
STATUS_PERIOD_S = 1.0            # live/status (wall clock)
CRITERIA_PERIOD_S = 0.25         # live/criteria at most this often (wall clock)
EVENT_WILDCARD = "event/*"

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


# --- what the launcher needs (imported there: keep this module's imports light) -------------------
# (and service_token, from fault_service.py)
def check_live_port(port: int) -> None:
    """SessionConfigError (exit 2, nothing started) if the live view's port on loopback is taken."""
    check_port_free(loopback_endpoint(port))


def live_urls(port: int) -> tuple[str, str]:
    """The WebSocket URL to open in Foxglove, and the Foxglove app URL that opens it."""
    ws = f"ws://{LOOPBACK_HOST}:{port}"
    return ws, f"https://app.foxglove.dev/?ds=foxglove-websocket&ds.url={quote(ws, safe='')}"


def topics_for(scenario) -> dict:
    """Bench topic -> its message type, for the scenario's loop."""
    kinds = dict(ATTITUDE_TOPICS if scenario.kind == "attitude" else RENDEZVOUS_TOPICS)
    if scenario.can is None:
        kinds.pop(keys.ACTUATOR_MTQ, None)
    return {**kinds, **EVENT_TOPICS}


class LiveView(Forwarding, FaultService):
    """The server, its channels, the Zenoh subscriptions they need, and the thread that forwards
    (what it forwards: Forwarding; the service: FaultService)."""

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
            can_schema = json_schema(CAN_FRAME_SCHEMA_NAME, CAN_FRAME_SCHEMA)
            names = [scenario.can.flight_channel] + ([] if self.can_step else [scenario.can.board_channel])
            for name in names:
                self.can_channels[f"can/{name}"] = foxglove.Channel(f"can/{name}", schema=can_schema,
                                                                    message_encoding="json", context=self.context)
        self._can_frame_json = None
        self.tf = FrameTransformChannel(TF_TOPIC, context=self.context)
        self.log = LogChannel(EVENTS_TOPIC, context=self.context)
        attitude = scenario.kind == "attitude"
        self.derived = {CRITERIA_TOPIC: foxglove.Channel(CRITERIA_TOPIC, schema=json_schema("bench.LiveCriteria", CRITERIA_SCHEMA),
                                                         message_encoding="json", context=self.context),
                        STATUS_TOPIC: foxglove.Channel(STATUS_TOPIC, schema=json_schema("bench.LiveStatus", STATUS_SCHEMA),
                                                       message_encoding="json", context=self.context)}
        if attitude:
            self.derived[ERROR_TOPIC] = foxglove.Channel(ERROR_TOPIC, schema=json_schema("bench.LiveAttitudeError", ERROR_SCHEMA),
                                                         message_encoding="json", context=self.context)
            self.derived[ESTIMATE_ERROR_TOPIC] = foxglove.Channel(
                ESTIMATE_ERROR_TOPIC, schema=json_schema("bench.LiveEstimateError", ESTIMATE_ERROR_SCHEMA),
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
                request=foxglove.MessageSchema(encoding="json", schema=json_schema("bench.InjectFaultRequest", REQUEST_SCHEMA)),
                response=foxglove.MessageSchema(encoding="json", schema=json_schema("bench.InjectFaultReply", REPLY_SCHEMA))),
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
