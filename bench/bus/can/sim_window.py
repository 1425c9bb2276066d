"""Lock-step on simulated time: the CAN frames of one plant step, as one message each way.

In lock-step the flight-side driver (controller process) and the bus with the board (canbus
process) do not trade frames one by one on the wall clock. For each plant step [start, end) the
driver sends one `CanWindow` with every frame it puts on the bus during the step, each stamped
with its simulated time (the law's command at the start, keep-alives at their slots, an NMT start
it owes the board); the bus answers with one `CanWindow` holding every frame the flight side
heard during the step, each stamped with the simulated time its last bit passed. The driver
handles those frames, in time order and at their times, before it sends the next step's: what
it detects is stamped on simulated time, and nothing waits on a wall-clock period.

Simulated time on the bus is integer nanoseconds, `SIM_ZERO_NS` at the mission's t = 0 s (far
from 0 so that no deadline looks back before it; the board boots `BOOT_S` before t = 0).
"""
from __future__ import annotations

import can
import msgspec

from bench.bus.schemas import Message

SIM_ZERO_NS = 10**12
BOOT_S = 0.05             # the board boots this long before the first step (CiA 301: NMT start first)


def sim_ns(t_s: float) -> int:
    """Bus time (ns) of a mission time (s)."""
    return SIM_ZERO_NS + round(t_s * 1e9)


def mission_s(t_ns: int) -> float:
    """Mission time (s) of a bus time (ns)."""
    return (t_ns - SIM_ZERO_NS) / 1e9


class SimFrame(msgspec.Struct, array_like=True, forbid_unknown_fields=True):
    """One CAN frame at a simulated time (compact: a JSON array)."""
    t_ns: int
    arbitration_id: int
    data: bytes
    is_fd: bool = False
    is_extended_id: bool = False
    is_error_frame: bool = False
    bitrate_switch: bool = False


class CanWindow(Message, tag="can_window"):
    """The frames of one plant step on one side of the bus (lock-step on simulated time).

    step: the plant step (negative: the board's boot, before step 0). start_ns, end_ns: the
    step's bus time; every frame's t_ns is inside it.
    """
    step: int
    start_ns: int
    end_ns: int
    frames: list[SimFrame] = []


def to_sim_frame(msg: can.Message, t_ns: int) -> SimFrame:
    return SimFrame(t_ns, msg.arbitration_id, bytes(msg.data), msg.is_fd, msg.is_extended_id, msg.is_error_frame,
                    msg.bitrate_switch)


def to_can_message(frame: SimFrame) -> can.Message:
    """A python-can frame stamped with its simulated time in seconds (bus time, `t_ns / 1e9`)."""
    return can.Message(timestamp=frame.t_ns / 1e9, arbitration_id=frame.arbitration_id, data=frame.data,
                       is_fd=frame.is_fd, is_extended_id=frame.is_extended_id, is_error_frame=frame.is_error_frame,
                       bitrate_switch=frame.bitrate_switch, dlc=len(frame.data), check=False)


class OutboxBus:
    """The driver's end of a bus whose frames leave once per step: what it sends is kept with
    the simulated time it was sent at, until `take` puts it in the step's CanWindow."""

    def __init__(self, clock):
        self.clock = clock              # SimClock
        self._sent: list[tuple[int, can.Message]] = []

    def send(self, msg: can.Message, timeout=None) -> None:
        self._sent.append((self.clock.t_ns, msg))

    def recv(self, timeout=0.0):
        return None                     # frames in come in the bus's CanWindow

    def take(self, not_before_ns: int) -> list[SimFrame]:
        """Everything sent since the last call; a frame sent while the driver caught up with the
        last step's frames (an NMT start it owed) goes out at the new step's start."""
        frames = [to_sim_frame(msg, max(t_ns, not_before_ns)) for t_ns, msg in self._sent]
        self._sent = []
        return sorted(frames, key=lambda f: f.t_ns)

    def shutdown(self) -> None:
        pass


def bus_on_simulated_time(scenario) -> bool:
    """Whether this run's CAN bus runs on simulated time: the attitude loop in lock-step with every
    part of the bus the bench's own, over the portable transport (no `driver_bus` or `board_bus`
    of another interface), the board the bench's own (not `[run] external = ["board"]`), and
    `[can] lock_step_clock` "simulated" (or "auto" with bus faults). Otherwise the driver and the
    board keep the wall clock (real time, a kernel bus, a part from outside, a fault-free "auto")
    and the lock-step plant pairs the board's reports with commands by counter."""
    can_config = getattr(scenario, "can", None)
    if can_config is None or scenario.kind != "attitude" or scenario.run.mode != "lock-step":
        return False
    if "board" in scenario.run.external:
        return False        # hardware keeps its own clock: nothing on the bus can run on simulated time
    clock = can_config.lock_step_clock
    own_bus = can_config.transport == "zenoh" and can_config.driver_bus is None and can_config.board_bus is None
    return own_bus and (clock == "simulated" or (clock == "auto" and bool(can_config.faults)))


def fault_clock_scale(scenario) -> float:
    """Seconds of the bus's clock per simulated second: what a fault's start_s and duration_s (the
    run's simulated seconds, FaultSpec.window_ns) are multiplied by on the bus. 1 where the bus runs
    on simulated time; 1 / time_factor where a real-time run puts it on the wall clock (a
    rendezvous at 6000: a fault at 18 000 s comes 3 s of wall time after the first command). A
    lock-step run with the bus on the wall clock has no wall time per simulated second: an
    attitude loop is refused faults there (bench.scenario), and a bus alone (no loop, or beside a
    lock-step rendezvous, which it does not touch) counts them in its own seconds (1)."""
    if bus_on_simulated_time(scenario) or scenario.run.mode != "real-time":
        return 1.0
    return 1.0 / float(scenario.run.time_factor)
