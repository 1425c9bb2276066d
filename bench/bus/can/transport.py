"""Open the CAN bus a scenario asks for: the same python-can `BusABC` whatever carries the frames.

- "socketcan": the Linux kernel's CAN (vcan0/vcan1 on a bench), where the kernel has it.
- "zenoh": frames over the bench's Zenoh session (bench.bus.can.zenoh_interface); works on any
  host, across processes and hosts. The default where there is no vcan.
- "virtual": python-can's in-process virtual bus; one process only (unit tests, baselines).
- any other python-can interface (`slcan`, `pcan`, `socketcand`, ...), named per node by a
  BusSpec ([can.driver_bus], [can.board_bus]) and opened by `open_bus`.
"""
from __future__ import annotations

import socket
from pathlib import Path

import can

from bench.bus import keys
from bench.bus.can.config import BusSpec
from bench.bus.session import SessionOptions

TRANSPORTS = ("zenoh", "socketcan", "virtual")
DEFAULT_VCAN = "vcan0"


class TransportUnavailable(RuntimeError):
    """The transport asked for cannot work on this host (e.g. socketcan without kernel CAN)."""


def kernel_has_can() -> bool:
    """True when this kernel can open a raw CAN socket (AF_CAN with the can-raw protocol)."""
    try:
        with socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW):
            return True
    except (OSError, AttributeError):  # AttributeError: a Python built without AF_CAN
        return False


def interface_exists(name: str) -> bool:
    return Path("/sys/class/net", name).exists()


def default_transport() -> str:
    """"socketcan" when vcan0 exists and AF_CAN works, else "zenoh"."""
    return "socketcan" if kernel_has_can() and interface_exists(DEFAULT_VCAN) else "zenoh"


def open_bus(
    spec: BusSpec,
    *,
    run_id: str,
    session=None,
    session_options: SessionOptions | None = None,
    receive_own_messages: bool = False,
) -> can.BusABC:
    """The python-can bus a BusSpec names; the caller shuts it down. `session`: a node's own Zenoh
    session, shared by its `zenoh` buses (one session per process)."""
    if spec.interface == "zenoh" and session is not None:
        return can.Bus(interface="zenoh", channel=spec.channel, run_id=run_id, session=session, fd=spec.fd,
                       receive_own_messages=receive_own_messages, ignore_config=True, **spec.options)
    if spec.interface in TRANSPORTS:
        return open_can_bus(spec.interface, spec.channel, run_id=run_id, session_options=session_options,
                            receive_own_messages=receive_own_messages, options=spec.options)
    # ignore_config: a user's ~/can.conf must not add arguments behind the scenario's back.
    kwargs = dict(spec.options)
    if spec.bitrate is not None:
        kwargs["bitrate"] = spec.bitrate
    return can.Bus(interface=spec.interface, channel=spec.channel, fd=spec.fd,
                   receive_own_messages=receive_own_messages, ignore_config=True, **kwargs)


def open_can_bus(
    transport: str,
    channel: str,
    *,
    run_id: str,
    session_options: SessionOptions | None = None,
    receive_own_messages: bool = False,
    options: dict | None = None,
) -> can.BusABC:
    """A python-can bus on `channel` over `transport`; the caller shuts it down. `options`: the
    interface's own keyword arguments.

    Raises ValueError for an unknown transport and TransportUnavailable, with what to do instead,
    when the host cannot provide it.
    """
    keys.check_run_id(run_id)
    options = dict(options or {})
    if transport == "zenoh":
        # Through python-can's plugin lookup (entry point "can.interface"), as any CAN tool would;
        # ignore_config keeps a user's ~/can.conf from adding arguments behind the bench's back.
        return can.Bus(
            interface="zenoh", channel=channel, run_id=run_id, session_options=session_options,
            receive_own_messages=receive_own_messages, fd=True, ignore_config=True, **options,
        )
    if transport == "socketcan":
        if not kernel_has_can():
            raise TransportUnavailable(
                'this kernel has no CAN sockets (AF_CAN fails): use transport = "zenoh"'
            )
        if not interface_exists(channel):
            raise TransportUnavailable(
                f"CAN interface {channel!r} does not exist: create it with `bench vcan up` "
                f'(as root) or use transport = "zenoh"'
            )
        # fd=True: the authenticated command (MTQ_CMD_AUTH) is a CAN FD frame (vcan needs mtu 72).
        return can.Bus(interface="socketcan", channel=channel, fd=True,
                       receive_own_messages=receive_own_messages, ignore_config=True, **options)
    if transport == "virtual":
        # python-can's virtual channels are process-global: the run id keeps parallel runs apart.
        return can.Bus(interface="virtual", channel=f"{run_id}/{channel}",
                       receive_own_messages=receive_own_messages, ignore_config=True, **options)
    raise ValueError(f"CAN transport {transport!r} is not one of {', '.join(TRANSPORTS)}")
