"""can-utils (cansend, canplayer) against the board on a kernel vcan in user-mode Linux.

One UML boot runs tests/uml_guest_canutils/; each guest test is reported here by name.
"""
from __future__ import annotations

import shutil
import subprocess

import pytest

import uml

GUEST_DIR = "tests/uml_guest_canutils"
# Four guest tests, each a few can-utils processes (seconds each to start on UML's one CPU) and
# waits of at most 10 s per step; a bound for a hang, not a speed check.
BOOT_TIMEOUT_S = 300
GUEST_TESTS = [
    "test_cansend_and_canplayer_on_the_e2e_profile",
    "test_cansend_and_canplayer_on_the_secoc_profile",
    "test_the_frames_sent_are_the_dbc_frames_decoded_by_cantools",
    "test_error_frames_from_cansend_leave_the_driver_error_active_again",
]

pytestmark = pytest.mark.timeout(BOOT_TIMEOUT_S + 60)


@pytest.fixture(scope="module")
def guest(tmp_path_factory):
    if not shutil.which("cansend"):   # installed by the project's system-deps script where it can
        subprocess.run(["bash", str(uml.INSTALL_DEPS)], capture_output=True, timeout=uml.INSTALL_TIMEOUT_S)
        if not shutil.which("cansend"):
            pytest.skip("can-utils is not installed (tools/install-system-deps.sh installs it as root)")
    return uml.guest_session(GUEST_DIR, tmp_path_factory.mktemp("uml-can-utils"), BOOT_TIMEOUT_S)


@pytest.mark.parametrize("name", GUEST_TESTS)
def test_can_utils_on_kernel_vcan(guest, name):
    uml.assert_guest_passed(guest, name)
