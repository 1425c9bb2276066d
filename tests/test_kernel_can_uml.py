"""Everything that needs the Linux kernel's CAN stack, inside user-mode Linux (tests/uml.py).

One file, so the test run's xdist workers (pyproject.toml) keep it on one worker and one UML boots
at a time: a guest starved by a second guest measures the host, not the bus. Each guest directory
is one boot; every guest test is reported here by name, so a guest test that fails, errors or
silently stops being collected fails on the host. The timeouts are hang bounds, not speed checks.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest

import uml
from bench.bus.can.transport import kernel_has_can


def _boot(pytestconfig, tmp_path_factory, guest_dir: str, name: str, boot_timeout_s: float, **kwargs):
    """One UML boot of a guest directory, selecting as this run does (`-m`: studies or not)."""
    return uml.guest_session(guest_dir, tmp_path_factory.mktemp(name), boot_timeout_s,
                             markexpr=pytestconfig.getoption("markexpr"), **kwargs)


# --- the socketcan transport on vcan0/vcan1 (tests/uml_guest/) ------------------------------------
SOCKETCAN_BOOT_TIMEOUT_S = 300   # `bench vcan` start-up alone takes tens of seconds on UML
GUEST_SOCKETCAN = [
    "test_kernel_vcan_is_the_default_transport",
    "test_frames_cross_processes_on_vcan0",
    "test_frames_of_one_sender_arrive_in_order",
    "test_vcan0_and_vcan1_are_separate_buses",
    "test_open_can_bus_socketcan_and_own_messages",
    "test_bench_vcan_up_and_down",
]


@pytest.fixture(scope="module")
def socketcan_guest(pytestconfig, tmp_path_factory):
    return _boot(pytestconfig, tmp_path_factory, "tests/uml_guest", "uml-socketcan", SOCKETCAN_BOOT_TIMEOUT_S)


@pytest.mark.timeout(SOCKETCAN_BOOT_TIMEOUT_S + 60)
@pytest.mark.parametrize("name", GUEST_SOCKETCAN)
def test_socketcan_inside_uml(socketcan_guest, name):
    uml.assert_guest_passed(socketcan_guest, name)


# --- the CAN fault suite on the kernel (tests/uml_guest_can/) -------------------------------------
# Three guest tests of 24-33 s each (idle host) plus the boot; one test hung to its own bound
# (uml.CAN_BENCH_TEST_TIMEOUT_S, 300 s) while the others run slowly on a loaded host (90 s each)
# and the boot takes a minute: 60 + 2 x 90 + 300 = 540 s.
FAULTS_BOOT_TIMEOUT_S = 600
GUEST_FAULTS = [
    "test_socketcan_clean_bus",
    "test_socketcan_dropped_commands",
    "test_socketcan_babbling_node",
]


@pytest.fixture(scope="module")
def faults_guest(pytestconfig, tmp_path_factory):
    return _boot(pytestconfig, tmp_path_factory, "tests/uml_guest_can", "uml-can-faults", FAULTS_BOOT_TIMEOUT_S,
                 per_test_timeout_s=uml.CAN_BENCH_TEST_TIMEOUT_S)


@pytest.mark.timeout(FAULTS_BOOT_TIMEOUT_S + 60)
@pytest.mark.parametrize("name", GUEST_FAULTS)
def test_can_fault_on_kernel_vcan(faults_guest, name):
    uml.assert_guest_passed(faults_guest, name)


# --- can-utils (cansend, canplayer) against the board (tests/uml_guest_canutils/) ----------------
# Four guest tests, each a few can-utils processes (seconds each to start on UML's one CPU) and
# waits of at most 10 s per step.
CAN_UTILS_BOOT_TIMEOUT_S = 300
GUEST_CAN_UTILS = [
    "test_cansend_and_canplayer_on_the_e2e_profile",
    "test_cansend_and_canplayer_on_the_secoc_profile",
    "test_the_frames_sent_are_the_dbc_frames_decoded_by_cantools",
    "test_error_frames_from_cansend_leave_the_driver_error_active_again",
]


@pytest.fixture(scope="module")
def can_utils_guest(pytestconfig, tmp_path_factory):
    if not shutil.which("cansend"):   # installed by the project's system-deps script where it can
        subprocess.run(["bash", str(uml.INSTALL_DEPS)], capture_output=True, timeout=uml.INSTALL_TIMEOUT_S)
        if not shutil.which("cansend"):
            pytest.skip("can-utils is not installed (tools/install-system-deps.sh installs it as root)")
    return _boot(pytestconfig, tmp_path_factory, "tests/uml_guest_canutils", "uml-can-utils", CAN_UTILS_BOOT_TIMEOUT_S)


@pytest.mark.timeout(CAN_UTILS_BOOT_TIMEOUT_S + 60)
@pytest.mark.parametrize("name", GUEST_CAN_UTILS)
def test_can_utils_on_kernel_vcan(can_utils_guest, name):
    uml.assert_guest_passed(can_utils_guest, name)


# --- the attitude loop over the kernel's SocketCAN (tests/uml_guest_attitude/) -------------------
# Real-time `bench run`s, one after the other: attitude_detumble_socketcan with dropped commands
# (12 s of real time) and, as a study (`make studies`: 66 s of the guest's one CPU),
# attitude_fault_all (30 s); then the pointing hold cut short (lock-step).
# Six processes a run on UML's one CPU. Measured: docs/can-bus.md.
ATTITUDE_TEST_TIMEOUT_S = 960     # each guest test; its `bench run` is bounded at 900 s inside
# Hang bounds: the two real-time runs and the lock-step run.
ATTITUDE_BOOT_TIMEOUT_S = 3 * ATTITUDE_TEST_TIMEOUT_S + 120
# Seven Python processes in the guest (pytest, the launcher, six nodes): 384M ran out (OOM killer);
# 3G held two lock-step runs at once (a planner and two gtsam smoothers). UML maps it from
# /dev/shm, and only the pages the guest touches take host memory.
ATTITUDE_GUEST_MEM = "3G"
GUEST_ATTITUDE = [
    "test_attitude_detumble_with_dropped_commands_over_kernel_socketcan",
    pytest.param("test_attitude_fault_scenario_over_kernel_socketcan[attitude_fault_all]", marks=pytest.mark.study),
    "test_pointing_hold_over_kernel_socketcan",
]


@pytest.fixture(scope="module")
def attitude_guest(pytestconfig, tmp_path_factory):
    return _boot(pytestconfig, tmp_path_factory, "tests/uml_guest_attitude", "uml-can-attitude", ATTITUDE_BOOT_TIMEOUT_S,
                 per_test_timeout_s=ATTITUDE_TEST_TIMEOUT_S, mem=ATTITUDE_GUEST_MEM)


@pytest.mark.timeout(ATTITUDE_BOOT_TIMEOUT_S + 60)
@pytest.mark.parametrize("name", GUEST_ATTITUDE)
def test_attitude_loop_on_kernel_vcan(attitude_guest, name):
    uml.assert_guest_passed(attitude_guest, name)


# --- `bench vcan up` on the host: the messages where it cannot work ------------------------------
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
