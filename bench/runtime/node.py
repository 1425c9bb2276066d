"""What every bench process has: its Zenoh session, its scenario, counters, and a clean stop.

A node is a module with `run(ctx: NodeContext) -> int`, registered in NODES. `bench node NAME`
builds the context and calls it; the launcher starts each node that way as its own OS process.

Messages arrive on Zenoh's threads; `subscribe` decodes and validates them there and hands typed
messages to the node's queue, so a node's logic runs on one thread and a malformed payload is
counted and logged where it arrives, never raised into the node. What no node of the loop waits for
(the plant's step report, applied commands, the sensors the estimator does not read) is published
with `publish_later` and goes out at the node's `publish_pending`, behind the next message the loop
waits on: off the loop's hot path. With the run's data key
(bench/bus/data_auth.py) every published message carries a MAC in its attachment (`_tag`), and a
received one without a valid, fresh MAC is dropped and counted before it is decoded (`_refused`).
Liveliness, readiness and clock readings are authenticated the same way: a node answers presence
queries on `presence/<name>` under the run's key (bench/bus/presence.py), and what it learns of its
peers comes only from such answers.
"""
from __future__ import annotations

import dataclasses
import faulthandler
import logging
import queue
import signal
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import zenoh

from bench.bus import data_auth, keys
from bench.bus.presence import PresenceQuery, PresenceResponder, PresenceWatcher
from bench.bus.certs import check_identity, identity_files
from bench.bus.deployment import DeploymentError, load_deployment
from bench.bus.schemas import MalformedMessage, Message, ProcessStats, decode, encode, header
from bench.bus.session import SessionOptions, open_session
from bench.runtime.hop_trace import HopTrace, TracedQueue, from_environment as hop_trace_from_environment
from bench.runtime.ownership import die_with_launcher
from bench.runtime.priority import node_realtime_priority, set_realtime_priority
from bench.runtime.time_model import TimeModel
from bench.runtime.reports import SIGNED_TYPES, key_from_environment, sign
from bench.scenario import Scenario

# How often a node waiting for a message looks at its stop flag: a run's end waits for the slowest
# node of each stop stage to see it (0.2 s here made every `bench run` 0.1 s longer on average).
STOP_POLL_S = 0.02
# A node still stopping this long after SIGTERM writes every thread's stack to its log.
STOP_STACKS_AFTER_S = 4.0
# ProcessStats' name for the presence answers a node refused (bench/bus/presence.py).
PRESENCE_TOPIC = "presence"

# Node name -> module with run(ctx). Other parts add theirs (the magnetorquer board, the recorder).
NODES: dict[str, str] = {
    "plant": "bench.plant.node",
    "estimator": "bench.estimator.node",
    "controller": "bench.controller.node",
    "recorder": "bench.recorder",
    "mtq": "bench.bus.can.nodes",       # magnetorquer board
    "canbus": "bench.bus.can.nodes",    # CAN bus model and fault injector
    "planner": "bench.planner.node",    # MILQR attitude plans (issue 12)
    "live": "bench.live.node",          # `bench run --live`: the Foxglove WebSocket server (issue 48)
}


