"""The scenario's [can] section: transport, bus, board, driver, scripted dipoles and faults.

Defaults are those of a CubeSat-class magnetorquer set (0.2 A m^2 per axis, coils of a few ms
time constant); the seeds give no board numbers, so these are assumptions a scenario overrides.
"""
from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from bench.bus.can.faults import FaultSpec
from bench.bus.can.protocol import CMD, HEARTBEAT, TLM_DIPOLE, cycle_time_s, transmission_mode


def _dbc_cycle_s(name: str):
    """A default period from the DBC's GenMsgCycleTime, the protocol's nominal; a scenario may
    override it (a deliberate deviation, e.g. a slow board)."""
    return msgspec.field(default_factory=lambda: cycle_time_s(name))

# MTQ_TLM_SETPOINT's set-point signals: 15 bits of 1e-4 A m^2 (mtq.dbc).
SETPOINT_ECHO_MAX_AM2 = 1.6383

PositiveS = Annotated[float, msgspec.Meta(gt=0, le=3600.0)]
NonNegS = Annotated[float, msgspec.Meta(ge=0, le=1e6)]
Vec3 = Annotated[list[Annotated[float, msgspec.Meta(ge=-1e3, le=1e3)]], msgspec.Meta(min_length=3, max_length=3)]


class BoardConfig(msgspec.Struct, forbid_unknown_fields=True):
    max_dipole_am2: Annotated[float, msgspec.Meta(gt=0, le=3.2)] = 0.2   # per axis; DBC holds +-3.27
    dipole_resolution_am2: Annotated[float, msgspec.Meta(ge=1e-4, le=3.2)] = 1e-3  # coil driver DAC step
    coil_time_constant_s: PositiveS = 0.005          # L/R of a coil
    coil_gain_am2_per_a: PositiveS = 2.0             # turns x area: dipole per ampere
    command_timeout_s: PositiveS = 0.1               # no valid command this long: coils off
    heartbeat_period_s: PositiveS = _dbc_cycle_s(HEARTBEAT)          # 0.1 s in mtq.dbc
    telemetry_period_s: PositiveS = _dbc_cycle_s(TLM_DIPOLE)         # 0.05 s (MTQ_TLM_COIL too)
    # Magnetometer sampling windows: coils held off for window_s every period_s (0: never).
    mag_window_period_s: NonNegS = 0.0
    mag_window_s: NonNegS = 0.0
    ambient_temperature_c: Annotated[float, msgspec.Meta(ge=-273.15, le=500.0)] = 20.0
    # E2E profile 2 receiver (protocol.E2EReceiver): MaxDeltaCounterInit (widened by one per
    # command period or frame without a valid command), SyncCounterInit (valid commands ignored
    # after the sequence was lost) and MaxNoNewOrRepeatedData.
    max_delta_counter: Annotated[int, msgspec.Meta(ge=1, le=15)] = 1
    sync_counter: Annotated[int, msgspec.Meta(ge=0, le=15)] = 2
    max_no_new_or_repeated: Annotated[int, msgspec.Meta(ge=0, le=14)] = 14
    # CiA 301 object 0x1015: least time between two emergency frames (a burst of bad frames must
    # not crowd the bus with EMCY at identifier 0x090, which out-ranks every command).
    emcy_inhibit_s: NonNegS = 0.01
    # Command acknowledgement: MTQ_TLM_SETPOINT (TPDO3) with the coil drivers' set-point, right
    # after each applied command and whenever the set-point changes without one. What lock-step
    # with an external board pairs with each step's command (docs/can-bus.md). Off by default: a
    # frame per command would change the bus load of every run.
    setpoint_echo: bool = False

    def __post_init__(self):
        if self.mag_window_period_s and self.mag_window_s >= self.mag_window_period_s:
            raise ValueError("mag_window_s must be shorter than mag_window_period_s")
        if self.setpoint_echo and self.max_dipole_am2 > SETPOINT_ECHO_MAX_AM2:
            raise ValueError(f"setpoint_echo: MTQ_TLM_SETPOINT holds +-{SETPOINT_ECHO_MAX_AM2} A m^2, less than "
                             f"max_dipole_am2 = {self.max_dipole_am2}")


