"""The CAN bus between the flight side and the board, with the time and arbitration vcan lacks.

Nodes submit frames; each node's controller keeps them in a transmit queue (FIFO, bounded like a
controller's buffers). Whenever the bus is free, the ready queue heads compete and the lowest
identifier wins (a babbling node of the fault injector competes too). A frame occupies the bus
for its exact bit count at the bitrate, and is delivered to the nodes that listen for it when
its last bit has passed. The fault injector acts on submission (drop, delay, alter, inject) and
on each transmission attempt (error frames, which drive the transmitter's error counter through
error-passive to bus-off and recovery).

The model runs on a clock it is given: `submit(source, msg, t_ns)` and `run_until(t_ns)`. The
canbus node feeds it wall-clock times; the unit tests feed it exact ones, deterministically.
Everything that happens to a frame goes to `capture` (a callable taking a can.Message, e.g. a
candump Logger's on_message_received) on a channel naming what happened: "bus" (on the wire),
"dropped", "replaced" (the original of an altered frame). Fault times count from the first
command frame (see FaultInjector.arm).
"""
from __future__ import annotations

import queue
import statistics
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Callable

import can
import numpy as np

from bench.bus.can import bittiming, errors
from bench.bus.can import protocol as p
from bench.bus.can.host_lateness import HostLateLog
from bench.bus.can.injector import SOURCE_INJECTOR, FaultInjector, Flood, Transmission
from bench.bus.spill import SpilledRows, WindowCounter

FLIGHT = "flight"
BOARD = "board"
NODES = (FLIGHT, BOARD)   # the nodes of a bench bus; BusModel(nodes=...) takes any number
LOAD_WINDOW_NS = 100_000_000
CHANNEL_BUS, CHANNEL_DROPPED, CHANNEL_REPLACED = "bus", "dropped", "replaced"
CHANNEL_ERRORS = "errors"   # error reports to nodes other than the flight side (not on the wire)
RECESSIVE_RUN_BITS = 11                                   # ISO 11898-1: one occurrence for bus-off recovery
RECOVERY_OCCURRENCES = bittiming.BUS_OFF_RECOVERY_BITS // RECESSIVE_RUN_BITS   # 128
PASSIVE_ERROR_FRAME_BITS = 6 + 8 + 3                      # passive (recessive) error flag, delimiter, intermission
SUSPEND_TRANSMISSION_BITS = 8                             # an error-passive transmitter's wait after intermission
BUS_OFF_EPISODES_LISTED = 100                             # the report lists the first ones; counts cover all


@dataclass(frozen=True)
class Delivery:
    msg: can.Message            # stamped with the wall time its last bit passed
    destinations: tuple[str, ...]


@dataclass
class _InFlight:
    tx: Transmission | None     # None: a babbler frame
    msg: can.Message
    start_ns: int
    end_ns: int
    destroyed_by: object | None = None          # the error_frames fault that destroys it
    error: errors.BusError | None = None        # a bus error the bus itself causes (collision, no ACK)
    together: tuple[Transmission, ...] = ()     # other transmitters of the same frame (equal id, equal data)
    collided: tuple[Transmission, ...] = ()     # other transmitters in an equal-id collision
    # Error-passive transmitters that lost at a data bit: their error flag is recessive, the frame
    # goes on without them (ISO 11898-1); each has a bit error all the same.
    passive_losers: tuple[Transmission, ...] = ()
    # Recessive bits at the attempt's end (ACK delimiter, end of frame, intermission; or an error
    # delimiter and intermission): what a bus-off node counts towards its recovery.
    recessive_tail_bits: int = RECESSIVE_RUN_BITS


@dataclass
class _Recovery:
    """A bus-off node watching the bus for the 128 occurrences of 11 consecutive recessive bits
    after which it rejoins (ISO 11898-1), counted bit for bit from `counted_ns` on."""
    bus_off_ns: int
    counted_ns: int             # the bus is counted up to here (after a restart delay: from its end)
    run_bits: int = 0           # recessive bits of the current run not yet an occurrence
    occurrences: int = 0


