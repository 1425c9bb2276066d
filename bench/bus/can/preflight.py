"""The launcher's check of a run's CAN buses, before any process starts.

Each bus a node of the run will open (the driver's, the board's, the bus model's two ends) is
checked the way it will be opened (CanConfig.bus_spec):
- the interface exists in this python-can (`can.interfaces.BACKENDS`: built-ins and `can.interface`
  entry points such as the bench's `zenoh`);
- `socketcan` needs kernel CAN (AF_CAN) and the named interface;
- `virtual` is refused: python-can's virtual bus lives in one process's memory, and the bench's
  nodes are separate processes, so it would carry nothing (a run would end "fine" with 0 frames);
- a serial interface's channel must be a character device, checked before it is opened (its text,
  a device path and never a URL, was checked when the scenario was loaded: config.channel_problem);
- any other interface's channel is opened and shut at once (a missing tty, adapter or server fails
  here, not 15 s into the run in a node's traceback).
The `zenoh` interface needs the run's hub, which is not up yet: only its channel name is checked.

A problem is a CanBusError naming the scenario field, one line; `bench run` exits 2 on it.
"""
from __future__ import annotations

import os
import stat

import can

from bench.bus.can.config import BAUD_SUFFIX_INTERFACES, SERIAL_INTERFACES, BusSpec, CanConfig
from bench.bus.can.transport import interface_exists, kernel_has_can, open_bus


class CanBusError(ValueError):
    """A bus of the run cannot work; the message names the scenario field and the problem."""


def roles_of_run(config: CanConfig, board_external: bool = False) -> list[str]:
    """The buses the run's own processes open: the driver's, and unless the board is provided
    from outside, the board's and the bus model's two ends."""
    return ["driver"] if board_external else ["driver", "board", "busmodel_flight", "busmodel_board"]


NODE_OF_ROLE = {"driver": "controller", "board": "mtq", "busmodel_flight": "canbus", "busmodel_board": "canbus"}


def roles_on_this_host(config: CanConfig, remote: dict[str, str] | set[str]) -> list[str]:
    """The run's buses whose node this host starts (not on another host of a deployment, not external)."""
    return [role for role in roles_of_run(config) if NODE_OF_ROLE[role] not in remote]


def check_run_buses(config: CanConfig, roles: list[str] | None = None) -> None:
    """Raise CanBusError for the first bus of `roles` (default: roles_of_run) that cannot work."""
    checked: set[tuple] = set()
    for role in roles_of_run(config) if roles is None else roles:
        spec = config.bus_spec(role)
        key = (spec.interface, spec.channel, spec.bitrate, spec.fd, tuple(sorted(spec.options.items())))
        if key in checked:
            continue
        checked.add(key)
        check_bus(spec, config.bus_field(role), config.channel_field(role))


def check_bus(spec: BusSpec, field: str, channel_field: str | None = None) -> None:
    """Raise CanBusError (naming `field`, e.g. "can.driver_bus", or `channel_field`, by default
    `field`.channel) if `spec` cannot carry frames between the run's processes on this host."""
    name = spec.interface
    channel_field = channel_field or f"{field}.channel"
    where = "interface" if field.endswith("_bus") else ""
    label = f"{field}.{where}" if where else field
    if name not in can.interfaces.BACKENDS:
        known = ", ".join(sorted(can.interfaces.BACKENDS))
        raise CanBusError(f"{label}: {name!r} is not a python-can interface in this python-can "
                          f"{can.__version__} (known: {known})")
    if name == "virtual":
        raise CanBusError(f"{label}: python-can's \"virtual\" bus is in-process only and the bench's nodes are "
                          f"separate processes, so it would carry no frame between them; use \"zenoh\" "
                          f"(any host) or \"socketcan\" (kernel vcan)")
    if name == "socketcan":
        if not kernel_has_can():
            raise CanBusError(f"{label}: \"socketcan\" needs kernel CAN and this host has none (AF_CAN sockets "
                              f"fail); use \"zenoh\", or run in user-mode Linux (docs/can-bus.md)")
        if not interface_exists(spec.channel):
            raise CanBusError(f"{channel_field}: CAN interface {spec.channel!r} does not exist on this host "
                              f"(`bench vcan up` creates vcan0/vcan1, as root)")
        return
    if name == "zenoh":
        from bench.bus.can.zenoh_interface import check_channel

        try:
            check_channel(spec.channel)
        except ValueError as exc:
            raise CanBusError(f"{channel_field}: {exc}") from None
        return
    if name in SERIAL_INTERFACES:
        problem = _not_a_tty(spec)
        if problem:
            raise CanBusError(f"{channel_field}: {name} channel {spec.channel!r} cannot be opened: {problem}")
    try:
        bus = open_bus(spec, run_id="preflight")
    except Exception as exc:  # noqa: BLE001 - any interface's failure to open is the user's to read
        detail = " ".join(str(exc).split()) or type(exc).__name__
        raise CanBusError(f"{channel_field}: {name} channel {spec.channel!r} cannot be opened: {detail}") from None
    try:
        bus.shutdown()
    except Exception:  # noqa: BLE001 - it opened; a failing close is not this check's finding
        pass


def _not_a_tty(spec: BusSpec) -> str | None:
    """Why a serial interface's channel is not a character device, else None; nothing is opened
    (pyserial opens its tty read-write: a regular file or a FIFO is not for it to open)."""
    path = spec.channel.partition("@")[0] if spec.interface in BAUD_SUFFIX_INTERFACES else spec.channel
    if not path:
        return "no tty given (e.g. /dev/ttyACM0)"
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        return exc.strerror or type(exc).__name__
    return None if stat.S_ISCHR(mode) else "not a character device (a tty)"
