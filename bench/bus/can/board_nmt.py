"""The magnetorquer board as a CiA 301 NMT slave (a part of MagnetorquerBoard, bench/bus/can/board.py):
boot (the boot-up heartbeat, then pre-operational), start, stop and enter-pre-operational (the
coils off when it leaves operational), reset node and reset communication (its parameters restored
from the object dictionary, booted again); on the "secoc" profile only an authenticated NMT frame
(MTQ_NMT_AUTH, MAC and freshness verified) changes its state.

NmtSlave reads and keeps MagnetorquerBoard's state: protocol, config, _configured, state, nmt_state,
nmt_name, nmt_freshness, e2e, power_log, _tx_counter, _pending_emcy, the schedule of its periodic
frames; and calls its update, _send and _reject.
"""
from __future__ import annotations

import math

import can
import msgspec
import numpy as np

from bench.bus.can import canopen_od
from bench.bus.can import protocol as p
from bench.bus.can import secoc


class NmtSlave:
    """Boot and the NMT state machine (a mixin of MagnetorquerBoard)."""

    def start(self, now_s: float) -> None:
        """Boot: announce ourselves (CANopen boot-up heartbeat), enter pre-operational, schedule
        the periodic frames."""
        if self._started_s is None:
            self._started_s = self._last_update_s = now_s
        self._send(self.protocol.encode(p.HEARTBEAT, {"NmtState": p.NMT_BOOT_UP}))
        self.nmt_state = p.NMT_PRE_OPERATIONAL
        self._next_heartbeat_s = self._first_heartbeat_s(now_s)
        self._next_telemetry_s = now_s + self.config.telemetry_period_s

    # --- CiA 301 NMT slave ----------------------------------------------------------------
    def _on_nmt(self, frame: p.Frame, now_s: float) -> None:
        if int(frame.signals["NodeId"]) not in (0, self.protocol.node_id):
            return
        command = int(frame.signals["Command"])
        if command == p.NMT_START and self.nmt_state != p.NMT_OPERATIONAL:
            self.nmt_state = p.NMT_OPERATIONAL
            if self.power_log and self.power_log[-1]["event"] == "booted":
                self.power_log.append({"event": "operational", "t_s": now_s})
            self._last_command_s = now_s            # the command timeout runs from the start
            self.e2e.reset()
        elif command in (p.NMT_STOP, p.NMT_ENTER_PRE_OPERATIONAL):
            self.nmt_state = p.NMT_STOPPED if command == p.NMT_STOP else p.NMT_PRE_OPERATIONAL
            self._coils_off(now_s)
        elif command in (p.NMT_RESET_NODE, p.NMT_RESET_COMMUNICATION):
            self._coils_off(now_s)
            # CiA 301: reset communication restores the communication parameters, reset node all.
            restored = canopen_od.PARAMETERS if command == p.NMT_RESET_NODE else canopen_od.COMMUNICATION_PARAMETERS
            self.config = msgspec.structs.replace(self.config, **{f: getattr(self._configured, f) for f in restored})
            self.e2e.reset()
            self._tx_counter.clear()
            self._pending_emcy.clear()
            self.start(now_s)                       # boot-up heartbeat, pre-operational

    def _nmt_authentic(self, frame: p.Frame, msg: can.Message, now_s: float) -> bool:
        """Whether an NMT frame may change the NMT state: on "e2e" any plain NMT frame; on "secoc"
        only MTQ_NMT_AUTH with a verified MAC and freshness value. Refusals are counted and
        reported (EMCY) like rejected commands; they change no state."""
        if frame.name != self.nmt_name:
            if self.nmt_freshness is None:
                return False    # MTQ_NMT_AUTH on an e2e bus: not this board's protocol
            status = p.E2EStatus.NOT_AUTHENTICATED
        else:
            if self.nmt_freshness is None:
                return True
            verdict, freshness, _ = self.nmt_freshness.verify(bytes(msg.data), now_s)
            if verdict is secoc.Verdict.OK:
                self.nmt_freshness.accept(freshness)
                return True
            status = p.E2EStatus[verdict.value]
        self._reject(f"NMT_{status.name}", None, p.EMCY_E2E_CHECK_FAILED, int(status), now_s)
        return False

    def _first_heartbeat_s(self, now_s: float) -> float:
        period_s = self.config.heartbeat_period_s
        return now_s + period_s if period_s > 0 else math.inf     # 0x1017 = 0: no heartbeat

    def _coils_off(self, now_s: float) -> None:
        """Leaving operational: no commands will come, the coils must not hold the last one."""
        s = self.state
        self.update(now_s)
        s.target_dipole_am2 = np.zeros(3)
        s.mode = p.MODE_OFF
        changed = not s.safe_state
        s.safe_state = True
        s.command_timeout = False
        self._last_command_s = None
        self._next_no_data_s = None
        if changed and self.on_coils_changed is not None:
            self.on_coils_changed(s)
