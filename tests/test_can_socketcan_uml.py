"""The socketcan transport on a real kernel vcan, inside user-mode Linux (tests/uml.py).

One UML boot runs every guest test in tests/uml_guest/; each is reported here by name, so a
guest test that fails, errors, or silently stops being collected fails on the host.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest

import uml
from bench.bus.can.transport import kernel_has_can

GUEST_DIR = "tests/uml_guest"
BOOT_TIMEOUT_S = 300   # a hang bound; `bench vcan` start-up alone takes tens of seconds on UML
GUEST_SOCKETCAN = [
    "test_kernel_vcan_is_the_default_transport",
    "test_frames_cross_processes_on_vcan0",
    "test_frames_of_one_sender_arrive_in_order",
    "test_vcan0_and_vcan1_are_separate_buses",
    "test_open_can_bus_socketcan_and_own_messages",
    "test_bench_vcan_up_and_down",
]


@pytest.fixture(scope="module")
def guest(tmp_path_factory):
    return uml.guest_session(GUEST_DIR, tmp_path_factory.mktemp("uml"), BOOT_TIMEOUT_S)


@pytest.mark.parametrize("name", GUEST_SOCKETCAN)
def test_socketcan_inside_uml(guest, name):
    uml.assert_guest_passed(guest, name)


def bench_vcan(*args: str, as_user: str | None = None) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "bench.cli", "vcan", *args]
    if as_user:
        command = ["setpriv", f"--reuid={as_user}", f"--regid={as_user}", "--clear-groups", *command]
    return subprocess.run(command, capture_output=True, text=True, timeout=30, cwd=uml.REPO)


def test_bench_vcan_up_as_a_user_says_root_is_needed():
    as_user = "65534" if os.geteuid() == 0 and shutil.which("setpriv") else None
    if os.geteuid() == 0 and as_user is None:
        pytest.skip("setpriv (util-linux) is missing: cannot drop root to check the message")
    result = bench_vcan("up", as_user=as_user)
    assert result.returncode == 2
    assert "needs root" in result.stderr and 'transport = "zenoh"' in result.stderr


@pytest.mark.skipif(os.geteuid() != 0, reason="checks the no-vcan message, which only root reaches")
@pytest.mark.skipif(kernel_has_can(), reason="this kernel has CAN: bench vcan up would succeed here")
def test_bench_vcan_up_on_a_kernel_without_vcan_says_so():
    result = bench_vcan("up")
    assert result.returncode == 2
    assert "the kernel has no vcan module (modprobe vcan failed" in result.stderr
    assert 'use transport = "zenoh"' in result.stderr