@dataclass
class NodeContext:
    name: str
    run_id: str
    scenario: Scenario
    session: zenoh.Session
    run_dir: Path
    log: logging.Logger
    stop: threading.Event = field(default_factory=threading.Event)
    peers: list[str] = field(default_factory=list)   # nodes whose ready token this one awaits
    lost_peers: list[str] = field(default_factory=list)    # every loss seen (log, tests)
    # Peers silent right now (no authentic presence answer for a lease), with the monotonic time
    # their lease ran out. A peer that answers again (a slow peer, starved past its lease) clears it.
    lost_since_s: dict[str, float] = field(default_factory=dict)
    published: Counter = field(default_factory=Counter)
    malformed: Counter = field(default_factory=Counter)
    _publishers: dict = field(default_factory=dict)
    _later: list = field(default_factory=list)       # (topic, message) for publish_later
    _keepalive: list = field(default_factory=list)
    # The secret the launcher handed this process: its reports to the launcher (ProcessStats, the
    # plant's StepDone) are signed with it (bench/runtime/reports.py). None: started by hand.
    report_key: bytes | None = None
    # The run's data-topic key (bench/bus/data_auth.py): what this node publishes is signed with
    # it, and what it receives is taken only with a valid, fresh MAC. None: neither (no key found).
    data_key: bytes | None = None
    # Messages dropped for their MAC: reason (forged, replayed) -> topic -> count (ProcessStats).
    unauthentic: dict = field(default_factory=dict)
    # The SCHED_FIFO priority this process runs at (bench/runtime/priority.py); 0: the default scheduler.
    realtime_priority: int = 0
    _signer: data_auth.Signer | None = None
    _presence: PresenceResponder | None = None       # this node's answer (declare_alive)
    _presence_query: PresenceQuery | None = None     # its questions (wait_for_ready, recorder's clocks)
    _watcher: PresenceWatcher | None = None          # its peers (watch_peers)
    # `bench node --break trust-inputs`: take every input without checking its tag or counter. Only
    # to show that `bench contract check` fails such a node (it sends forged inputs); never in a run.
    trust_inputs: bool = False
    # `bench node mtq --break MODE` (bench/bus/can/board_breaks.py): the board broken on purpose, for
    # `bench contract check board`'s self-test only.
    breaks: tuple[str, ...] = ()
    # Live operation (issue 48): the run was started with --allow-live-faults (canbus takes faults
    # from the command channel, the board live hardware faults), and the live view's WebSocket port.
    allow_live_faults: bool = False
    live_port: int | None = None
    # benchmarks/bench_hop_trace.py: each message's stamps through publish, Zenoh and the hand-off
    # (bench/runtime/hop_trace.py); None, the default: nothing is stamped.
    hop_trace: HopTrace | None = field(default_factory=hop_trace_from_environment)

    @property
    def time_model(self) -> TimeModel:
        """What the run's time model asks of this node (bench/runtime/time_model.py)."""
        return TimeModel.of(self.scenario)

    # --- publishing -----------------------------------------------------------------------
    def publish(self, topic: str, message: Message) -> None:
        pub = self._publishers.get(topic)
        if pub is None:
            pub = self.declare_publisher(topic)
        if self.report_key is not None and isinstance(message, SIGNED_TYPES):
            message = sign(message, self.report_key)
        started_ns = time.monotonic_ns()
        payload = encode(message)
        attachment = self._tag(topic, payload)
        signed_ns = time.monotonic_ns()
        pub.put(payload, attachment=attachment)
        if self.hop_trace is not None:
            self.hop_trace.published.append((topic, message.header.seq, started_ns, signed_ns, time.monotonic_ns()))
        self.published[topic] += 1

    def publish_later(self, topic: str, message: Message) -> None:
        """Keep `message` until publish_pending: for what no node of the loop waits on, so that the
        next message the loop does wait on leaves first."""
        self._later.append((topic, message))

    def publish_pending(self) -> None:
        """Publish what publish_later kept, in its order (a node's end does it too)."""
        later, self._later = self._later, []
        for topic, message in later:
            self.publish(topic, message)

    def _tag(self, topic: str, payload: bytes) -> bytes | None:
        if self.data_key is None:
            return None
        if self._signer is None:
            self._signer = data_auth.Signer(self.data_key, self.name)
        return self._signer(keys.key(self.run_id, topic), payload)

    def _refused(self, verifier: data_auth.Verifier | None, sample: zenoh.Sample, topic: str, payload: bytes) -> bool:
        """Whether a sample fails the MAC check (then it is counted and logged, never raised)."""
        if verifier is None:
            return False
        reason = verifier.check(str(sample.key_expr), payload, data_auth.attachment_bytes(sample))
        if reason is None:
            return False
        counts = self.unauthentic.setdefault(reason, Counter())
        counts[topic] += 1
        if counts[topic] <= 5 or counts[topic] % 100 == 0:
            self.log.warning("%s message #%d on %s dropped (no valid MAC under the run's key)" if reason == data_auth.FORGED
                             else "%s message #%d on %s dropped (its counter was already seen)", reason, counts[topic], topic)
        return True

    def declare_publisher(self, topic: str) -> zenoh.Publisher:
        # Reliable and blocking: in lock-step a lost sample would stall the loop, and the
        # recorder must see everything that was published.
        pub = self.session.declare_publisher(
            keys.key(self.run_id, topic),
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        self._publishers[topic] = pub
        return pub

    # --- subscribing ----------------------------------------------------------------------
    def subscribe(self, topic: str, kind: type[Message], on_message: Callable[[Message], None]) -> None:
        """Decode every sample on `topic` as `kind`; count and log the ones that are not."""
        self.subscribe_topics(topic, {topic: kind}, on_message)

    def subscribe_topics(self, key_topic: str, kinds: dict[str, type[Message]],
                         on_message: Callable[[Message], None]) -> None:
        """One subscriber on `key_topic` (a topic or a wildcard such as `sense/*`) for the topics in
        `kinds`, each decoded as its own type; anything else under it is counted as malformed. One
        subscriber sees one publisher's samples in publishing order across the topics; separate
        subscribers do not (benchmarks/bench_sensor_order.py: up to a quarter of the earlier topics'
        samples came after the last topic's sample of the same tick)."""
        prefix = keys.key(self.run_id, "")
        verifier = data_auth.Verifier(self.data_key) if self.data_key is not None and not self.trust_inputs else None

        def handle(sample: zenoh.Sample) -> None:
            arrived_ns = time.monotonic_ns()
            topic = str(sample.key_expr)[len(prefix):]
            kind = kinds.get(topic)
            payload = sample.payload.to_bytes()
            if self._refused(verifier, sample, topic, payload):
                return
            try:
                if kind is None:
                    raise MalformedMessage(f"no message is expected on {topic}")
                message = decode(payload, kind)
            except MalformedMessage as exc:
                self.malformed[topic] += 1
                if self.malformed[topic] <= 5 or self.malformed[topic] % 100 == 0:
                    self.log.warning("malformed message #%d on %s: %s", self.malformed[topic], topic, exc)
                return
            if message.header.run_id != self.run_id:
                self.malformed[topic] += 1
                self.log.warning("message on %s carries run id %r", topic, message.header.run_id)
                return
            decoded_ns = time.monotonic_ns()
            on_message(message)
            if self.hop_trace is not None:
                self.hop_trace.received.append((topic, message.header.seq, arrived_ns, decoded_ns, time.monotonic_ns()))

        self._keepalive.append(self.session.declare_subscriber(keys.key(self.run_id, key_topic), handle))

    def subscribe_queue(self, topic: str, kind: type[Message]) -> "queue.Queue[Message]":
        # Not SimpleQueue, though its hand-off is cheaper: a node's thread is the one SIGTERM
        # interrupts, and such a SimpleQueue.get(timeout) was seen never to return
        # (bench/bus/can/realtime_bridge.py).
        q: queue.Queue[Message] = queue.Queue() if self.hop_trace is None else TracedQueue(self.hop_trace, topic)
        self.subscribe(topic, kind, q.put)
        return q

    def until_stopped(self, messages: "queue.Queue[Message]", poll_s: float = STOP_POLL_S):
        """Yield messages from a subscription queue until the node is told to stop; then the
        calling thread leaves its real-time priority (what follows is the node's files)."""
        while not self.stop.is_set():
            try:
                yield messages.get(timeout=poll_s)
            except queue.Empty:
                continue
        self.leave_realtime_priority()

    # --- liveliness -----------------------------------------------------------------------
    def declare_alive(self, host: str | None = None) -> None:
        """Answer presence queries from now on (alive; ready once declare_ready says so).
        host: the deployment's name of this host, reported with the clock readings."""
        self._presence = PresenceResponder(self.session, self.run_id, self.name, self.data_key, host)
        self._keepalive.append(self._presence)

    @property
    def presence(self) -> PresenceQuery:
        """This node's presence queries, under the run's key (one object: its refusals are counted once)."""
        if self._presence_query is None:
            self._presence_query = PresenceQuery(self.session, self.run_id, self.data_key)
        return self._presence_query

    def leave_realtime_priority(self) -> None:
        """The calling thread back to the default scheduler (a node's last work, writing its files,
        must not hold up another run's nodes at the same priority)."""
        if self.realtime_priority:
            set_realtime_priority(0)

    def declare_ready(self, consumed_topics: list[str], timeout_s: float | None = None) -> None:
        """Answer `ready` to presence queries once each of `consumed_topics` reaches a subscriber.

        Lock-step depends on it: a sample published before its subscriber is matched is lost.
        The default wait is the scenario's [run.liveliness] startup_timeout_s.
        """
        if timeout_s is None:
            timeout_s = self.scenario.run.liveliness.startup_timeout_s
        deadline = time.monotonic() + timeout_s
        for topic in consumed_topics:
            pub = self._publishers.get(topic) or self.declare_publisher(topic)
            while not pub.matching_status.matching:
                if time.monotonic() > deadline or self.stop.is_set():
                    raise TimeoutError(f"{self.name}: no subscriber for {topic} after {timeout_s} s")
                time.sleep(0.005)
        if self._presence is None:
            self.declare_alive()
        self._presence.ready = True

    def wait_for_ready(self, names: list[str], timeout_s: float) -> None:
        """Block until every name answers `ready`, authenticated (TimeoutError naming the others)."""
        self.presence.wait_ready(names, timeout_s, self.stop, who=self.name)

    def watch_peers(self, names: list[str]) -> None:
        """Note a peer that stops answering presence queries for a lease (process died, or hung).

        The node's loop reads `lost_peer`; only an authentic answer counts as a sign of life, so
        nothing without the run's key can hide a hung peer.
        """
        # Its thread ends with the session (a query on a closed session raises).
        self._watcher = PresenceWatcher(self.session, self.run_id, self.data_key, names,
                                        self.scenario.run.liveliness.lease_s).start()

    def _refresh_lost(self) -> None:
        if self._watcher is None:
            return
        now = time.monotonic()
        for peer in sorted(self._watcher.names):
            since = self._watcher.silent_since(peer, now)
            if since is None:
                if self.lost_since_s.pop(peer, None) is not None:
                    self.log.warning("peer '%s' is back (it answers presence queries again)", peer)
            elif peer not in self.lost_since_s:
                self.lost_since_s[peer] = since
                self.lost_peers.append(peer)
                self.log.warning("peer '%s' lost (no authentic presence answer for %.1f s)", peer,
                                 self._watcher.lease_s)

    def lost_peer(self, min_age_s: float) -> str | None:
        """A peer silent for at least min_age_s past its lease, else None.

        A busy machine can starve a peer past its lease without it being hung; it answers again
        when it is scheduled, so only a silence that lasts is a lost peer.
        """
        self._refresh_lost()
        now = time.monotonic()
        for peer, since in list(self.lost_since_s.items()):
            if now - since >= min_age_s:
                return peer
        return None

    # --- shutdown -------------------------------------------------------------------------
    def _unauthentic_counts(self) -> dict:
        counts = {reason: dict(by_topic) for reason, by_topic in self.unauthentic.items()}
        refused = sum(q.refused for q in (self._presence_query, self._watcher and self._watcher.query) if q)
        if refused:     # presence answers that did not authenticate (bench/bus/presence.py)
            counts.setdefault(data_auth.FORGED, {})[PRESENCE_TOPIC] = refused
        return counts

    def publish_stats(self) -> None:
        stats = ProcessStats(
            header=header(self.run_id, 0, 0.0),
            process=self.name,
            published=dict(self.published),
            malformed=dict(self.malformed),
            unauthentic=self._unauthentic_counts(),
            realtime_priority=self.realtime_priority,
        )
        self.publish(f"{keys.STATUS_STATS}/{self.name}", stats)
        self.log.info("published %s; malformed %s; unauthentic %s", dict(self.published), dict(self.malformed),
                      stats.unauthentic)


def node_options(args) -> SessionOptions:
    """Session options of `bench node`: from --deployment/--host, or --cert-dir, or plain endpoints."""
    config_file = Path(args.zenoh_config) if args.zenoh_config else None
    deployment_file = getattr(args, "deployment", None)
    if deployment_file:
        if not getattr(args, "host", None):
            raise ValueError("--deployment needs --host NAME (which of the file's hosts this is)")
        deployment = load_deployment(deployment_file)
        if args.host not in deployment.hosts:
            raise DeploymentError(f"--host: {args.host!r} is not one of the hosts ({', '.join(deployment.hosts)})")
        deployment.check_certificates(args.host, [args.name])
        options = deployment.node_options(args.name, args.host)
        extra_connect = tuple(e for e in (args.connect or ()) if e not in options.connect)
        return dataclasses.replace(options, listen=tuple(args.listen or ()) or options.listen,
                                   connect=options.connect + extra_connect, config_file=config_file)
    identity = identity_files(Path(args.cert_dir), args.name) if getattr(args, "cert_dir", None) else None
    return SessionOptions(
        listen=tuple(args.listen or ()),
        connect=tuple(args.connect or ()),
        config_file=config_file,
        identity=identity,
    )


def stop_when_gone(ctx: NodeContext, process: str) -> None:
    """Stop the node when `process` (the launcher, for nodes on other hosts: it cannot signal them,
    so it ends the run by leaving the bus) stops answering presence queries for a lease.

    Its liveliness token's delete is a hint that makes the node ask at once (the launcher
    undeclares its presence answer before its token at the end of a run); the answer, signed under
    the run's key, decides: a token held by anyone else can neither keep the node running nor stop it.
    """
    key_expr = keys.key(ctx.run_id, f"{keys.ALIVE}/{process}")
    watcher = PresenceWatcher(ctx.session, ctx.run_id, ctx.data_key, [process],
                              ctx.scenario.run.liveliness.lease_s).start()

    def gone(why: str) -> None:
        if not ctx.stop.is_set():
            ctx.log.info("'%s' left the bus (%s): stopping", process, why)
            ctx.stop.set()

    def confirm() -> None:
        # Not in Zenoh's callback thread: a query from there would wait on that same thread.
        try:
            if process in ctx.presence.ask(process, timeout_s=1.0):
                return
        except Exception:   # noqa: BLE001 - the session is closing: stopping anyway
            pass
        gone("its token went and it does not answer")

    def follow() -> None:
        while not ctx.stop.wait(watcher.period_s):
            if watcher.silent_since(process) is not None:
                gone(f"no authentic presence answer for {watcher.lease_s:g} s")

    def on_token(sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            threading.Thread(target=confirm, name=f"{process}-gone", daemon=True).start()

    threading.Thread(target=follow, name=f"{process}-watch", daemon=True).start()
    ctx._keepalive.append(ctx.session.liveliness().declare_subscriber(key_expr, on_token))


def run_node(name: str, run_id: str, scenario: Scenario, options: SessionOptions, run_dir: Path,
             peers: list[str] | None = None, stop_with: str | None = None, host: str | None = None,
             trust_inputs: bool = False, breaks: tuple[str, ...] = (), allow_live_faults: bool = False,
             live_port: int | None = None) -> int:
    """Open the session, install signal handlers, run the node, always close cleanly.

    stop_with: also stop when that process's alive token vanishes (nodes on other hosts than the
    launcher). host: the deployment's name of this host, reported with the clock offsets.
    """
    import importlib

    if name not in NODES:
        raise ValueError(f"unknown node {name!r} (known: {', '.join(sorted(NODES))})")
    if breaks and name != "mtq":
        raise ValueError(f"--break {', '.join(breaks)} breaks the board (node mtq), not {name}")
    die_with_launcher()
    report_key = key_from_environment()
    if options.identity is not None:
        check_identity(options.identity)     # a bad certificate is named before a missing key
    data_key = data_auth.node_key(run_dir, options.identity.ca_path.parent if options.identity else None)
    module = importlib.import_module("bench.bus.can.board_breaks" if breaks else NODES[name])
    log = logging.getLogger(f"bench.{name}")
    lease_ms = int(round(scenario.run.liveliness.lease_s * 1000))
    # Before the session: Zenoh's threads, started with it, inherit the priority.
    priority = node_realtime_priority(name, scenario)
    if priority and not set_realtime_priority(priority, inherited=True):
        log.warning("SCHED_FIFO %d refused (no CAP_SYS_NICE): the host may hold this node up", priority)
        priority = 0
    session = open_session(dataclasses.replace(options, lease_ms=lease_ms))
    ctx = NodeContext(name=name, run_id=run_id, scenario=scenario, session=session, run_dir=run_dir, log=log,
                      peers=list(peers or []), report_key=report_key, data_key=data_key, realtime_priority=priority,
                      trust_inputs=trust_inputs, breaks=tuple(breaks), allow_live_faults=allow_live_faults,
                      live_port=live_port)
    if trust_inputs:
        log.warning("--break trust-inputs: this node takes every input without checking its tag (a broken node, "
                    "for bench contract check's self-test)")
    if data_key is None:
        log.warning("no data key (%s): this node signs and checks nothing, and the run's nodes drop what it "
                    "publishes", run_dir / data_auth.KEY_FILE)

    def request_stop(signum, _frame):
        log.info("signal %d: stopping", signum)
        # A stop that hangs says where: every thread's stack into this node's log, before the
        # launcher kills a node that idles past its grace (5 s, bench/launcher/children.py).
        faulthandler.dump_traceback_later(STOP_STACKS_AFTER_S)
        ctx.stop.set()

    signal.signal(signal.SIGTERM, request_stop)
    signal.signal(signal.SIGINT, request_stop)
    try:
        if stop_with:
            stop_when_gone(ctx, stop_with)
        ctx.declare_alive(host)     # presence answers: liveliness, readiness and the recorder's clock pings
        code = module.run(ctx)
        ctx.publish_pending()
        if ctx.hop_trace is not None:
            ctx.hop_trace.write(run_dir, name)
        ctx.publish_stats()
        time.sleep(0.05)  # let the stats sample leave before the session closes
        return code
    finally:
        session.close()