class SecurityConfig(msgspec.Struct, forbid_unknown_fields=True):
    """How the bus is protected: "secoc" (the default: authenticity and freshness, MTQ_CMD_AUTH and
    MTQ_NMT_AUTH, CAN FD) or "e2e" (integrity only: MTQ_CMD and plain NMT; anyone on the bus can
    command the coils or stop the board). Under "secoc" the board applies a command or an NMT
    state change only if its MAC verifies and its age, from the freshness value, is at most one
    command period (the DBC cycle time) plus freshness_margin_s and at most max_future_s ahead of
    the board's clock.

    key_hex: the AES-128 key, 32 hex digits. Empty (the default) means the run's key: the launcher
    generates one per run (or takes the deployment's, secoc.key beside the certificates) and hands
    it to the nodes in the run's scenario.json (mode 0600). There is no built-in key."""
    profile: Literal["e2e", "secoc"] = "secoc"
    key_hex: Annotated[str, msgspec.Meta(max_length=64)] = ""
    freshness_margin_s: PositiveS = 0.02
    max_future_s: NonNegS = 0.005

    def __post_init__(self):
        if not self.key_hex:
            return
        try:
            key = bytes.fromhex(self.key_hex)
        except ValueError:
            raise ValueError("security.key_hex must be hexadecimal") from None
        if len(key) != 16:
            raise ValueError(f"security.key_hex must hold 16 bytes (AES-128), not {len(key)}")

    @property
    def key(self) -> bytes | None:
        """The key, or None when none was handed over yet (key_hex empty)."""
        return bytes.fromhex(self.key_hex) if self.key_hex else None

    @property
    def authenticated(self) -> bool:
        return self.profile == "secoc"


class DriverConfig(msgspec.Struct, forbid_unknown_fields=True):
    command_period_s: PositiveS = _dbc_cycle_s(CMD)                  # 0.02 s in mtq.dbc
    # How commands go out (AUTOSAR COM): "cyclic" every command period with the newest dipole;
    # "on_change" the moment the law gives one (and never otherwise: the board's command timeout
    # then needs a law at least that fast); "mixed" both, on change and every period as a
    # keep-alive. Default: the DBC's GenMsgSendType of MTQ_CMD (CyclicAndSpontaneous: mixed).
    transmission: Literal["cyclic", "on_change", "mixed"] = msgspec.field(default_factory=lambda: transmission_mode(CMD))
    # A board is lost when its heartbeat is this many heartbeat periods late (CANopen consumer time).
    heartbeat_timeout_periods: Annotated[float, msgspec.Meta(ge=1.0, le=1000.0)] = 2.5
    telemetry_timeout_periods: Annotated[float, msgspec.Meta(ge=1.0, le=1000.0)] = 3.0
    max_delta_counter: Annotated[int, msgspec.Meta(ge=1, le=15)] = 1
    # Plausibility of the applied dipole against the command: beyond tolerance for longer than
    # mismatch_time_s (after the coils had settle_s to follow) is a stuck or corrupted actuator.
    dipole_tolerance_am2: PositiveS = 0.01
    settle_s: PositiveS = 0.06
    mismatch_time_s: PositiveS = 0.15
    # After a spoofed command, an implausible applied dipole or bad telemetry, health is not ok
    # for this long (a fault that stops is not forgotten at the next good frame).
    fault_hold_s: PositiveS = 1.0
    # The driver is the board's NMT master: it starts the board whenever it reports boot-up or
    # pre-operational (CiA 301: a node processes commands only when operational).
    nmt_auto_start: bool = True


ROLES = ("driver", "board")     # the nodes whose bus a scenario may name ([can.driver_bus], [can.board_bus])


