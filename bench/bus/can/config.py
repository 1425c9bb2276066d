"""The scenario's [can] section: transport, bus, board, driver, scripted dipoles and faults.

Defaults are those of a CubeSat-class magnetorquer set (0.2 A m^2 per axis, coils of a few ms
time constant); the seeds give no board numbers, so these are assumptions a scenario overrides.
"""
from __future__ import annotations

import ipaddress
import re
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
    # Plausibility of the applied dipole (the coils' current sensors) against the commands: outside
    # the range of the set-points the coils can be following (driver._check_plausibility) by more
    # than the tolerance for longer than mismatch_time_s is a coil that does not do what it is told
    # (open, stuck) or a corrupted command. The set-points are the board's (DAC step, limit), so
    # the tolerance is the telemetry's 1e-4 A m^2 resolution with a margin: half a DAC step of the
    # default board (an open coil commanded one DAC step shows).
    dipole_tolerance_am2: PositiveS = 0.0005
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


# An interface option: a scalar, bounded like every scenario field (a baud rate, a host name, a
# flag; never a path or a URL: option_problem below).
OptionValue = (Annotated[str, msgspec.Meta(max_length=256)] | Annotated[int, msgspec.Meta(ge=-2**31, le=2**32)]
               | Annotated[float, msgspec.Meta(ge=-1e9, le=1e9)] | bool)


# --- Channels are devices, never URLs (issue 44) -------------------------------------------------
# A scenario names the device a node opens and nothing else. python-can's serial interfaces hand
# their channel to pyserial's serial_for_url, which reads "scheme://..." as a protocol handler:
# `spy:///x?file=victim.txt` truncated a file the user could write (the launcher's preflight opened
# the channel before it refused the run), `socket://` and `rfc2217://` connect out, `loop://`,
# `alt://` and `hwgrep://` open something other than the device named. So every field that names a
# channel is checked here, by its text, when the scenario is validated: before the launcher opens
# anything, and in every process that loads the scenario. A network endpoint only where the
# interface defines its field as one (udp_multicast's group, socketcand's `host` option).

# Interfaces whose channel is a tty opened with pyserial; slcan and robotell also take the tty's
# baud rate after '@' ("/dev/ttyACM0@115200").
SERIAL_INTERFACES = frozenset({"slcan", "robotell", "serial", "seeedstudio"})
BAUD_SUFFIX_INTERFACES = frozenset({"slcan", "robotell"})
# Interfaces whose channel is a network interface: the kernel's (socketcan) or the socketcand server's.
NETDEV_INTERFACES = frozenset({"socketcan", "socketcand"})
# The bench's zenoh interface (and python-can's in-process virtual bus): one key-expression chunk,
# bench/<run_id>/can/<channel> (zenoh_interface.check_channel).
ZENOH_CHANNEL = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
_DEVICE_PATH = re.compile(r"^(/[A-Za-z0-9_.+,:=-]+)+$")
_NETDEV = re.compile(r"^[A-Za-z0-9_.-]{1,15}$")          # Linux: IFNAMSIZ - 1, no '/', ':' or space
# Any other interface's channel names one of the adapter's channels ("PCAN_USBBUS1", "0", "CAN1"):
# a name or a number.
_ADAPTER_CHANNEL = re.compile(r"^[A-Za-z0-9_.,: -]{0,64}$")
_HOST_NAME = re.compile(r"^(?=.{1,253}$)[A-Za-z0-9]([A-Za-z0-9-]*[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]*[A-Za-z0-9])?)*$")
# Options that name a file or an endpoint, which a scenario does not give: a library to load
# (neovi's override_library_name, usb2can's dll) or the zenoh interface's own session (the bench's
# nodes open their buses on theirs).
FILE_OR_ENDPOINT_OPTIONS = frozenset({"dll", "override_library_name", "listen", "connect"})


def device_path_problem(path: str) -> str | None:
    """Why `path` is not a device path, else None: the one check of every field naming a device.

    A device is named by an absolute, normalised path of plain characters (/dev/ttyACM0,
    /dev/serial/by-id/usb-...-if00, /dev/pts/3): so never a URL (no "scheme://": pyserial would
    open it with a protocol handler), never relative (the launcher and the nodes have other working
    directories), no '.' or '..' component. Whether it is a device is the preflight's to check."""
    if not _DEVICE_PATH.match(path):
        return (f"{path!r} is not a device path (channels are devices, never URLs: an absolute path such as "
                f"/dev/ttyACM0, of letters, digits and _.+,:=-)")
    if any(part in (".", "..") for part in path.split("/")):
        return f"{path!r} is not a device path: no '.' or '..' component"
    return None


def channel_problem(interface: str, channel: str) -> str | None:
    """Why `channel` is not a channel of the python-can `interface`, else None (its text only;
    whether it opens is the launcher's preflight, bench/bus/can/preflight.py)."""
    if interface in SERIAL_INTERFACES:
        if not channel:
            return None    # python-can refuses an empty tty before it opens anything
        path = channel
        if interface in BAUD_SUFFIX_INTERFACES and "@" in channel:
            path, _, baud = channel.partition("@")
            if not (baud.isascii() and baud.isdigit() and len(baud) <= 8):
                return f"{channel!r}: after '@' comes the tty's baud rate, in digits"
        return device_path_problem(path)
    if interface in NETDEV_INTERFACES:
        if _NETDEV.match(channel) and channel not in (".", ".."):
            return None
        return f"{channel!r} is not a network interface name (1-15 letters, digits, _.-, e.g. can0)"
    if interface in ("zenoh", "virtual"):
        return None if ZENOH_CHANNEL.match(channel) else f"{channel!r} is not a {interface} CAN channel (1-64 letters, digits, _.-)"
    if interface == "udp_multicast":
        try:
            multicast = ipaddress.ip_address(channel).is_multicast
        except ValueError:
            multicast = False
        return None if multicast else f"{channel!r} is not a multicast group address (224.0.0.0/4, ff00::/8)"
    if _ADAPTER_CHANNEL.match(channel):
        return None
    return f"{channel!r} is not a {interface} channel name (letters, digits, _.,: -): never a path or a URL"


def option_problem(interface: str, key: str, value) -> str | None:
    """Why an interface option cannot be given by a scenario, else None: options are names and
    numbers, never a file or an endpoint, except socketcand's server (`host`), which is one."""
    if key in FILE_OR_ENDPOINT_OPTIONS:
        return f"{key} names a file or an endpoint, which a scenario does not give"
    if not isinstance(value, str):
        return None
    if interface == "socketcand" and key == "host":
        try:
            ipaddress.ip_address(value)
            return None
        except ValueError:
            return None if _HOST_NAME.match(value) else f"{value!r} is not a host name or an IP address"
    if "/" in value or "\\" in value:
        return f"{value!r}: an option is a name or a number, never a path or a URL"
    return None


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
        problem = channel_problem(self.interface, self.channel)
        if problem:
            raise ValueError(f"channel: {problem}")
        for key, value in self.options.items():
            problem = option_problem(self.interface, key, value)
            if problem:
                raise ValueError(f"options.{key}: {problem}")


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
        for name in ("flight_channel", "board_channel"):
            problem = channel_problem(self.transport, getattr(self, name))
            if problem:
                raise ValueError(f"{name}: {problem}")
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

    def channel_field(self, role: str) -> str:
        """The scenario field a role's channel comes from, for error messages."""
        if role in ROLES and getattr(self, f"{role}_bus") is not None:
            return f"can.{role}_bus.channel"
        return "can.flight_channel" if role in ("driver", "busmodel_flight") else "can.board_channel"

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
