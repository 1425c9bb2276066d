"""A python-can interface that carries CAN frames over the bench's Zenoh session.

For hosts without kernel CAN and for benches spread over several hosts. Registered as the
python-can interface plugin `zenoh` (entry point group `can.interface`), so driver and node code
open it like any other bus:

    can.Bus(interface="zenoh", channel="vcan0", run_id="r1", connect=["tcp/127.0.0.1:7447"])

Bus semantics follow a real CAN bus (and python-can's `virtual` interface): every bus instance on
the same run id and channel sees every frame the others send; a sender does not receive its own
frames unless `receive_own_messages=True`. One channel is one key expression,
`bench/<run_id>/can/<channel>`. Frames from one sender arrive in the order sent (one reliable
Zenoh publisher per bus); frames of different senders have no global order, as on vcan, which has
no arbitration either: the bench's bus model supplies that.

Payloads that are not frames are counted (`stats.malformed`) and dropped, never raised: a
process must not die because something else wrote garbage on its key expression.
"""
from __future__ import annotations

import logging
import queue
import secrets
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

import can
import zenoh
from can.bus import BusABC, CanProtocol

from bench.bus import keys
from bench.bus.can import zenoh_wire
from bench.bus.can.config import ZENOH_CHANNEL
from bench.bus.session import SessionConfigError, SessionOptions, open_session

log = logging.getLogger(__name__)

CAN_TOPIC = "can"
# Frames waiting to be read. A full queue drops the newest frame and counts it, as a SocketCAN
# socket does when its receive buffer is full: a slow reader must not grow memory without bound.
DEFAULT_RX_QUEUE_FRAMES = 10_000
_CHANNEL = ZENOH_CHANNEL     # one key-expression chunk: the rule a scenario's channel is checked by
_SHUTDOWN = object()


def channel_key(run_id: str, channel: str) -> str:
    """Key expression of one CAN channel: `bench/<run_id>/can/<channel>`."""
    return keys.key(keys.check_run_id(run_id), f"{CAN_TOPIC}/{check_channel(channel)}")


def member_key(run_id: str, channel: str, member: str = "*") -> str:
    """Liveliness key of the bus instances attached to a channel (one token each)."""
    return f"{channel_key(run_id, channel)}/member/{member}"


def check_channel(channel: str) -> str:
    """A channel is one key-expression chunk: no '/', no wildcards."""
    if not isinstance(channel, str) or not _CHANNEL.match(channel):
        raise ValueError(f"CAN channel {channel!r} must be 1-64 characters of letters, digits, '_', '.', '-'")
    return channel


def _endpoints(value: str | Sequence[str] | None) -> tuple[str, ...]:
    # python-can configuration files give strings; code gives lists.
    if value is None:
        return ()
    if isinstance(value, str):
        return tuple(e.strip() for e in value.split(",") if e.strip())
    return tuple(value)


# Senders whose frame sequence a bus follows (gap counts); more are forgotten oldest first.
MAX_TRACKED_SENDERS = 64


@dataclass
class ZenohCanStats:
    sent: int = 0
    received: int = 0
    malformed: int = 0            # payloads that were not frames; dropped
    rx_overflow: int = 0          # frames dropped because the reader fell behind
    sequence_gaps: int = 0        # frames a sender sent that never arrived here


