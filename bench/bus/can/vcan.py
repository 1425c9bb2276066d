"""`bench vcan up` / `bench vcan down`: the kernel's virtual CAN interfaces for the socketcan transport.

Uses `modprobe` and `ip` (iproute2) as an administrator would, rather than a netlink library: two
commands are all it takes, and their error text is what a user searches for. Where the host
cannot have vcan (not root, no vcan module, no CAN in the kernel) it says so in one line, names
the way out (the `zenoh` transport), and exits 2.
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

DEFAULT_INTERFACES = ("vcan0", "vcan1")  # the flight side and the board side of the bus model
# vcan gives the interfaces (it pulls in can-dev), can_raw the AF_CAN sockets.
KERNEL_MODULES = ("vcan", "can_raw")
COMMAND_TIMEOUT_S = 10
USE_ZENOH = 'use transport = "zenoh"'
_IFNAME = re.compile(r"^[A-Za-z0-9_.-]{1,15}$")  # the kernel's limit is 15 characters


class VcanUnavailable(RuntimeError):
    """This host cannot provide vcan interfaces; the message says why and what to do instead."""


def _run(argv: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(argv, capture_output=True, text=True, timeout=COMMAND_TIMEOUT_S)


def _module_loaded(name: str) -> bool:
    return Path("/sys/module", name).is_dir()


def _interface_exists(name: str) -> bool:
    return Path("/sys/class/net", name).exists()


def _check_tools() -> None:
    if os.geteuid() != 0:
        raise VcanUnavailable(f"creating CAN interfaces needs root (CAP_NET_ADMIN): run `sudo bench vcan up`, or {USE_ZENOH}")
    if shutil.which("ip") is None:
        raise VcanUnavailable(f"`ip` (Debian package iproute2) is not installed: install it, or {USE_ZENOH}")


def load_modules() -> None:
    """Load can_raw and vcan unless already there (built in, or loaded by the UML harness)."""
    for module in KERNEL_MODULES:
        if _module_loaded(module):
            continue
        if shutil.which("modprobe") is None:
            raise VcanUnavailable(f"`modprobe` (Debian package kmod) is not installed: install it, or {USE_ZENOH}")
        result = _run(["modprobe", module])
        if result.returncode != 0:
            detail = result.stderr.strip().splitlines()[-1] if result.stderr.strip() else f"exit {result.returncode}"
            raise VcanUnavailable(
                f"the kernel has no {module} module (modprobe {module} failed: {detail}): {USE_ZENOH}"
            )


def _check_names(names: tuple[str, ...]) -> None:
    for name in names:
        if not _IFNAME.match(name):
            raise VcanUnavailable(f"interface name {name!r} must be 1-15 letters, digits, '_', '.', '-'")


def up(names: tuple[str, ...] = DEFAULT_INTERFACES) -> list[str]:
    """Create and bring up each vcan interface; returns one line per interface for the user."""
    _check_names(names)
    _check_tools()
    load_modules()
    report = []
    for name in names:
        if _interface_exists(name):
            report.append(f"{name}: already exists")
        else:
            result = _run(["ip", "link", "add", "dev", name, "type", "vcan"])
            if result.returncode != 0:
                raise VcanUnavailable(f"ip link add dev {name} type vcan failed: {result.stderr.strip()}; {USE_ZENOH}")
            report.append(f"{name}: created")
        # mtu 72 carries CAN FD frames (the authenticated command, MTQ_CMD_AUTH, is one).
        result = _run(["ip", "link", "set", "dev", name, "mtu", "72", "up"])
        if result.returncode != 0:
            raise VcanUnavailable(f"ip link set dev {name} up failed: {result.stderr.strip()}")
    return report


def down(names: tuple[str, ...] = DEFAULT_INTERFACES) -> list[str]:
    """Delete each interface that exists; one that does not is already down."""
    _check_names(names)
    _check_tools()
    report = []
    for name in names:
        if not _interface_exists(name):
            report.append(f"{name}: not present")
            continue
        result = _run(["ip", "link", "delete", "dev", name])
        if result.returncode != 0:
            raise VcanUnavailable(f"ip link delete dev {name} failed: {result.stderr.strip()}")
        report.append(f"{name}: deleted")
    return report


def _command(args: argparse.Namespace) -> int:
    action = up if args.action == "up" else down
    try:
        for line in action(tuple(args.interfaces)):
            print(line)
    except VcanUnavailable as exc:
        print(f"bench vcan {args.action}: {exc}", file=sys.stderr)
        return 2
    return 0


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("vcan", help="create or delete the kernel vcan interfaces (socketcan transport)")
    parser.add_argument("action", choices=("up", "down"))
    parser.add_argument("interfaces", nargs="*", default=list(DEFAULT_INTERFACES), metavar="IFACE",
                        help=f"interface names (default: {' '.join(DEFAULT_INTERFACES)})")
    parser.set_defaults(func=_command)
