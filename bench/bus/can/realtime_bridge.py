"""The bus model on the wall clock: RealTimeBridge runs a BusModel between the python-can buses of
the bus's ends (the flight side's channel, the board's), as the canbus node of a real-time run.
"""
from __future__ import annotations

import queue
import time

import can

from bench.bus.can.busmodel import BusModel, Delivery
from bench.bus.can.host_lateness import HostLateLog
from bench.bus.can.wire_time import WireClock


class RealTimeBridge:
    """Runs a BusModel on the wall clock between two python-can buses (flight side, board side).

    A frame enters the model at the time its sender put it on its bus (python-can's timestamp:
    the sender's clock over Zenoh, the kernel's on SocketCAN), not when this process got round
    to reading it: a stall here must delay deliveries, never bunch frames 20 ms apart into a burst
    that overflows a transmit queue in the model. Frames are submitted in that time order, the
    model advanced to just before each first: frames sent at one time (both ends at once) start
    together if they reach this process before the model has run past that time. Deliveries
    leave at most `granularity_s` after the model says their last bit passed.

    Each end's node is the first sender heard on its channel (the Zenoh transport says which bus
    instance sent a frame). Any other process on a channel (a rogue, a CAN tool) is a node of its
    own, with its own controller, transmit queue and error counters, as a third device on a real
    bus is: what it sends arbitrates with the ends' frames and the ends acknowledge it, but it
    never waits in an end's transmit queue nor counts as that end's transmission. (Taken as the
    ends' own, one NMT frame put on both channels at once was both ends sending the same frame,
    which nobody else was there to acknowledge: ACK errors until one end was error-passive, and
    before suspend transmission without end, the driver's commands dropped behind them and the
    board in safe state; issue 44.) At most MAX_OTHER_SENDERS such nodes; further senders share one.
    """

    MAX_OTHER_SENDERS = 8

    # A delivery leaving this much after its last bit passed in the model, or a wait ending this
    # much after it should: this process was not scheduled in time (a host overrun). Recorded so
    # the flight side's fault checks can tell a starved bridge from a bus fault.
    HOST_LATE_S = 0.005

    def __init__(self, model: BusModel, buses: dict[str, can.BusABC], granularity_s: float = 0.0001):
        self.model = model
        self.buses = buses
        self.granularity_s = granularity_s
        self.send_failures = 0
        self.host_lateness = HostLateLog()                     # on the monotonic clock
        self._wire_clock = WireClock()                         # a frame enters the model when it was sent
        # queue.Queue, not SimpleQueue: on CPython 3.11 a SimpleQueue.get(timeout) that a signal
        # interrupts (SIGTERM: stop) was seen never to return, so the node could not stop.
        self._inbox: queue.Queue = queue.Queue()
        self._end_sender: dict[str, int] = {}                 # side -> the bus instance of its node
        self.other_senders: dict[tuple[str, int], str] = {}   # (side, sender) -> its node in the model
        # A bus that can hand its frames over on its own receive thread (the Zenoh transport) does;
        # any other python-can bus gets a Notifier thread that reads it.
        self._notifiers = []
        for side, bus in buses.items():
            listener = _Inbox(side, self._inbox)
            if hasattr(bus, "forward_to"):
                bus.forward_to(listener.on_frame, with_sender=True)
            else:
                self._notifiers.append(can.Notifier(bus, [listener], timeout=0.05))

    def run(self, stop) -> None:
        try:
            while not stop.is_set():
                now_ns = time.monotonic_ns()
                next_ns = self.model.next_event_ns()
                wait_s = 0.01 if next_ns is None else min(0.01, max(self.granularity_s, (next_ns - now_ns) / 1e9))
                arrivals = self._arrivals(wait_s)
                if not arrivals:
                    self._count_late((time.monotonic_ns() - now_ns) / 1e9 - wait_s)
                for t_ns, side, msg in sorted(arrivals, key=lambda a: a[0]):
                    # To just before it: frames sent at the same time (by both ends at once) are
                    # all queued before any starts, so they arbitrate (equal identifiers collide).
                    self._deliver(self.model.run_until(t_ns - 1))
                    self.model.submit(side, msg, t_ns)
                self._deliver(self.model.run_until(time.monotonic_ns()))
        finally:
            for notifier in self._notifiers:
                notifier.stop()

    def _arrivals(self, wait_s: float) -> list[tuple[int, str, can.Message]]:
        """Everything that arrived (waiting up to wait_s for the first), with its send time."""
        arrivals = []
        try:
            item = self._inbox.get(timeout=wait_s)
            while True:
                side, msg, arrival_ns, *sender = item
                sent_ns = self._wire_clock.sent_ns(msg, arrival_ns)
                arrivals.append((sent_ns, self._node(side, sender[0] if sender else None), msg))
                item = self._inbox.get_nowait()
        except queue.Empty:
            pass
        return arrivals

    def _node(self, side: str, sender: int | None) -> str:
        """The model's node that sent a frame heard on `side`'s channel (see the class docstring)."""
        if sender is None or self._end_sender.setdefault(side, sender) == sender:
            return side
        node = self.other_senders.get((side, sender))
        if node is None:
            node = f"{side}/{sender:016x}"
            if len(self.other_senders) >= self.MAX_OTHER_SENDERS:
                node = f"{side}/others"     # not kept per sender: a rogue drawing new ids costs no memory
            else:
                self.other_senders[(side, sender)] = node
            if node not in self.model.queues:
                self.model.add_node(node)
                self.model.wire_of[node] = side
        return node

    def _count_late(self, late_s: float) -> None:
        if late_s > self.HOST_LATE_S:
            self.host_lateness.note(time.monotonic_ns(), late_s)

    def report(self) -> dict:
        """The bridge's own figures, for the bus model's report beside the model's."""
        return {"send_failures": self.send_failures, **self.host_lateness.report(),
                "other_senders": sorted(n for n in self.model.nodes if n in self.model.wire_of)}

    def _deliver(self, deliveries: list[Delivery]) -> None:
        if deliveries:
            # msg.timestamp: the wall time its last bit passed, in the model
            last_bit_wall_ns = max(round(d.msg.timestamp * 1e9) for d in deliveries)
            self._count_late((time.time_ns() - last_bit_wall_ns) / 1e9)
        for delivery in deliveries:
            for side in delivery.destinations:
                if side not in self.buses:
                    continue    # another sender on a channel: it hears that channel's frames there
                try:
                    self.buses[side].send(delivery.msg)
                except (can.CanError, ValueError):  # counted; the bridge must keep running
                    self.send_failures += 1


class _Inbox(can.Listener):
    def __init__(self, side: str, inbox):
        self.side = side
        self.inbox = inbox

    def on_message_received(self, msg: can.Message) -> None:
        self.inbox.put((self.side, msg, time.monotonic_ns()))

    def on_frame(self, msg: can.Message, sender: int) -> None:
        self.inbox.put((self.side, msg, time.monotonic_ns(), sender))
