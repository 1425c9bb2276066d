"""CAN fault confinement (ISO 11898-1) and the SocketCAN error frames that report it.

Each node has a transmit and a receive error counter (TEC, REC), changed by the standard's rules
(ISO 11898-1:2015, 12.1.4):
- a transmitter that sends an error flag: TEC + 8 (rule 3), except an error-passive transmitter
  whose error is a missing ACK (exception 1: a node alone on the bus stays error-passive, never
  goes bus-off);
- a receiver that detects an error: REC + 1 (rule 1);
- a successful transmission: TEC - 1 (rule 7); a successful reception: REC - 1, or back to 119
  from above 127 (rule 8: "a value between 119 and 127", 119 here);
- error-passive when TEC or REC exceeds 127, bus-off when TEC exceeds 255; back from bus-off
  (after 128 x 11 recessive bits) with both counters at zero.
SocketCAN also reports the warning level (96). The bus model reports each error and each change
of state to the node concerned as a SocketCAN error frame (linux/can/error.h), which python-can
delivers with is_error_frame set, so the driver reads them the same way from a kernel bus.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass

import can

# linux/can/error.h: error class in the identifier, details in the data bytes.
CAN_ERR_CRTL = 0x00000004          # data[1]
CAN_ERR_PROT = 0x00000008          # data[2] type, data[3] location
CAN_ERR_ACK = 0x00000020
CAN_ERR_BUSOFF = 0x00000040
CAN_ERR_BUSERROR = 0x00000080
CAN_ERR_RESTARTED = 0x00000100
CAN_ERR_CNT = 0x00000200           # data[6] = TEC, data[7] = REC
CAN_ERR_CRTL_RX_WARNING = 0x04
CAN_ERR_CRTL_TX_WARNING = 0x08
CAN_ERR_CRTL_RX_PASSIVE = 0x10
CAN_ERR_CRTL_TX_PASSIVE = 0x20
CAN_ERR_CRTL_ACTIVE = 0x40
CAN_ERR_PROT_BIT = 0x01            # single bit error (0x02 is FORM)
CAN_ERR_PROT_FORM = 0x02
CAN_ERR_PROT_STUFF = 0x04
CAN_ERR_PROT_BIT0 = 0x08           # unable to send a dominant bit
CAN_ERR_PROT_BIT1 = 0x10           # unable to send a recessive bit
CAN_ERR_PROT_TX = 0x80             # the error occurred on transmission
CAN_ERR_PROT_LOC_DATA = 0x0A
CAN_ERR_PROT_LOC_ACK = 0x19

WARNING_LIMIT = 96
PASSIVE_LIMIT = 128
BUS_OFF_LIMIT = 256
TEC_STEP_ON_ERROR = 8
REC_STEP_ON_ERROR = 1
REC_AFTER_PASSIVE_RECEPTION = 119
BUS_OFF_RECOVERY_BITS = 128 * 11


class ErrorState(enum.Enum):
    ACTIVE = "error_active"
    WARNING = "error_warning"
    PASSIVE = "error_passive"
    BUS_OFF = "bus_off"


class BusError(enum.Enum):
    """What went wrong in one transmission (SocketCAN protocol-error type or ACK)."""
    BIT = "bit"            # the node read back another bit than it sent (e.g. an equal-id collision)
    STUFF = "stuff"
    FORM = "form"
    ACK = "ack"            # no other node acknowledged

    @property
    def prot_type(self) -> int:
        return {BusError.BIT: CAN_ERR_PROT_BIT, BusError.STUFF: CAN_ERR_PROT_STUFF,
                BusError.FORM: CAN_ERR_PROT_FORM, BusError.ACK: 0}[self]


@dataclass
class ErrorCounters:
    """One node's TEC and REC and the state they put it in."""
    tec: int = 0
    rec: int = 0
    bus_off: bool = False

    @property
    def state(self) -> ErrorState:
        if self.bus_off:
            return ErrorState.BUS_OFF
        if self.tec >= PASSIVE_LIMIT or self.rec >= PASSIVE_LIMIT:
            return ErrorState.PASSIVE
        if self.tec >= WARNING_LIMIT or self.rec >= WARNING_LIMIT:
            return ErrorState.WARNING
        return ErrorState.ACTIVE

    def on_transmit_error(self, error: BusError = BusError.BIT) -> ErrorState:
        if error is BusError.ACK and self.state is ErrorState.PASSIVE:
            return self.state          # exception 1 of rule 3
        self.tec += TEC_STEP_ON_ERROR
        if self.tec >= BUS_OFF_LIMIT:
            self.bus_off = True
        return self.state

    def on_receive_error(self) -> ErrorState:
        if not self.bus_off:
            self.rec = min(self.rec + REC_STEP_ON_ERROR, 255)
        return self.state

    def on_transmit_success(self) -> ErrorState:
        self.tec = max(0, self.tec - 1)
        return self.state

    def on_receive_success(self) -> ErrorState:
        if self.rec >= PASSIVE_LIMIT:
            self.rec = REC_AFTER_PASSIVE_RECEPTION
        elif self.rec > 0:
            self.rec -= 1
        return self.state

    # The names of the transmit-only model this class replaces.
    on_error = on_transmit_error
    on_success = on_transmit_success

    def restart(self) -> ErrorState:
        """Recovered from bus-off: counters start again at zero."""
        self.tec, self.rec, self.bus_off = 0, 0, False
        return self.state