@dataclass
class BusStats:
    busy_ns: int = 0
    frames: Counter = field(default_factory=Counter)          # by frame name or hex id
    dropped: Counter = field(default_factory=Counter)         # by reason
    error_frames: int = 0
    bus_off: Counter = field(default_factory=Counter)         # by node
    tec_max: Counter = field(default_factory=Counter)
    bus_errors: Counter = field(default_factory=Counter)      # by kind (bit, ack, ...)
    # Per command frame and per 100 ms window: on disk as they come (bench/bus/spill.py), so that
    # a bus model of any run length keeps a flat memory; the report reads them back, exact.
    command_latency_ns: dict = field(default_factory=lambda: {"without_flood": SpilledRows((), np.int64),
                                                              "with_flood": SpilledRows((), np.int64)})
    load_windows: WindowCounter = field(default_factory=WindowCounter)    # window index -> busy ns
    bus_off_recovered: Counter = field(default_factory=Counter)   # by node
    bus_off_time_ns: Counter = field(default_factory=Counter)     # by node, recovered episodes
    bus_off_longest_ns: Counter = field(default_factory=Counter)  # by node
    bus_off_episodes: list = field(default_factory=list)          # [node, bus-off ns, recovered ns | None], the first few
    bus_off_episodes_left_off: int = 0


