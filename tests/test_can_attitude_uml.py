"""The attitude loop over the kernel's SocketCAN, inside user-mode Linux (tests/uml.py).

One UML boot runs every test of tests/uml_guest_attitude/ (two real-time `bench run`s of
attitude_detumble_socketcan, clean and with dropped commands); each is reported here by name, so a
guest test that fails, errors or silently stops being collected fails on the host.
"""
from __future__ import annotations

import pytest

import uml

GUEST_DIR = "tests/uml_guest_attitude"
# Two runs of six processes each on UML's one CPU: start-up 1-3 min a run under host load (up to
# the scenario's 600 s startup_timeout_s), 12 s of real time, shutdown. Bounds for a hang, not a
# speed check.
PER_TEST_TIMEOUT_S = 960     # each guest test; its `bench run` is bounded at 900 s inside
BOOT_TIMEOUT_S = 2 * PER_TEST_TIMEOUT_S + 120
# Seven Python processes in the guest (pytest, the launcher, six nodes): 384M ran out (OOM killer).
GUEST_MEM = "1536M"
GUEST_TESTS = [
    "test_attitude_detumble_over_kernel_socketcan",
    "test_attitude_detumble_with_dropped_commands_over_kernel_socketcan",
]

pytestmark = pytest.mark.timeout(BOOT_TIMEOUT_S + 60)


@pytest.fixture(scope="module")
def guest(tmp_path_factory):
    return uml.guest_session(GUEST_DIR, tmp_path_factory.mktemp("uml-can-attitude"), BOOT_TIMEOUT_S,
                             per_test_timeout_s=PER_TEST_TIMEOUT_S, mem=GUEST_MEM)


@pytest.mark.parametrize("name", GUEST_TESTS)
def test_attitude_loop_on_kernel_vcan(guest, name):
    uml.assert_guest_passed(guest, name)
