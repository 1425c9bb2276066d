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

The parts: the frames and nodes they share (bus_frames.py), fault confinement with bus-off and
recovery (confinement.py); the model on the wall clock is RealTimeBridge (realtime_bridge.py).
"""
from __future__ import annotations

import statistics
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Callable

import can
import numpy as np

from bench.bus.can import bittiming, errors
from bench.bus.can import protocol as p
from bench.bus.can.bus_frames import (BOARD, CHANNEL_BUS, CHANNEL_DROPPED, CHANNEL_REPLACED, FLIGHT, NODES, Delivery,
                                      InFlight, stamped_frame)
from bench.bus.can.confinement import FaultConfinement, Recovery
from bench.bus.can.injector import SOURCE_INJECTOR, FaultInjector, Flood, Transmission
from bench.bus.spill import SpilledRows, WindowCounter

LOAD_WINDOW_NS = 100_000_000
PASSIVE_ERROR_FRAME_BITS = 6 + 8 + 3                      # passive (recessive) error flag, delimiter, intermission
SUSPEND_TRANSMISSION_BITS = 8                             # an error-passive transmitter's wait after intermission


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


class BusModel(FaultConfinement):
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
        self._recovery: dict[str, Recovery] = {}
        self._suspended_until_ns: dict[str, int] = {}   # error-passive transmitters (suspend transmission)
        self.in_flight: InFlight | None = None
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
        flight = InFlight(tx, msg, start_ns, 0, passive_losers=passive_losers)
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

    def _complete(self, flight: InFlight) -> list[Delivery]:
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

    def _transmitted(self, flight: InFlight) -> list[Delivery]:
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
        stamped = stamped_frame(flight.msg, self.to_wall_s(flight.end_ns), CHANNEL_BUS)
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
        self.capture(stamped_frame(msg, self.to_wall_s(t_ns), channel))

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


def _percentiles_us(values_ns: list[int]) -> dict:
    if not values_ns:
        return {"n": 0}
    ordered = sorted(values_ns)
    p99 = ordered[min(len(ordered) - 1, round(0.99 * (len(ordered) - 1)))]
    return {"n": len(ordered), "median": statistics.median(ordered) / 1e3, "p99": p99 / 1e3, "max": ordered[-1] / 1e3}