class BusModel:
    def __init__(self, injector: FaultInjector, protocol: p.Protocol, t0_ns: int, *,
                 bitrate_bps: int = bittiming.DEFAULT_BITRATE_BPS, tx_queue_frames: int = 8,
                 capture: Callable[[can.Message], None] | None = None,
                 to_wall_s: Callable[[int], float] = lambda t_ns: t_ns / 1e9,
                 nodes: tuple[str, ...] = NODES):
        self.injector = injector
        self.protocol = protocol
        self.t0_ns = t0_ns
        self.bitrate_bps = bitrate_bps
        self.tx_queue_frames = tx_queue_frames
        self.capture = capture or (lambda msg: None)
        self.to_wall_s = to_wall_s
        self.nodes: list[str] = []
        self.queues: dict[str, deque[Transmission]] = {}   # controllers' FIFOs
        self.counters: dict[str, errors.ErrorCounters] = {}
        self.tec = self.counters                            # its former name
        # A node on another node's wire: a process on that end's transport channel that is not its
        # node (RealTimeBridge). What it sends goes to every node but that one: the channel it
        # shares with it carried the frame there already.
        self.wire_of: dict[str, str] = {}
        for node in nodes:
            self.add_node(node)
        self._held: list[Transmission] = []    # the injector's frames and frames it holds back, by time
        self.recover_at_ns: dict[str, int] = {}   # bus-off nodes: when they rejoin if the bus stays idle
        self.unpowered: set[str] = set()          # nodes without power (board_power_loss): off the bus
        self._recovery: dict[str, _Recovery] = {}
        self._suspended_until_ns: dict[str, int] = {}   # error-passive transmitters (suspend transmission)
        self.in_flight: _InFlight | None = None
        self.bus_free_ns = t0_ns
        self.now_ns = t0_ns
        self.stats = BusStats()
        self._cmd_id = protocol.frame_ids[protocol.command_name]

    def add_node(self, name: str) -> None:
        """Another CAN controller on the bus, with its own queue and error counters."""
        if name in self.queues or name == SOURCE_INJECTOR:
            raise ValueError(f"node {name!r} is already on the bus")
        self.nodes.append(name)
        self.queues[name] = deque()
        self.counters[name] = errors.ErrorCounters()

    def listeners(self, source: str) -> tuple[str, ...]:
        same_wire = self.wire_of.get(source)
        return tuple(n for n in self.nodes if n != source and n != same_wire)

    def _on_bus(self, node: str) -> bool:
        # A bus-off node neither sends, hears nor ACKs; nor does a board without power.
        return node not in self.recover_at_ns and node not in self.unpowered

    def _apply_power(self, t_ns: int) -> bool:
        """The board's power supply at t_ns (the injector's board_power_loss windows): a board that
        loses power leaves the bus, and the frames in its controller's queue are gone. True if
        that changed anything."""
        hardware = self.injector.hardware
        if not hardware.windows:
            return False
        off = {BOARD} if BOARD in self.queues and not hardware.powered(t_ns / 1e9) else set()
        if off == self.unpowered:
            return False
        for node in off - self.unpowered:
            for tx in self.queues[node]:
                self._log(tx.msg, CHANNEL_DROPPED, t_ns)
                self.stats.dropped["power_loss"] += 1
            self.queues[node].clear()
        self.unpowered = off
        return True

    # --- input ----------------------------------------------------------------------------
    def submit(self, source: str, msg: can.Message, t_ns: int) -> None:
        """A node asks to send a frame at t_ns (its controller queues it)."""
        if source not in self.queues:
            raise ValueError(f"unknown node {source!r} (nodes: {', '.join(self.nodes)})")
        if self.injector.t0_ns is None and source == FLIGHT and msg.arbitration_id == self._cmd_id:
            self.injector.arm(t_ns)
        tx = Transmission(msg, source, t_ns, t_ns, self.listeners(source))
        outcome = self.injector.on_submit(tx)
        for dropped, reason in outcome.dropped:
            self._log(dropped, CHANNEL_DROPPED, t_ns)
            self.stats.dropped[reason] += 1
        for original in outcome.replaced:
            self._log(original, CHANNEL_REPLACED, t_ns)
        for queued in outcome.queued:
            if queued.held or queued.source == SOURCE_INJECTOR:
                self._held.append(queued)
                self._held.sort(key=lambda h: h.ready_ns)   # stable: equal times keep their order
                continue
            queue = self.queues[queued.source]
            if len(queue) >= self.tx_queue_frames:
                self._log(queued.msg, CHANNEL_DROPPED, t_ns)
                self.stats.dropped["tx_overflow"] += 1
                continue
            queue.append(queued)

    # --- time -----------------------------------------------------------------------------
    def run_until(self, t_ns: int) -> list[Delivery]:
        """Advance the bus to t_ns; the frames whose last bit passed by then, in order."""
        deliveries: list[Delivery] = []
        while True:
            if self.in_flight is not None:
                if self.in_flight.end_ns > t_ns:
                    break
                deliveries += self._complete(self.in_flight)
                self.in_flight = None
                continue
            start_ns = self._next_start_ns()
            due_ns = min(self.recover_at_ns.values(), default=None)
            if due_ns is not None and due_ns <= t_ns and (start_ns is None or due_ns <= start_ns):
                deliveries += self._restart_recovered(due_ns)   # in time order with the frames
                continue
            if start_ns is None or start_ns > t_ns:
                break
            if self._apply_power(start_ns):
                continue          # who is on the bus changed: the frame that starts may be another
            self._arbitrate(start_ns)
        self.now_ns = max(self.now_ns, t_ns)
        return deliveries

    def next_event_ns(self) -> int | None:
        """When run_until next has something to do (None: nothing pending). A frame in flight
        holds everything else until its end, a node's bus-off recovery too: run_until restarts
        the node after the frame, so the recovery's time may then be past."""
        if self.in_flight is not None:
            return self.in_flight.end_ns
        times = list(self.recover_at_ns.values())
        start = self._next_start_ns()
        if start is not None:
            times.append(start)
        return min(times) if times else None

    def _ready_heads(self) -> list[Transmission]:
        heads = [q[0] for s, q in self.queues.items() if q and self._on_bus(s)]
        held = self._held[:1]
        if held and held[0].after is not None and self._queued(held[0].after):
            held = []   # waits until the frame it follows has gone
        return heads + held

    def _queued(self, tx: Transmission) -> bool:
        return any(tx is queued for queued in self.queues.get(tx.source, ())) or any(tx is h for h in self._held)

    def _ready_ns(self, tx: Transmission) -> int:
        """When tx may start: an error-passive node that transmitted the last frame waits 8 more
        bits after the intermission (suspend transmission), and hears whatever starts meanwhile."""
        if not self._suspended_until_ns:
            return tx.ready_ns
        return max(tx.ready_ns, self._suspended_until_ns.get(tx.source, tx.ready_ns))

    def _next_start_ns(self) -> int | None:
        heads = self._ready_heads()
        readies = [self._ready_ns(tx) for tx in heads] if self._suspended_until_ns else [tx.ready_ns for tx in heads]
        babbler = self.injector.babbler()
        if babbler is not None:
            readies.append(babbler[1])
        if not readies:
            return None
        return max(self.bus_free_ns, min(readies))

    def _arbitrate(self, start_ns: int) -> None:
        """Bitwise arbitration: every ready transmitter sends its arbitration field; a recessive
        bit overwritten by a dominant one loses. Equal fields go on together: one frame if their
        frames are identical, else a bit error where they first differ: for every transmitter if
        an error-active one sent the recessive bit, else only for the error-passive ones that did
        (_without_passive_losers)."""
        contenders: list[tuple[tuple[int, ...], object]] = [
            (bittiming.message_arbitration_bits(tx.msg), tx) for tx in self._ready_heads()
            if (self._ready_ns(tx) if self._suspended_until_ns else tx.ready_ns) <= start_ns]
        babbler = self.injector.babbler()
        if babbler is not None and babbler[1] <= start_ns:
            contenders.append((bittiming.message_arbitration_bits(babbler[0].msg), babbler[0]))
        if self._suspended_until_ns:           # a suspension is over once a frame starts after it
            self._suspended_until_ns = {n: t for n, t in self._suspended_until_ns.items() if t > start_ns}
        if self._recovery:
            self._count_recessive_until(start_ns)  # the start of frame is dominant: a run ends here
        best = min(key for key, _ in contenders)
        winners = [item for key, item in contenders if key == best]
        passive_losers: tuple[Transmission, ...] = ()
        if len(winners) > 1:
            winners, passive_losers = self._without_passive_losers(winners)
        first = winners[0]
        if isinstance(first, Flood):
            if first.affected == 0:
                self.injector.record(start_ns, first.label, "injected", first.msg)  # first of many
            first.sent(start_ns)
            msg, tx = first.msg, None
        else:
            msg, tx = first.msg, first
        others = tuple(w for w in winners[1:] if isinstance(w, Transmission))
        frames = {_frame_identity(w.msg) for w in winners}
        bits = bittiming.frame_bits(msg)
        flight = _InFlight(tx, msg, start_ns, 0, passive_losers=passive_losers)
        if len(frames) > 1:
            # Equal arbitration fields, different frames: a bit error at the first differing bit.
            streams = [bittiming.stuffed_bits(w.msg) for w in winners]
            differ = min(_first_difference(streams[0], s) for s in streams[1:])
            bits = differ + 1 + bittiming.ERROR_FRAME_BITS
            flight.error, flight.collided = errors.BusError.BIT, others
        else:
            flight.together = others
            transmitters = {w.source for w in (*winners, *passive_losers) if isinstance(w, Transmission)}
            if transmitters <= set(self.nodes) and tx is not None and not any(
                    self._on_bus(n) for n in self.nodes if n not in transmitters):
                # Nobody else on the bus to acknowledge: ACK error after the ACK slot (CRC delimiter
                # and ACK slot, recessive). Error-passive transmitters' error flag is recessive too.
                if all(self._error_passive(t) for t in (tx, *others)):
                    bits = bits - bittiming.TAIL_BITS + 2 + PASSIVE_ERROR_FRAME_BITS
                    flight.recessive_tail_bits = 2 + PASSIVE_ERROR_FRAME_BITS
                else:
                    bits = bits - bittiming.TAIL_BITS + 2 + bittiming.ERROR_FRAME_BITS
                flight.error = errors.BusError.ACK
            else:
                flight.destroyed_by = self.injector.destroys(tx, start_ns) if tx is not None and tx.source in self.queues else None
                if flight.destroyed_by is not None:
                    bits = bits - bittiming.TAIL_BITS + bittiming.ERROR_FRAME_BITS
        flight.end_ns = start_ns + bittiming.duration_ns(bits, self.bitrate_bps)
        self.in_flight = flight
        self.bus_free_ns = flight.end_ns
        self._account_busy(start_ns, flight.end_ns)

    def _error_passive(self, item: object) -> bool:
        counters = self.counters.get(item.source) if isinstance(item, Transmission) else None
        return counters is not None and not counters.bus_off and \
            (counters.tec >= errors.PASSIVE_LIMIT or counters.rec >= errors.PASSIVE_LIMIT)

    def _without_passive_losers(self, winners: list) -> tuple[list, tuple[Transmission, ...]]:
        """Equal arbitration fields, different frames: at the first bit where they differ, the
        transmitters of a recessive bit read a dominant one, a bit error (ISO 11898-1). If one of
        them is error-active, its active error flag destroys the frame for all (the caller's
        collision). If all are error-passive, their error flags are recessive: nobody sees them,
        they drop out, and the frame goes on for the transmitters of the dominant bit (compared
        again from there). The babbler and the injector have no controller: taken as error-active."""
        losers: list[Transmission] = []
        while len({_frame_identity(w.msg) for w in winners}) > 1:
            streams = [bittiming.stuffed_bits(w.msg) for w in winners]
            at = min(_first_difference(streams[0], s) for s in streams[1:])
            sent = [s[at] if at < len(s) else 1 for s in streams]   # past its CRC: the recessive delimiter
            recessive = [w for w, bit in zip(winners, sent) if bit == 1]
            if not recessive or len(recessive) == len(winners) or not all(self._error_passive(w) for w in recessive):
                break
            losers += recessive
            winners = [w for w, bit in zip(winners, sent) if bit == 0]
        return winners, tuple(losers)

    def _flush_queue(self, node: str, t_ns: int) -> None:
        """Bus-off: the controller's transmit buffers are cleared (nothing stale is sent later)."""
        queue = self.queues[node]
        while queue:
            flushed = queue.popleft()
            self._log(flushed.msg, CHANNEL_DROPPED, t_ns)
            self.stats.dropped["bus_off_flush"] += 1

    def _complete(self, flight: _InFlight) -> list[Delivery]:
        if self._recovery:
            self._count_recessive_tail(flight)
        if flight.destroyed_by is not None or flight.error is not None:
            deliveries = self._transmission_error(flight)
        else:
            deliveries = self._transmitted(flight)
        if flight.passive_losers:
            deliveries += self._passive_losses(flight)
        # Suspend transmission (ISO 11898-1): an error-passive transmitter of this frame waits
        # 8 bits after the intermission before it may start again.
        transmitters = (flight.tx,) if not (flight.together or flight.collided or flight.passive_losers) \
            else (flight.tx, *flight.together, *flight.collided, *flight.passive_losers)
        for t in transmitters:
            if self._error_passive(t):
                self._suspended_until_ns[t.source] = flight.end_ns + bittiming.duration_ns(
                    SUSPEND_TRANSMISSION_BITS, self.bitrate_bps)
        return deliveries

    def _passive_losses(self, flight: _InFlight) -> list[Delivery]:
        """Error-passive transmitters that lost at a data bit: a bit error each (TEC + 8), and
        bus-off at the end of this frame if it takes them above 255; they retry otherwise."""
        deliveries: list[Delivery] = []
        for loser in flight.passive_losers:
            self.stats.bus_errors[errors.BusError.BIT.value] += 1
            deliveries += self._count(loser.source, flight.end_ns, transmit=True, ok=False, error=errors.BusError.BIT)
            if self.counters[loser.source].bus_off:
                self._go_bus_off(loser, flight)
        return deliveries

    def _transmitted(self, flight: _InFlight) -> list[Delivery]:
        """The frame went through: counters, capture, and the nodes that hear it."""
        tx = flight.tx
        deliveries: list[Delivery] = []
        transmitters = [t for t in (tx, *flight.together) if t is not None]
        for sender in transmitters:
            self._dequeue(sender)
            if sender.source in self.queues:
                deliveries += self._count(sender.source, flight.end_ns, transmit=True, ok=True)
        senders = {t.source for t in transmitters}
        senders.update(t.source for t in flight.passive_losers)
        hearing = tuple(n for n in self.nodes if n not in senders and self._on_bus(n))
        for node in hearing:
            deliveries += self._count(node, flight.end_ns, transmit=False, ok=True)
        stamped = _stamped(flight.msg, self.to_wall_s(flight.end_ns), CHANNEL_BUS)
        self.capture(stamped)
        self.stats.frames[p.frame_kind(self.protocol, flight.msg)] += 1
        if tx is None:
            return deliveries   # no node's acceptance filter takes the babbler's identifier
        if tx.source == FLIGHT and flight.msg.arbitration_id == self._cmd_id:
            key = "with_flood" if self.injector.flood_active(tx.submitted_ns) else "without_flood"
            self.stats.command_latency_ns[key].append(flight.end_ns - tx.submitted_ns)
        destinations = tuple(n for n in dict.fromkeys(d for t in transmitters for d in t.destinations)
                             if n not in senders and self._on_bus(n))
        return [Delivery(stamped, destinations)] + deliveries

    def _count(self, node: str, t_ns: int, *, transmit: bool, ok: bool,
               error: errors.BusError | None = None) -> list[Delivery]:
        """Apply one fault-confinement rule to a node; an error report when the controller would
        send one: every change of its state, and every error it transmitted except a missing ACK
        (a node alone retries back to back, thousands a second: SocketCAN reports those only with
        berr-reporting on, and a bridge forwarding each would fall behind the wall clock)."""
        counters = self.counters[node]
        before = counters.state
        if ok:
            after = counters.on_transmit_success() if transmit else counters.on_receive_success()
        else:
            after = counters.on_transmit_error(error) if transmit else counters.on_receive_error()
        self.stats.tec_max[node] = max(self.stats.tec_max[node], counters.tec)
        if after is before and (ok or not transmit or error is errors.BusError.ACK):
            return []
        report = errors.error_frame(after, counters.tec, rec=counters.rec, error=None if ok else error,
                                    transmitting=transmit, state_changed=after is not before,
                                    timestamp_s=self.to_wall_s(t_ns))
        return [self._report(report, node)]

    def _report(self, report: can.Message, node: str) -> Delivery:
        # The flight side's error frames are what its candump shows; others go to the accounting.
        report.channel = CHANNEL_BUS if node == FLIGHT else f"{CHANNEL_ERRORS}:{node}"
        self.capture(report)
        if node == FLIGHT:
            self.stats.error_frames += 1
        return Delivery(report, (node,))

    def _transmission_error(self, flight: _InFlight) -> list[Delivery]:
        """The frame was destroyed: error counters change; retry, or bus-off and drop it."""
        error = flight.error or errors.BusError.BIT
        self.stats.bus_errors[error.value] += 1
        deliveries: list[Delivery] = []
        transmitters = [t for t in (flight.tx, *flight.collided) if t is not None]
        for tx in transmitters:
            if tx.source not in self.queues:
                # The injector's frame in a collision: it gives up (no controller to retry it).
                self._dequeue(tx)
                self.injector.record(flight.end_ns, tx.fault or SOURCE_INJECTOR, "collided", tx.msg)
                continue
            deliveries += self._count(tx.source, flight.end_ns, transmit=True, ok=False, error=error)
            if self.counters[tx.source].bus_off:
                self._go_bus_off(tx, flight)
        senders = {t.source for t in (*transmitters, *flight.passive_losers)}
        for node in self.nodes:
            if node not in senders and self._on_bus(node) and error is not errors.BusError.ACK:
                deliveries += self._count(node, flight.end_ns, transmit=False, ok=False)
        return deliveries

    def _go_bus_off(self, tx: Transmission, flight: _InFlight) -> None:
        self._dequeue(tx)
        self._log(tx.msg, CHANNEL_DROPPED, flight.end_ns)
        self.stats.dropped["bus_off"] += 1
        self.stats.bus_off[tx.source] += 1
        self._flush_queue(tx.source, flight.end_ns)
        # The controller rejoins after it has seen 128 occurrences of 11 consecutive recessive bits
        # (ISO 11898-1), counted from the end of the error frame that took it bus-off: 1408 bit
        # times on an idle bus, more when frames pass meanwhile (_count_recessive_*). Whoever
        # caused it, collisions included. Only the error_frames fault adds its restart_delay_s
        # before the count (SocketCAN's restart-ms, a host restarting the controller).
        restart_s = 0.0
        if flight.destroyed_by is not None and tx is flight.tx:
            restart_s = flight.destroyed_by.spec.param("restart_delay_s")
        self._recovery[tx.source] = _Recovery(flight.end_ns, flight.end_ns + round(restart_s * 1e9))
        self._predict_recovery(tx.source)
        self.stats.bus_off_episodes_left_off += len(self.stats.bus_off_episodes) >= BUS_OFF_EPISODES_LISTED
        if len(self.stats.bus_off_episodes) < BUS_OFF_EPISODES_LISTED:
            self.stats.bus_off_episodes.append([tx.source, flight.end_ns, None])

    def _count_recessive_until(self, t_ns: int) -> None:
        """A frame starts at t_ns: the idle bus before it counts for each bus-off node, and its
        start-of-frame bit (dominant) ends the run of recessive bits."""
        for node, r in self._recovery.items():
            if t_ns > r.counted_ns:
                run = r.run_bits + (t_ns - r.counted_ns) * self.bitrate_bps // 1_000_000_000
                r.occurrences += run // RECESSIVE_RUN_BITS
                r.run_bits, r.counted_ns = 0, t_ns
                self._predict_recovery(node)

    def _count_recessive_tail(self, flight: _InFlight) -> None:
        """An attempt ended: its recessive tail counts for each bus-off node that watched it (a
        frame's stuffed bits hold no 6 equal bits, its tail 11 or more recessive ones)."""
        for node, r in self._recovery.items():
            if flight.end_ns > r.counted_ns:
                seen = min(flight.recessive_tail_bits,
                           (flight.end_ns - r.counted_ns) * self.bitrate_bps // 1_000_000_000)
                run = r.run_bits + seen
                r.occurrences += run // RECESSIVE_RUN_BITS
                r.run_bits, r.counted_ns = run % RECESSIVE_RUN_BITS, flight.end_ns
                self._predict_recovery(node)

    def _predict_recovery(self, node: str) -> None:
        """When the node rejoins if the bus stays idle from what has been counted (an idle bus is
        recessive: one occurrence every 11 bit times); a frame that starts first is counted anew."""
        r = self._recovery[node]
        left_bits = RECESSIVE_RUN_BITS * (RECOVERY_OCCURRENCES - r.occurrences) - r.run_bits
        self.recover_at_ns[node] = r.counted_ns + bittiming.duration_ns(max(0, left_bits), self.bitrate_bps)

    def _restart_recovered(self, t_ns: int) -> list[Delivery]:
        out = []
        for node, at_ns in list(self.recover_at_ns.items()):
            if at_ns <= t_ns:
                del self.recover_at_ns[node]
                recovery = self._recovery.pop(node)
                self.counters[node].restart()
                self.stats.bus_off_recovered[node] += 1
                self.stats.bus_off_time_ns[node] += at_ns - recovery.bus_off_ns
                self.stats.bus_off_longest_ns[node] = max(self.stats.bus_off_longest_ns[node], at_ns - recovery.bus_off_ns)
                for episode in self.stats.bus_off_episodes:
                    if episode[0] == node and episode[1] == recovery.bus_off_ns:
                        episode[2] = at_ns
                report = errors.error_frame(errors.ErrorState.ACTIVE, 0, restarted=True,
                                            timestamp_s=self.to_wall_s(at_ns))
                self.bus_free_ns = max(self.bus_free_ns, at_ns)
                out.append(self._report(report, node))
        return out

    def _dequeue(self, tx: Transmission) -> None:
        (self._held if tx.held or tx.source == SOURCE_INJECTOR else self.queues[tx.source]).remove(tx)

    # --- accounting -----------------------------------------------------------------------
    def _account_busy(self, start_ns: int, end_ns: int) -> None:
        self.stats.busy_ns += end_ns - start_ns
        t = start_ns
        while t < end_ns:  # split across load windows
            window = (t - self.t0_ns) // LOAD_WINDOW_NS
            window_end = self.t0_ns + (window + 1) * LOAD_WINDOW_NS
            self.stats.load_windows[window] += min(end_ns, window_end) - t
            t = window_end

    def _log(self, msg: can.Message, channel: str, t_ns: int) -> None:
        self.capture(_stamped(msg, self.to_wall_s(t_ns), channel))

    def report(self) -> dict:
        """Bus load, frames, drops, errors and command latency with and without a babbler."""
        elapsed_ns = max(1, self.now_ns - self.t0_ns)
        latency = {key: _percentiles_us(values) for key, values in self.stats.command_latency_ns.items()}
        return {
            "bitrate_bps": self.bitrate_bps,
            "elapsed_s": elapsed_ns / 1e9,
            "bus_load_pct": 100.0 * self.stats.busy_ns / elapsed_ns,
            "peak_load_pct": 100.0 * max(self.stats.load_windows.values(), default=0) / LOAD_WINDOW_NS,
            "load_timeline_pct": [[w * LOAD_WINDOW_NS / 1e9, 100.0 * busy / LOAD_WINDOW_NS]
                                  for w, busy in sorted(self.stats.load_windows.items())],
            "frames": dict(self.stats.frames),
            "dropped": dict(self.stats.dropped),
            "error_frames": self.stats.error_frames,
            "bus_off": dict(self.stats.bus_off),
            # Each bus-off and its recovery (128 x 11 recessive bits): counts and times per node,
            # and the first episodes (bus time; recovered_ns None: still bus-off at the end).
            "bus_off_recovered": dict(self.stats.bus_off_recovered),
            "bus_off_time_ns": dict(self.stats.bus_off_time_ns),
            "bus_off_longest_ns": dict(self.stats.bus_off_longest_ns),
            "bus_off_recovery_bits": bittiming.BUS_OFF_RECOVERY_BITS,
            "bus_off_episodes": [{"node": n, "bus_off_ns": off, "recovered_ns": back}
                                 for n, off, back in self.stats.bus_off_episodes],
            "bus_off_episodes_left_off": self.stats.bus_off_episodes_left_off,
            "tec_max": dict(self.stats.tec_max),
            "command_latency_us": latency,
            "faults_t0_ns": self.injector.t0_ns,
            # bus seconds per simulated second of the faults' start_s and duration_s (1 / time_factor
            # on a real-time run's wall clock); each fault's window as armed is in "faults"
            "fault_clock_scale": self.injector.wall_s_per_sim_s,
            "faults": self.injector.summary(),
        }


def _frame_identity(msg: can.Message) -> tuple:
    return (msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame, msg.is_fd, msg.dlc, bytes(msg.data))


def _first_difference(a: list[int], b: list[int]) -> int:
    """Index of the first bit where two transmitters differ (the shorter one's end if a prefix)."""
    for i, (x, y) in enumerate(zip(a, b)):
        if x != y:
            return i
    return min(len(a), len(b))


def _stamped(msg: can.Message, timestamp_s: float, channel: str) -> can.Message:
    return can.Message(timestamp=timestamp_s, arbitration_id=msg.arbitration_id, is_extended_id=msg.is_extended_id,
                       is_remote_frame=msg.is_remote_frame, is_error_frame=msg.is_error_frame, dlc=msg.dlc,
                       is_fd=msg.is_fd, data=bytes(msg.data), channel=channel, is_rx=False)


def _percentiles_us(values_ns: list[int]) -> dict:
    if not values_ns:
        return {"n": 0}
    ordered = sorted(values_ns)
    p99 = ordered[min(len(ordered) - 1, round(0.99 * (len(ordered) - 1)))]
    return {"n": len(ordered), "median": statistics.median(ordered) / 1e3, "p99": p99 / 1e3, "max": ordered[-1] / 1e3}


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

    # A timestamp further from the arrival than this is another host's clock: use the arrival.
    MAX_TRANSPORT_DELAY_NS = 1_000_000_000
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
        self._wall_minus_monotonic_ns = time.time_ns() - time.monotonic_ns()
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
                arrivals.append((self._sent_ns(msg, arrival_ns), self._node(side, sender[0] if sender else None), msg))
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

    def _sent_ns(self, msg: can.Message, arrival_ns: int) -> int:
        if msg.timestamp:
            sent_ns = round(msg.timestamp * 1e9) - self._wall_minus_monotonic_ns
            if 0 <= arrival_ns - sent_ns <= self.MAX_TRANSPORT_DELAY_NS:
                return sent_ns
        return arrival_ns

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