class DipoleStep(msgspec.Struct, forbid_unknown_fields=True):
    t_s: NonNegS
    dipole_am2: Vec3


def _default_profile() -> list[DipoleStep]:
    # Each axis in turn, both signs: every applied value differs from the one before.
    return [DipoleStep(0.0, [0.1, 0.0, 0.0]), DipoleStep(0.3, [0.0, 0.1, 0.0]), DipoleStep(0.6, [0.0, 0.0, 0.1]),
            DipoleStep(0.9, [-0.1, 0.0, 0.0]), DipoleStep(1.2, [0.0, -0.1, 0.0]), DipoleStep(1.5, [0.0, 0.0, -0.1])]


# An interface option: a scalar, bounded like every scenario field (a tty path, a baud rate, a
# host name, a flag).
OptionValue = (Annotated[str, msgspec.Meta(max_length=256)] | Annotated[int, msgspec.Meta(ge=-2**31, le=2**32)]
               | Annotated[float, msgspec.Meta(ge=-1e9, le=1e9)] | bool)


class BusSpec(msgspec.Struct, forbid_unknown_fields=True):
    """One node's CAN bus as python-can opens it: `can.Bus(interface=, channel=, bitrate=, fd=,
    **options)`. `interface` is any python-can interface name (`slcan`, `pcan`, `kvaser`,
    `gs_usb`, `udp_multicast`, `socketcand`, ...; `zenoh` is the bench's own), `options` the
    interface's own keyword arguments (e.g. `{ tty_baudrate = 115200, sleep_after_open = 0 }` for
    slcan). Whether the interface exists and the channel opens is checked by the launcher before
    any process starts (bench/bus/can/preflight.py), not here: parsing a scenario does no I/O."""
    interface: Annotated[str, msgspec.Meta(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")]
    channel: Annotated[str, msgspec.Meta(max_length=256)] = ""
    bitrate: Annotated[int, msgspec.Meta(ge=10_000, le=8_000_000)] | None = None
    # CAN FD: the secoc profile's authenticated frames (MTQ_CMD_AUTH, MTQ_NMT_AUTH) are FD frames,
    # so it needs fd = true; a classic-only adapter needs security.profile = "e2e".
    fd: bool = True
    options: Annotated[dict[Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z_][A-Za-z0-9_]*$", max_length=64)],
                            OptionValue], msgspec.Meta(max_length=64)] = {}

    def __post_init__(self):
        reserved = {"interface", "channel", "bitrate", "fd", "run_id", "session", "ignore_config"} & set(self.options)
        if reserved:
            raise ValueError(f"options: {', '.join(sorted(reserved))} is set by the bench or is a field of its own, "
                             f"not an option")


class CanConfig(msgspec.Struct, forbid_unknown_fields=True):
    # Shorthand for every bus of the run: the bench's nodes (driver, bus model, board) each open
    # this python-can interface on their channel. driver_bus / board_bus override one node's end.
    transport: Literal["zenoh", "socketcan", "virtual"] = "zenoh"
    flight_channel: Annotated[str, msgspec.Meta(max_length=64)] = "flight"   # the driver's side of the bus model
    board_channel: Annotated[str, msgspec.Meta(max_length=64)] = "board"     # the board's side
    bitrate_bps: Annotated[int, msgspec.Meta(ge=10_000, le=1_000_000)] = 1_000_000
    node_id: Annotated[int, msgspec.Meta(ge=1, le=127)] = 0x10
    tx_queue_frames: Annotated[int, msgspec.Meta(ge=1, le=1024)] = 8   # a controller's transmit buffers
    board: BoardConfig = msgspec.field(default_factory=BoardConfig)
    driver: DriverConfig = msgspec.field(default_factory=DriverConfig)
    security: SecurityConfig = msgspec.field(default_factory=SecurityConfig)
    # Scripted dipole (until the attitude law commands it): steps held until the next, repeated
    # every profile_repeat_s when that is set.
    dipole_profile: Annotated[list[DipoleStep], msgspec.Meta(max_length=10_000)] = msgspec.field(default_factory=_default_profile)
    profile_repeat_s: NonNegS = 1.8
    faults: Annotated[list[FaultSpec], msgspec.Meta(max_length=256)] = []
    capture: bool = True               # candump .log of the bus model in the run directory
    # Lock-step attitude runs: "simulated" runs the driver's periodic frames, the bus's bit times
    # and the board's timeouts and heartbeats on the run's simulated time (bench/bus/can/sim_window.py),
    # every frame of every simulated second computed; "wall" keeps them on the wall clock and pairs
    # the board's reports with commands by counter (what a kernel bus or a part from outside needs;
    # on a fault-free bus the trajectory is the same, at the cost of the hops only). "auto": simulated
    # when the scenario injects bus faults, whose timing then must not depend on the host.
    # Real-time runs are on the wall clock.
    lock_step_clock: Literal["auto", "simulated", "wall"] = "auto"
    # On the wall clock (real time, a kernel bus, a part from outside): SCHED_FIFO priority of the
    # board's, the bus model's and the driver's (controller's) processes, all their threads (0: the
    # default scheduler). They stand for hardware and flight software, which no other program on
    # the host holds up; under the default scheduler a loaded host delays frames past the board's
    # command timeout and its freshness window, faults the bus never had (bench/runtime/priority.py).
    realtime_priority: Annotated[int, msgspec.Meta(ge=0, le=99)] = 20
    # The flight-side driver's and the board's own bus, when not the bus model's end of `transport`
    # on flight_channel / board_channel: any python-can interface (BusSpec; docs/can-bus.md).
    driver_bus: BusSpec | None = None
    board_bus: BusSpec | None = None

    def __post_init__(self):
        times = [s.t_s for s in self.dipole_profile]
        if times != sorted(times):
            raise ValueError("dipole_profile steps must be in increasing t_s")
        for role in ROLES:
            spec = getattr(self, f"{role}_bus")
            if spec is not None and self.security.authenticated and not spec.fd:
                raise ValueError(f"{role}_bus.fd: the secoc profile's authenticated frames are CAN FD; "
                                 f"set fd = true or security.profile = \"e2e\"")

    def bus_spec(self, role: str) -> BusSpec:
        """The bus a node opens: role "driver" or "board" (its own spec, else the transport on its
        channel), or "busmodel_flight" / "busmodel_board" (the bus model's ends: always `transport`)."""
        if role in ROLES and getattr(self, f"{role}_bus") is not None:
            return getattr(self, f"{role}_bus")
        channel = {"driver": self.flight_channel, "busmodel_flight": self.flight_channel,
                   "board": self.board_channel, "busmodel_board": self.board_channel}[role]
        return BusSpec(interface=self.transport, channel=channel)

    def bus_field(self, role: str) -> str:
        """The scenario field a role's bus comes from, for error messages."""
        return f"can.{role}_bus" if role in ROLES and getattr(self, f"{role}_bus") is not None else "can.transport"

    def protocol(self):
        """The protocol of this bus: node id, command profile and key (None if not handed over:
        such a Protocol decodes but cannot send an authenticated frame; board and driver refuse it)."""
        from bench.bus.can.protocol import Protocol
        return Protocol(self.node_id, self.security.profile, self.security.key if self.security.authenticated else None)

    def dipole_at(self, t_s: float) -> list[float]:
        """The scripted dipole at time t_s since the start of commanding."""
        if not self.dipole_profile:
            return [0.0, 0.0, 0.0]
        if self.profile_repeat_s > 0:
            t_s = t_s % self.profile_repeat_s
        current = [0.0, 0.0, 0.0]
        for step in self.dipole_profile:
            if step.t_s > t_s:
                break
            current = step.dipole_am2
        return list(current)
