"""What the magnetorquer board sends (a part of MagnetorquerBoard, bench/bus/can/board.py): its
telemetry, the set-point echo, emergency frames no two closer than the EMCY inhibit time (the error
register and history they set), each protected frame with its own alive counter; nothing without
power, and a send that fails is counted, never fatal.

BoardTransmitter uses MagnetorquerBoard's bus, protocol, config, state, nmt_state, rejected, sent,
error_register, error_history, _powered, _tx_counter, _pending_emcy, _last_emcy_s and its
applied_dipole_am2 and setpoint_am2.
"""
from __future__ import annotations

import logging

import can

from bench.bus.can import protocol as p

# The board's logger: these are its messages, as before its sending had a module of its own.
log = logging.getLogger("bench.bus.can.board")

ERROR_REGISTER_GENERIC = 0x01
ERROR_REGISTER_COMMUNICATION = 0x10
ERROR_HISTORY_ENTRIES = 4        # 0x1003's standard error fields in mtq.eds


class BoardTransmitter:
    """The board's frames out (a mixin of MagnetorquerBoard)."""

    def _emergency(self, error_code: int, e2e_status: int, counter: int | None, now_s: float,
                   error_register: int = ERROR_REGISTER_GENERIC | ERROR_REGISTER_COMMUNICATION) -> None:
        """Send an EMCY now, or when the inhibit time since the last one has passed. Waiting EMCYs
        queue in order; one of the same error code as the last waiting one replaces it (a burst
        of rejections is one report; RejectedFrames carries the running count)."""
        if self.nmt_state == p.NMT_STOPPED:
            return   # CiA 301: a stopped node sends only its heartbeat
        emcy = {"ErrorCode": error_code, "ErrorRegister": error_register, "E2eStatus": e2e_status,
                "RejectedCounter": counter or 0}
        if self._pending_emcy and self._pending_emcy[-1]["ErrorCode"] == error_code:
            self._pending_emcy[-1] = emcy
        else:
            self._pending_emcy.append(emcy)
        self._flush_emergency(now_s)

    def _flush_emergency(self, now_s: float) -> None:
        if not self._pending_emcy:
            return
        if self._last_emcy_s is not None and now_s - self._last_emcy_s < self.config.emcy_inhibit_s:
            return
        signals = self._pending_emcy.pop(0) | {"RejectedFrames": min(sum(self.rejected.values()), 0xFFFF)}
        self._last_emcy_s = now_s
        self.error_register = signals["ErrorRegister"]
        if signals["ErrorCode"] != p.EMCY_NO_ERROR:
            self.error_history.appendleft(signals["ErrorCode"])
        self._send(self.protocol.encode(p.EMCY, signals))

    # --- sending --------------------------------------------------------------------------
    def _send_telemetry(self) -> None:
        s = self.state
        dipole = self.applied_dipole_am2
        self._send(self._protected(p.TLM_DIPOLE, {
            "SafeState": s.safe_state, "ActuationPaused": s.actuation_paused,
            "CommandTimeout": s.command_timeout, "Saturated": s.saturated,
            **{f"AppliedDipole{a}": float(v) for a, v in zip(p.AXES, dipole)},
        }))
        self._send(self._protected(p.TLM_COIL, {
            "CommandRejected": s.command_rejected_since_tlm, "OverTemperature": False,
            **{f"CoilCurrent{a}": float(v) for a, v in zip(p.AXES, s.coil_current_a)},
            "Temperature": self.config.ambient_temperature_c, "LastCommandCounter": s.last_command_counter,
        }))
        s.command_rejected_since_tlm = False

    def _echo_setpoint(self, command_applied: bool) -> None:
        """MTQ_TLM_SETPOINT (config.setpoint_echo): what the coil drivers are set to now, and the
        counter of the command applied last; a TPDO, so only when operational."""
        if not self.config.setpoint_echo or self.nmt_state != p.NMT_OPERATIONAL:
            return
        s = self.state
        self._send(self._protected(p.TLM_SETPOINT, {
            "CommandCounter": s.last_command_counter, "CommandApplied": command_applied,
            "SafeState": s.safe_state, "ActuationPaused": s.actuation_paused,
            **{f"Setpoint{a}": float(v) for a, v in zip(p.AXES, self.setpoint_am2)},
        }))

    def _protected(self, name: str, signals: dict) -> can.Message:
        counter = self._tx_counter[name]
        self._tx_counter[name] = (counter + 1) % p.COUNTER_MODULO
        return self.protocol.encode(name, signals, counter)

    def _send(self, msg: can.Message) -> None:
        if not self._powered:
            return
        try:
            self.bus.send(msg)
            self.sent[p.frame_kind(self.protocol, msg)] += 1
        except can.CanError as exc:  # a full or broken bus must not kill the board
            self.sent["send_failed"] += 1
            log.warning("send failed: %s", exc)