class ZenohCanBus(BusABC):
    """python-can bus whose wire is a Zenoh key expression; see the module docstring."""

    def __init__(
        self,
        channel: str = "vcan0",
        *,
        run_id: str | None = None,
        listen: str | Sequence[str] | None = None,
        connect: str | Sequence[str] | None = None,
        session_options: SessionOptions | None = None,
        session: zenoh.Session | None = None,
        receive_own_messages: bool = False,
        rx_queue_size: int = DEFAULT_RX_QUEUE_FRAMES,
        fd: bool = False,
        express: bool = True,
        can_filters=None,
        **kwargs,
    ) -> None:
        """
        :param channel: name of the CAN channel, e.g. "vcan0"; one key-expression chunk.
        :param run_id: the bench run; buses of different runs never see each other.
        :param listen, connect: Zenoh endpoints of this bus's own session (e.g.
            "tcp/127.0.0.1:7447"); a string may list several separated by commas.
        :param session_options: a full SessionOptions instead of listen/connect.
        :param session: an open session to share (a node's own); it is not closed on shutdown.
        :param fd: accept CAN FD frames, as SocketCAN's `fd=True`; otherwise they are refused.
        :param express: send each frame at once rather than batching: CAN frames are small and
            latency matters more than Zenoh's batching throughput.
        """
        if run_id is None:
            raise can.CanInitializationError("the zenoh CAN interface needs run_id=... (the bench run to join)")
        try:
            self._key = channel_key(run_id, channel)
        except ValueError as exc:
            raise can.CanInitializationError(str(exc)) from exc
        if session is not None and (listen or connect or session_options):
            raise can.CanInitializationError("give either session= or listen/connect/session_options, not both")
        if session_options is not None and (listen or connect):
            raise can.CanInitializationError("give either session_options= or listen/connect, not both")
        super().__init__(channel=channel, can_filters=can_filters, **kwargs)
        self.channel_info = f"Zenoh CAN channel {self._key}"
        self._can_protocol = CanProtocol.CAN_FD if fd else CanProtocol.CAN_20
        self.receive_own_messages = receive_own_messages
        self.stats = ZenohCanStats()
        self._channel = channel
        self._fd = fd
        self._sender_id = secrets.randbits(64)
        self._tx_sequence = 0
        self._rx_sequence: dict[int, int] = {}
        self._peers: set[str] = set()
        self._peers_changed = threading.Condition()
        self._queue: queue.Queue = queue.Queue(maxsize=rx_queue_size)
        self._listener = None     # forward_to(): frames go to it on Zenoh's thread instead of the queue
        self._with_sender = False
        self._tx_lock = threading.Lock()
        self._open = False

        self._owns_session = session is None
        if session is None:
            options = session_options or SessionOptions(listen=_endpoints(listen), connect=_endpoints(connect))
            try:
                session = open_session(options)
            except SessionConfigError as exc:
                raise can.CanInitializationError(str(exc)) from exc
        self._session = session
        try:
            # Subscriber before token: a peer that sees this bus's token can rely on its frames
            # reaching this bus, since Zenoh propagates the declarations in order.
            self._subscriber = session.declare_subscriber(self._key, self._on_sample)
            self._publisher = session.declare_publisher(
                self._key,
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
                express=express,
            )
            self._member_subscriber = session.liveliness().declare_subscriber(
                member_key(run_id, channel), self._on_member, history=True
            )
            self._token = session.liveliness().declare_token(member_key(run_id, channel, f"{self._sender_id:016x}"))
        except Exception as exc:
            if self._owns_session:
                session.close()
            raise can.CanInitializationError(f"could not attach to {self._key}: {exc}") from exc
        self._open = True

    # --- receiving (Zenoh's threads) -------------------------------------------------------
    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            msg, sender, sequence = zenoh_wire.decode(sample.payload.to_bytes(), self._channel)
        except Exception as exc:  # MalformedFrame, or anything else: nothing may escape into Zenoh's thread
            self._count_malformed(exc)
            return
        if sender == self._sender_id:
            return  # our own frame; receive_own_messages is served locally in send()
        last = self._rx_sequence.get(sender)
        if last is not None:
            self.stats.sequence_gaps += (sequence - last - 1) & 0xFFFFFFFF
        elif len(self._rx_sequence) >= MAX_TRACKED_SENDERS:
            # Anyone on the channel can send under a new id each frame: the oldest id goes, so
            # memory stays bounded (a forgotten sender's next frame counts no gap).
            self._rx_sequence.pop(next(iter(self._rx_sequence)))
        self._rx_sequence[sender] = sequence
        listener = self._listener
        if listener is None:
            self._enqueue(msg)
            return
        self.stats.received += 1
        try:
            if self._with_sender:
                listener(msg, sender)
            else:
                listener(msg)
        except Exception as exc:   # nothing may escape into Zenoh's thread
            log.error("listener of %s failed on a frame: %s", self._key, exc)

    def _count_malformed(self, exc: Exception) -> None:
        self.stats.malformed += 1
        if self.stats.malformed <= 5 or self.stats.malformed % 100 == 0:
            log.warning("dropped malformed CAN payload #%d on %s: %s", self.stats.malformed, self._key, exc)

    def _enqueue(self, msg: can.Message) -> None:
        try:
            self._queue.put_nowait(msg)
            self.stats.received += 1
        except queue.Full:
            self.stats.rx_overflow += 1

    def _on_member(self, sample: zenoh.Sample) -> None:
        member = str(sample.key_expr).rsplit("/", 1)[-1]
        if member == f"{self._sender_id:016x}":
            return
        with self._peers_changed:
            if sample.kind == zenoh.SampleKind.PUT:
                self._peers.add(member)
            else:
                self._peers.discard(member)
            self._peers_changed.notify_all()

    # --- python-can interface --------------------------------------------------------------
    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        self._check_open()
        try:
            item = self._queue.get(block=True, timeout=timeout)
        except queue.Empty:
            return None, False
        if item is _SHUTDOWN:
            self._queue.put_nowait(_SHUTDOWN)  # wake any other reader too
            raise can.CanOperationError(f"{self._key} was shut down while receiving")
        return item, False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Put one frame on the channel.

        Raises ValueError for a frame that is not valid CAN (bad id, dlc, data length), and
        CanOperationError once shut down. `timeout` is not used: a reliable Zenoh put blocks only
        while the link is congested, bounded by Zenoh's own congestion settings.
        """
        self._check_open()
        if msg.is_fd and not self._fd:
            raise ValueError("CAN FD frame on a bus opened without fd=True")
        timestamp_s = time.time()  # the time the frame is on the wire, as SocketCAN stamps it
        with self._tx_lock:  # one sequence order on the wire per sender
            payload = zenoh_wire.encode(msg, timestamp_s=timestamp_s, sender_id=self._sender_id,
                                        sequence=self._tx_sequence)
            self._tx_sequence = (self._tx_sequence + 1) & 0xFFFFFFFF
            try:
                self._publisher.put(payload)
            except Exception as exc:
                raise can.CanOperationError(f"could not send on {self._key}: {exc}") from exc
            self.stats.sent += 1
        if self.receive_own_messages:
            own, _, _ = zenoh_wire.decode(payload, self._channel)
            own.is_rx = False
            self._enqueue(own)

    def shutdown(self) -> None:
        super().shutdown()
        if not self._open:
            return
        self._open = False
        for declared in (self._token, self._member_subscriber, self._publisher, self._subscriber):
            try:
                declared.undeclare()
            except Exception as exc:  # already gone with a closed session
                log.debug("undeclare on %s: %s", self._key, exc)
        if self._owns_session:
            self._session.close()
        try:
            self._queue.put_nowait(_SHUTDOWN)
        except queue.Full:
            pass

    # --- bench extras ----------------------------------------------------------------------
    def forward_to(self, listener, with_sender: bool = False) -> None:
        """From now on, hand each received frame to `listener(msg)` on Zenoh's thread instead of
        queueing it for `recv`: one thread hand-off less for a reader that has its own queue
        (the bus model's bridge), as a python-can Notifier would add one more.

        with_sender: `listener(msg, sender)`, with the id of the bus instance that sent the frame
        (each draws its own at random): the bus model tells the node at the other end of its
        channel from any other process on that channel by it."""
        self._with_sender = with_sender
        self._listener = listener

    @property
    def peers(self) -> set[str]:
        """Ids of the other bus instances on this channel that are alive now."""
        with self._peers_changed:
            return set(self._peers)

    def wait_for_peers(self, count: int, timeout_s: float) -> bool:
        """Wait until at least `count` other buses are on this channel.

        Zenoh delivers a frame only to buses it already knows about; a process that sends
        right after starting waits here first, as a CAN node waits for the bus to come up.
        """
        deadline = time.monotonic() + timeout_s
        with self._peers_changed:
            while len(self._peers) < count:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._peers_changed.wait(remaining)
            return True

    def _check_open(self) -> None:
        if not self._open:
            raise can.CanOperationError(f"{self._key} is shut down")
