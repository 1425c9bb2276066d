"""What the live view's forwarding thread does with each sample (a part of LiveView,
bench/live/node.py): it checks the sample's tag and decodes it, logs it on its Foxglove channel at
the run's simulated time, and derives from it the frame transforms (/tf), the attitude and estimate
errors, the events' log lines (/events) and the criteria's figures; CAN frames are decoded with
the run's DBC as the recorder does.

Forwarding uses LiveView's ctx, scenario, prefix, kinds, sim, metrics, verifier, inbox, channels,
can_channels, can_step, can_protocol, derived, tf, log, forwarded and _can_frame_json, and its
_tick between batches.
"""
from __future__ import annotations

import json
import math
import queue
from collections import Counter

import numpy as np

from bench.bus import keys
from bench.bus.schemas import (
    AttitudeEstimate, AttitudeTruth, BusEvent, DeadlineEvent, FaultWindow, MalformedMessage, TruthState, decode,
)
from bench.live.channels import ERROR_TOPIC, ESTIMATE_ERROR_TOPIC, EVENTS_TOPIC, TF_TOPIC

CAN_STEP_TOPICS = (keys.CAN_STEP_FLIGHT, keys.CAN_STEP_BUS)
# Driver events that say the bus is well again (bench.studies.fault_bus.BENIGN_EVENTS): info, not warnings.
BENIGN_EVENTS = frozenset({"heartbeat_resumed", "board_error_reset", "error_active", "bus_restarted", "host_overrun"})


def _ns(sim_s: float) -> int:
    return max(0, int(round(sim_s * 1e9))) if math.isfinite(sim_s) else 0


class Forwarding:
    """The forwarding thread's work (a mixin of LiveView)."""

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