TransmitErrorCounter = ErrorCounters


def error_frame(state: ErrorState, tec: int, *, rec: int = 0, restarted: bool = False,
                error: BusError | None = BusError.BIT, transmitting: bool = True,
                state_changed: bool = True, timestamp_s: float = 0.0) -> can.Message:
    """The SocketCAN error frame a controller reports: the bus error it saw (if any), its state
    (when it changed, or always for bus-off and restart) and its counters."""
    data = bytearray(8)
    class_bits = CAN_ERR_CNT
    data[6], data[7] = min(tec, 255), min(rec, 255)
    if restarted:
        return can.Message(arbitration_id=CAN_ERR_RESTARTED | CAN_ERR_CRTL | CAN_ERR_CNT, is_error_frame=True,
                           is_extended_id=False, data=bytes([0, CAN_ERR_CRTL_ACTIVE, 0, 0, 0, 0, 0, 0]),
                           timestamp=timestamp_s)
    if error is BusError.ACK:
        class_bits |= CAN_ERR_ACK | CAN_ERR_BUSERROR
        data[3] = CAN_ERR_PROT_LOC_ACK
    elif error is not None:
        class_bits |= CAN_ERR_PROT | CAN_ERR_BUSERROR
        data[2] = error.prot_type | (CAN_ERR_PROT_TX if transmitting else 0)
        data[3] = CAN_ERR_PROT_LOC_DATA
    if state is ErrorState.BUS_OFF:
        class_bits |= CAN_ERR_BUSOFF
    elif state_changed:
        class_bits |= CAN_ERR_CRTL
        if state is ErrorState.PASSIVE:
            data[1] = (CAN_ERR_CRTL_TX_PASSIVE if tec >= PASSIVE_LIMIT else 0) | (CAN_ERR_CRTL_RX_PASSIVE if rec >= PASSIVE_LIMIT else 0)
        elif state is ErrorState.WARNING:
            data[1] = (CAN_ERR_CRTL_TX_WARNING if tec >= WARNING_LIMIT else 0) | (CAN_ERR_CRTL_RX_WARNING if rec >= WARNING_LIMIT else 0)
        else:
            data[1] = CAN_ERR_CRTL_ACTIVE
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
    if class_bits & CAN_ERR_CRTL:
        if data[1] & (CAN_ERR_CRTL_TX_PASSIVE | CAN_ERR_CRTL_RX_PASSIVE):
            return ErrorState.PASSIVE, False
        if data[1] & (CAN_ERR_CRTL_TX_WARNING | CAN_ERR_CRTL_RX_WARNING):
            return ErrorState.WARNING, False
        if data[1] & CAN_ERR_CRTL_ACTIVE:
            return ErrorState.ACTIVE, False
    if class_bits & CAN_ERR_CNT:
        worst = max(data[6], data[7])
        if worst >= PASSIVE_LIMIT:
            return ErrorState.PASSIVE, False
        if worst >= WARNING_LIMIT:
            return ErrorState.WARNING, False
    return ErrorState.ACTIVE, False
