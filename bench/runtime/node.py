"""What every bench process has: its Zenoh session, its scenario, counters, and a clean stop.

A node is a module with `run(ctx: NodeContext) -> int`, registered in NODES. `bench node NAME`
builds the context and calls it; the launcher starts each node that way as its own OS process.

Messages arrive on Zenoh's threads; `subscribe` decodes and validates them there and hands typed
messages to the node's queue, so a node's logic runs on one thread and a malformed payload is
counted and logged where it arrives, never raised into the node.
"""
from __future__ import annotations

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

from bench.bus import keys
from bench.bus.clock_sync import declare_clock_responder
from bench.bus.schemas import MalformedMessage, Message, ProcessStats, decode, encode, header
from bench.bus.session import SessionOptions, open_session
from bench.scenario import Scenario

# Node name -> module with run(ctx). Other parts add theirs (the magnetorquer board, the recorder).
NODES: dict[str, str] = {
    "plant": "bench.plant.node",
    "estimator": "bench.estimator.node",
    "controller": "bench.controller.node",
    "recorder": "bench.recorder",
    "mtq": "bench.bus.can.nodes",       # magnetorquer board
    "canbus": "bench.bus.can.nodes",    # CAN bus model and fault injector
    "planner": "bench.planner.node",    # MILQR attitude plans (issue 12)
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
    lost_peers: list[str] = field(default_factory=list)
    published: Counter = field(default_factory=Counter)
    malformed: Counter = field(default_factory=Counter)
    _publishers: dict = field(default_factory=dict)
    _keepalive: list = field(default_factory=list)

    # --- publishing -----------------------------------------------------------------------
    def publish(self, topic: str, message: Message) -> None:
        pub = self._publishers.get(topic)
        if pub is None:
            pub = self.declare_publisher(topic)
        pub.put(encode(message))
        self.published[topic] += 1

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

        def handle(sample: zenoh.Sample) -> None:
            try:
                message = decode(sample.payload.to_bytes(), kind)
            except MalformedMessage as exc:
                self.malformed[topic] += 1
                if self.malformed[topic] <= 5 or self.malformed[topic] % 100 == 0:
                    self.log.warning("malformed message #%d on %s: %s", self.malformed[topic], topic, exc)
                return
            if message.header.run_id != self.run_id:
                self.malformed[topic] += 1
                self.log.warning("message on %s carries run id %r", topic, message.header.run_id)
                return
            on_message(message)

        self._keepalive.append(self.session.declare_subscriber(keys.key(self.run_id, topic), handle))

    def subscribe_queue(self, topic: str, kind: type[Message]) -> "queue.Queue[Message]":
        q: queue.Queue[Message] = queue.Queue()
        self.subscribe(topic, kind, q.put)
        return q

    def until_stopped(self, messages: "queue.Queue[Message]", poll_s: float = 0.2):
        """Yield messages from a subscription queue until the node is told to stop."""
        while not self.stop.is_set():
            try:
                yield messages.get(timeout=poll_s)
            except queue.Empty:
                continue

    # --- liveliness -----------------------------------------------------------------------
    def declare_alive(self) -> None:
        self._keepalive.append(self.session.liveliness().declare_token(keys.key(self.run_id, f"{keys.ALIVE}/{self.name}")))

    def declare_ready(self, consumed_topics: list[str], timeout_s: float = 20.0) -> None:
        """Declare `ready/<name>` once each of `consumed_topics` reaches a subscriber.

        Lock-step depends on it: a sample published before its subscriber is matched is lost.
        """
        deadline = time.monotonic() + timeout_s
        for topic in consumed_topics:
            pub = self._publishers.get(topic) or self.declare_publisher(topic)
            while not pub.matching_status.matching:
                if time.monotonic() > deadline or self.stop.is_set():
                    raise TimeoutError(f"{self.name}: no subscriber for {topic} after {timeout_s} s")
                time.sleep(0.005)
        self._keepalive.append(self.session.liveliness().declare_token(keys.key(self.run_id, f"{keys.READY}/{self.name}")))

    def wait_for_tokens(self, kind: str, names: list[str], timeout_s: float) -> None:
        """Block until liveliness tokens `<kind>/<name>` exist for every name."""
        deadline = time.monotonic() + timeout_s
        missing = set(names)
        while missing:
            replies = self.session.liveliness().get(keys.key(self.run_id, f"{kind}/*"), timeout=1.0)
            for reply in replies:
                if reply.ok is not None:
                    missing.discard(str(reply.ok.key_expr).rsplit("/", 1)[-1])
            if not missing:
                return
            if time.monotonic() > deadline or self.stop.is_set():
                raise TimeoutError(f"{self.name}: no {kind} token from {', '.join(sorted(missing))} after {timeout_s} s")
            time.sleep(0.02)

    def watch_peers(self, names: list[str]) -> None:
        """Note a peer whose `alive` token vanishes (process died, or hung past the lease).

        The node's loop reads `lost_peers`; Zenoh drops a hung peer's token after the lease.
        """
        watched = set(names)

        def on_token(sample: zenoh.Sample) -> None:
            peer = str(sample.key_expr).rsplit("/", 1)[-1]
            if sample.kind == zenoh.SampleKind.DELETE and peer in watched:
                self.lost_peers.append(peer)
                self.log.error("peer '%s' lost (its liveliness token vanished)", peer)

        self._keepalive.append(self.session.liveliness().declare_subscriber(
            keys.key(self.run_id, f"{keys.ALIVE}/*"), on_token))

    # --- shutdown -------------------------------------------------------------------------
    def publish_stats(self) -> None:
        stats = ProcessStats(
            header=header(self.run_id, 0, 0.0),
            process=self.name,
            published=dict(self.published),
            malformed=dict(self.malformed),
        )
        self.publish(f"{keys.STATUS_STATS}/{self.name}", stats)
        self.log.info("published %s; malformed %s", dict(self.published), dict(self.malformed))


def node_options(args) -> SessionOptions:
    return SessionOptions(
        listen=tuple(args.listen or ()),
        connect=tuple(args.connect or ()),
        config_file=Path(args.zenoh_config) if args.zenoh_config else None,
    )


def run_node(name: str, run_id: str, scenario: Scenario, options: SessionOptions, run_dir: Path,
             peers: list[str] | None = None) -> int:
    """Open the session, install signal handlers, run the node, always close cleanly."""
    import importlib

    if name not in NODES:
        raise ValueError(f"unknown node {name!r} (known: {', '.join(sorted(NODES))})")
    module = importlib.import_module(NODES[name])
    log = logging.getLogger(f"bench.{name}")
    session = open_session(options)
    ctx = NodeContext(name=name, run_id=run_id, scenario=scenario, session=session, run_dir=run_dir, log=log,
                      peers=list(peers or []))

    def request_stop(signum, _frame):
        log.info("signal %d: stopping", signum)
        ctx.stop.set()

    signal.signal(signal.SIGTERM, request_stop)
    signal.signal(signal.SIGINT, request_stop)
    try:
        ctx.declare_alive()
        ctx._keepalive.append(declare_clock_responder(session, run_id, name))   # clock offsets (recorder)
        code = module.run(ctx)
        ctx.publish_stats()
        time.sleep(0.05)  # let the stats sample leave before the session closes
        return code
    finally:
        session.close()
