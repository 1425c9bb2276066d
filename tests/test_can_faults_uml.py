"""The SocketCAN subset of the fault suite on a kernel vcan inside user-mode Linux (tests/uml.py).

One UML boot runs every test of tests/uml_guest_can/; each is reported here by name, so a guest
test that fails, errors or silently stops being collected fails on the host.
"""
from __future__ import annotations

import pytest

import uml

GUEST_DIR = "tests/uml_guest_can"
# Six guest tests of 24-33 s each in one boot (measured, idle host: 158 s in all) plus the boot;
# a bound for a hang, not a speed check: one test hung to its own bound
# (uml.CAN_BENCH_TEST_TIMEOUT_S, 300 s) while the five others run slowly on a loaded host
# (90 s each) and the boot takes a minute: 60 + 5 x 90 + 300 = 810 s.
BOOT_TIMEOUT_S = 840
GUEST_TESTS = [
    "test_socketcan_clean_bus",
    "test_socketcan_dropped_commands",
    "test_socketcan_corrupted_commands",
    "test_socketcan_spoofed_commands",
    "test_socketcan_board_death",
    "test_socketcan_babbling_node",
]

pytestmark = pytest.mark.timeout(BOOT_TIMEOUT_S + 60)


@pytest.fixture(scope="module")
def guest(tmp_path_factory):
    return uml.guest_session(GUEST_DIR, tmp_path_factory.mktemp("uml-can-faults"), BOOT_TIMEOUT_S,
                             per_test_timeout_s=uml.CAN_BENCH_TEST_TIMEOUT_S)


@pytest.mark.parametrize("name", GUEST_TESTS)
def test_can_fault_on_kernel_vcan(guest, name):
    uml.assert_guest_passed(guest, name)
