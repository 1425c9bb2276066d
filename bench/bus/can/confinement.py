"""Fault confinement on the modelled CAN bus (a part of BusModel, bench/bus/can/busmodel.py):
each attempt's outcome applied to the nodes' error counters by the rules of ISO 11898-1
(bench/bus/can/errors.py), the error reports a controller would send, bus-off (the frame dropped,
the transmit queue flushed) and the recovery after 128 occurrences of 11 consecutive recessive
bits, counted bit for bit as frames pass.

FaultConfinement reads and keeps BusModel's state: counters, queues, nodes, stats, injector,
bitrate_bps, bus_free_ns, recover_at_ns, _recovery, capture, to_wall_s; and calls its _on_bus,
_dequeue and _log.
"""
from __future__ import annotations

from dataclasses import dataclass

import can

from bench.bus.can import bittiming, errors
from bench.bus.can.bus_frames import (CHANNEL_BUS, CHANNEL_DROPPED, CHANNEL_ERRORS, FLIGHT, RECESSIVE_RUN_BITS,
                                      Delivery, InFlight)
from bench.bus.can.injector import SOURCE_INJECTOR, Transmission

RECOVERY_OCCURRENCES = bittiming.BUS_OFF_RECOVERY_BITS // RECESSIVE_RUN_BITS   # 128
BUS_OFF_EPISODES_LISTED = 100                             # the report lists the first ones; counts cover all


@dataclass
class Recovery:
    """A bus-off node watching the bus for the 128 occurrences of 11 consecutive recessive bits
    after which it rejoins (ISO 11898-1), counted bit for bit from `counted_ns` on."""
    bus_off_ns: int
    counted_ns: int             # the bus is counted up to here (after a restart delay: from its end)
    run_bits: int = 0           # recessive bits of the current run not yet an occurrence
    occurrences: int = 0


class FaultConfinement:
    """The error counters, error reports, bus-off and recovery of BusModel's nodes."""

    def _error_passive(self, item: object) -> bool:
        counters = self.counters.get(item.source) if isinstance(item, Transmission) else None
        return counters is not None and not counters.bus_off and \
            (counters.tec >= errors.PASSIVE_LIMIT or counters.rec >= errors.PASSIVE_LIMIT)

    def _flush_queue(self, node: str, t_ns: int) -> None:
        """Bus-off: the controller's transmit buffers are cleared (nothing stale is sent later)."""
        queue = self.queues[node]
        while queue:
            flushed = queue.popleft()
            self._log(flushed.msg, CHANNEL_DROPPED, t_ns)
            self.stats.dropped["bus_off_flush"] += 1

    def _passive_losses(self, flight: InFlight) -> list[Delivery]:
        """Error-passive transmitters that lost at a data bit: a bit error each (TEC + 8), and
        bus-off at the end of this frame if it takes them above 255; they retry otherwise."""
        deliveries: list[Delivery] = []
        for loser in flight.passive_losers:
            self.stats.bus_errors[errors.BusError.BIT.value] += 1
            deliveries += self._count(loser.source, flight.end_ns, transmit=True, ok=False, error=errors.BusError.BIT)
            if self.counters[loser.source].bus_off:
                self._go_bus_off(loser, flight)
        return deliveries

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

    def _transmission_error(self, flight: InFlight) -> list[Delivery]:
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

    def _go_bus_off(self, tx: Transmission, flight: InFlight) -> None:
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
        self._recovery[tx.source] = Recovery(flight.end_ns, flight.end_ns + round(restart_s * 1e9))
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

    def _count_recessive_tail(self, flight: InFlight) -> None:
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
