"""CAN fault confinement: the transmit error counter (ISO 11898-1) and SocketCAN error frames.

A transmitter's TEC rises by 8 for each error it is involved in and falls by 1 for each frame it
sends successfully. At 96 the controller warns, at 128 it is error-passive, above 255 it goes
bus-off and takes no part in the bus until it has seen 128 x 11 recessive bits and (SocketCAN's
`restart-ms`) its driver restarts it. The bus model reports these changes to the transmitting node
as SocketCAN error frames (linux/can/error.h), which python-can delivers with is_error_frame set,
so the driver reads them the same way from a kernel bus and from the bus model.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass

import can

# linux/can/error.h: error class in the identifier, details in the data bytes.
CAN_ERR_CRTL = 0x00000004
CAN_ERR_PROT = 0x00000008
CAN_ERR_BUSOFF = 0x00000040
CAN_ERR_RESTARTED = 0x00000100
CAN_ERR_CNT = 0x00000200          # data[6] = TEC, data[7] = REC
CAN_ERR_CRTL_TX_WARNING = 0x08    # data[1]
CAN_ERR_CRTL_TX_PASSIVE = 0x20
CAN_ERR_CRTL_ACTIVE = 0x40
CAN_ERR_PROT_BIT = 0x02           # data[2]

WARNING_LIMIT = 96
PASSIVE_LIMIT = 128
BUS_OFF_LIMIT = 256
TEC_STEP_ON_ERROR = 8
BUS_OFF_RECOVERY_BITS = 128 * 11


class ErrorState(enum.Enum):
    ACTIVE = "error_active"
    WARNING = "error_warning"
    PASSIVE = "error_passive"
    BUS_OFF = "bus_off"


@dataclass
class TransmitErrorCounter:
    tec: int = 0
    bus_off: bool = False

    @property
    def state(self) -> ErrorState:
        if self.bus_off:
            return ErrorState.BUS_OFF
        if self.tec >= PASSIVE_LIMIT:
            return ErrorState.PASSIVE
        if self.tec >= WARNING_LIMIT:
            return ErrorState.WARNING
        return ErrorState.ACTIVE

    def on_error(self) -> ErrorState:
        self.tec += TEC_STEP_ON_ERROR
        if self.tec >= BUS_OFF_LIMIT:
            self.bus_off = True
        return self.state

    def on_success(self) -> ErrorState:
        self.tec = max(0, self.tec - 1)
        return self.state

    def restart(self) -> ErrorState:
        """Recovered from bus-off: counters start again at zero."""
        self.tec, self.bus_off = 0, False
        return self.state


def error_frame(state: ErrorState, tec: int, *, restarted: bool = False, timestamp_s: float = 0.0) -> can.Message:
    """The SocketCAN error frame a controller reports after an error, in `state`, with `tec`."""
    class_bits = CAN_ERR_PROT | CAN_ERR_CNT
    data = bytearray(8)
    data[2] = CAN_ERR_PROT_BIT
    data[6] = min(tec, 255)
    if restarted:
        class_bits = CAN_ERR_RESTARTED | CAN_ERR_CRTL | CAN_ERR_CNT
        data[1] = CAN_ERR_CRTL_ACTIVE
        data[2] = 0
    elif state is ErrorState.BUS_OFF:
        class_bits |= CAN_ERR_BUSOFF
    elif state is ErrorState.PASSIVE:
        class_bits |= CAN_ERR_CRTL
        data[1] = CAN_ERR_CRTL_TX_PASSIVE
    elif state is ErrorState.WARNING:
        class_bits |= CAN_ERR_CRTL
        data[1] = CAN_ERR_CRTL_TX_WARNING
    return can.Message(arbitration_id=class_bits, is_error_frame=True, is_extended_id=False,
                       data=bytes(data), timestamp=timestamp_s)


def read_error_frame(msg: can.Message) -> tuple[ErrorState, bool]:
    """(controller state, restarted) that a SocketCAN error frame reports."""
    class_bits = msg.arbitration_id
    data = bytes(msg.data) + bytes(8 - len(msg.data))
    if class_bits & CAN_ERR_RESTARTED:
        return ErrorState.ACTIVE, True
    if class_bits & CAN_ERR_BUSOFF:
        return ErrorState.BUS_OFF, False
    if class_bits & CAN_ERR_CRTL and data[1] & CAN_ERR_CRTL_TX_PASSIVE:
        return ErrorState.PASSIVE, False
    if class_bits & CAN_ERR_CRTL and data[1] & CAN_ERR_CRTL_TX_WARNING:
        return ErrorState.WARNING, False
    if class_bits & CAN_ERR_CNT:
        tec = data[6]
        if tec >= PASSIVE_LIMIT:
            return ErrorState.PASSIVE, False
        if tec >= WARNING_LIMIT:
            return ErrorState.WARNING, False
    return ErrorState.ACTIVE, False
