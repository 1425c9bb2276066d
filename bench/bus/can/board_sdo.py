"""The board's SDO server: canopen's, driven by the board's own loop and clock.

A CANopen tool reads and writes the board's object dictionary (mtq.eds) over SDO: identity
(0x1018), device name (0x1008), the error register and error history (0x1001, 0x1003), the
heartbeat time (0x1017), the EMCY inhibit time (0x1015) and the command timeout (0x2100).
Transfers are canopen's `SdoServer` in a `LocalNode`; the network is passive: the board hands
it each SDO request from its own `handle` (no listener thread), and its answers go out through
the board's own send. Nothing here runs a timer: the board produces its heartbeat on its own
clock (real or simulated), so canopen's NMT slave heartbeat task is never started.

SDO carries no authentication (CiA 301 has none), so on the secoc profile, where the board obeys
only authenticated commands and NMT, the dictionary is read-only over SDO: a write from anyone on
the bus could otherwise lengthen the command timeout (the board would hold a stale command for
longer) or silence the heartbeat. Writes are served on the e2e profile only.
"""
from __future__ import annotations

import struct
from typing import Callable

import can
import canopen
from canopen.sdo import SdoAbortedError

from bench.bus.can import canopen_od as od_

SDO_ABORT_VALUE_TOO_LOW = 0x06090032      # CiA 301 SDO abort codes
SDO_ABORT_LOCAL_CONTROL = 0x08000021      # data cannot be stored because of local control
SDO_FRAME_BYTES = 8


class _InertTask:
    """What canopen's NMT slave gets instead of a periodic-send thread (see module docstring)."""

    def stop(self) -> None:
        pass

    def update(self, data) -> None:
        pass


class _BoardNetwork(canopen.Network):
    """A canopen network with no thread of its own: frames come in by `notify`, go out by `send`."""

    def __init__(self, send: Callable[[can.Message], None]):
        super().__init__(bus=None)
        self._send = send

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self._send(can.Message(arbitration_id=can_id, is_extended_id=can_id > 0x7FF, data=bytes(data),
                               is_remote_frame=remote))

    def send_periodic(self, can_id, data, period, remote=False):
        return _InertTask()


class BoardSdoServer:
    """SDO access to one board's parameters.

    read_parameter(field) -> seconds and write_parameter(field, seconds) are the board's own
    BoardConfig fields (canopen_od.PARAMETERS); error_register() and error_history() (newest
    first) its emergency state.
    """

    def __init__(self, node_id: int, send: Callable[[can.Message], None],
                 read_parameter: Callable[[str], float], write_parameter: Callable[[str, float], None],
                 error_register: Callable[[], int], error_history: Callable[[], list[int]],
                 clear_error_history: Callable[[], None], writable: bool = True):
        self.writable = writable
        self.node = canopen.LocalNode(node_id, od_.object_dictionary(node_id))
        self.network = _BoardNetwork(send)
        self.network.add_node(self.node)
        self.request_id = od_.SDO_REQUEST_BASE + node_id
        self._read_parameter = read_parameter
        self._write_parameter = write_parameter
        self._error_register = error_register
        self._error_history = error_history
        self._clear_error_history = clear_error_history
        self.refused_writes = 0     # SDO writes refused on the secoc profile (board.json)
        self._fields = {index: (field, per_s) for field, (index, per_s) in od_.PARAMETERS.items()}
        self.node.add_read_callback(self._on_read)
        self.node.add_write_callback(self._on_write)

    def is_request(self, msg: can.Message) -> bool:
        return msg.arbitration_id == self.request_id and not msg.is_extended_id

    def handle(self, msg: can.Message) -> bool:
        """Serve one SDO request; False (not served) for a frame that is no SDO request (remote,
        FD, not 8 bytes: CiA 301 SDO frames are classic 8-byte data frames)."""
        if msg.is_remote_frame or msg.is_error_frame or msg.is_fd or len(msg.data) != SDO_FRAME_BYTES:
            return False
        self.network.notify(msg.arbitration_id, bytes(msg.data), msg.timestamp)
        return True

    def _on_read(self, index: int, subindex: int, od) -> int | None:
        if index in self._fields:
            field, per_s = self._fields[index]
            return round(self._read_parameter(field) * per_s)
        if index == 0x1001:
            return self._error_register()
        if index == 0x1003:
            history = self._error_history()
            if subindex == 0:
                return len(history)
            return history[subindex - 1] if subindex <= len(history) else 0
        return None    # the EDS's value (identity, name, PDO parameters)

    def _on_write(self, index: int, subindex: int, od, data: bytes) -> None:
        if not self.writable:
            self.refused_writes += 1
            raise SdoAbortedError(SDO_ABORT_LOCAL_CONTROL)
        if index == 0x1003 and subindex == 0:
            if data != b"\x00":
                raise SdoAbortedError(0x06090030)   # CiA 301: only 0 may be written (clears the history)
            self._clear_error_history()
        elif index in self._fields:
            field, per_s = self._fields[index]
            value, = struct.unpack("<H", data)
            if value == 0 and index == od_.COMMAND_TIMEOUT:   # 0 is "none" for the heartbeat and the inhibit time
                raise SdoAbortedError(SDO_ABORT_VALUE_TOO_LOW)
            self._write_parameter(field, value / per_s)
