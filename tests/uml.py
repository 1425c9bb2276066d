"""Run commands and pytest selections inside user-mode Linux, for the SocketCAN tests.

The kernels here have no CAN, so a real kernel vcan comes from Debian's user-mode Linux booted with
the host filesystem as root (tools/uml/run-in-uml.sh): the guest runs this checkout's .venv Python
against vcan0/vcan1. One boot runs a whole pytest selection; the host test reads the guest's
JUnit XML and reports each guest test on its own.

Tests skip, with the reason, only when UML cannot be installed (no package and not root or no
apt) or the host refuses to boot it (the kernel never reaches init). Anything that goes wrong
after the guest is up is a failure.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from bench.runtime.can_bench import EXIT_TIMEOUT_S, STARTUP_TIMEOUT_S

REPO = Path(__file__).resolve().parents[1]
RUN_IN_UML = REPO / "tools" / "uml" / "run-in-uml.sh"
INSTALL_DEPS = REPO / "tools" / "install-system-deps.sh"
UML_KERNEL = Path("/usr/bin/linux.uml")
INSTALL_TIMEOUT_S = 300
BOOT_ERROR = 125          # run-in-uml.sh: UML or the guest's CAN setup failed
INIT_REACHED = "as init process"   # the kernel's console line when it starts our init
# The guest's memory (no swap): enough for the three processes of a CAN bench. A whole attitude
# run (seven Python processes, 80-300 MB virtual each) needs more: with 384M the guest's OOM
# killer took pytest itself (measured 2026-12). UML maps it from a file in /dev/shm, and only
# the pages the guest touches take host memory.
DEFAULT_MEM = "384M"
GUEST_NICE = -10          # the guest's priority on the host, as root (run)
# Each guest test's bound (tests may set their own): one test that hangs fails alone and the
# boot still reports the others.
PER_TEST_TIMEOUT_S = 90
# A guest test on bench.runtime.can_bench.CanBench (the fault suite): longer than CanBench's own
# bounds (two node start-ups of STARTUP_TIMEOUT_S each, two exits of EXIT_TIMEOUT_S, 2.4 s of
# driving) so that a slow start fails with CanBench's message naming the node, not with a bare
# timeout; plus the two re-runs tests/test_can_faults.py makes of a run the host starved (about
# 60 s each on a loaded host), so that a healthy test slowed by host load is not cut off.
# Measured 2026-12 in UML on a host at load average ~9: `bench node mtq` spawn to first
# heartbeat 5.8-15.8 s (lazy CLI).
CAN_BENCH_TEST_TIMEOUT_S = 2 * STARTUP_TIMEOUT_S + 2 * EXIT_TIMEOUT_S + 40 + 2 * 60


class UmlUnavailable(Exception):
    """UML cannot run on this host; the message is the reason tests skip with."""


@dataclass
class UmlResult:
    returncode: int
    output: str
    job_dir: Path


def ensure_uml() -> None:
    """Install user-mode Linux if missing and possible (root with apt), or raise UmlUnavailable.

    `make test` installs it first through tools/install-system-deps.sh; this covers a bare
    `pytest` run on the same kind of machine.
    """
    if UML_KERNEL.exists() and shutil.which("ip") and shutil.which("insmod"):
        return
    result = subprocess.run(["bash", str(INSTALL_DEPS)], capture_output=True, text=True, timeout=INSTALL_TIMEOUT_S)
    if not UML_KERNEL.exists():
        said = (result.stdout + result.stderr).strip() or "no output"
        raise UmlUnavailable(f"user-mode Linux is not installed and could not be installed: {said}")


def run(command: list[str], job_dir: Path, *, timeout_s: float = 60, mem: str = DEFAULT_MEM) -> UmlResult:
    """Boot UML, run `command` (from the repository root) inside it, and return its result."""
    ensure_uml()
    # The guest is a machine of its own running real-time CAN tests on its one emulated CPU. As
    # root it runs at a higher priority (nice -10) than the host's other work (the suite's other
    # xdist workers, whatever else loads the host), so that the guest's timing is the guest's:
    # with three workers and both cores busy, a guest starved of CPU missed a flood's heartbeat
    # timeout altogether.
    boost = ["nice", "-n", str(GUEST_NICE)] if os.geteuid() == 0 and shutil.which("nice") else []
    proc = subprocess.run(
        [*boost, "bash", str(RUN_IN_UML), "--timeout", str(int(timeout_s)), "--mem", mem, "--job", str(job_dir), "--", *command],
        capture_output=True, text=True, cwd=REPO, timeout=timeout_s + 15,
    )
    console = job_dir / "console.log"
    if proc.returncode == BOOT_ERROR and not (job_dir / "status").exists():
        console_text = console.read_text(errors="replace") if console.exists() else ""
        if INIT_REACHED not in console_text:
            tail = " | ".join(console_text.strip().splitlines()[-3:]) or proc.stderr.strip()
            raise UmlUnavailable(f"user-mode Linux does not boot on this host: {tail}")
    return UmlResult(proc.returncode, proc.stdout + proc.stderr, job_dir)


def run_pytest(selection: list[str], job_dir: Path, *, timeout_s: float = 60,
               per_test_timeout_s: float = PER_TEST_TIMEOUT_S, mem: str = DEFAULT_MEM) -> tuple[UmlResult, dict[str, str]]:
    """Run a pytest selection inside one UML boot; returns the result and {test name: outcome}.

    Guest tests live in files named guest_*.py so the host's pytest never collects them.
    per_test_timeout_s bounds each guest test (a timeout marker on the test wins), so one hung
    test fails alone and the boot still reports the others within timeout_s. A CAN fault test
    takes 12-33 s on UML's one emulated CPU on an idle host (measured 2026-12: 24-33 s when run
    six in a row); under host load its two node start-ups alone may take up to CanBench's bound
    each, hence CAN_BENCH_TEST_TIMEOUT_S for those.
    """
    junit = job_dir / "junit.xml"
    # -n 0: the guest's tests run one at a time (pyproject's addopts spreads the host's suite over
    # xdist workers; two CAN benches at once would share the guest's vcan0/vcan1).
    command = [sys.executable, "-m", "pytest", "-q", "-n", "0", "-p", "no:cacheprovider", "-o", "python_files=guest_*.py",
               f"--junitxml={junit}", f"--basetemp={job_dir / 'tmp'}", f"--timeout={per_test_timeout_s:g}", *selection]
    result = run(command, job_dir, timeout_s=timeout_s, mem=mem)
    outcomes: dict[str, str] = {}
    if junit.exists():
        for case in ET.parse(junit).getroot().iter("testcase"):
            outcome = "passed"
            for child in case:
                if child.tag in ("failure", "error"):
                    outcome = "failed"
                elif child.tag == "skipped":
                    outcome = "skipped"
            outcomes[case.get("name")] = outcome
    return result, outcomes


def guest_session(guest_dir: Path, job_dir: Path, timeout_s: float, per_test_timeout_s: float = PER_TEST_TIMEOUT_S,
                  mem: str = DEFAULT_MEM, markexpr: str = ""):
    """Run a guest pytest directory in one UML boot; skip (with UML's reason) where it cannot boot.
    markexpr: the host run's -m, so the guest selects what the host does (studies or not)."""
    import pytest

    selection = [*(("-m", markexpr) if markexpr else ()), str(guest_dir)]
    try:
        return run_pytest(selection, job_dir, timeout_s=timeout_s, per_test_timeout_s=per_test_timeout_s, mem=mem)
    except UmlUnavailable as exc:
        pytest.skip(str(exc))


def assert_guest_passed(guest, name: str) -> None:
    """One guest test's outcome, with the end of UML's console where it did not pass."""
    result, outcomes = guest
    assert outcomes.get(name) == "passed", (
        f"guest test {name}: {outcomes.get(name, 'did not run')} (UML exit {result.returncode})\n"
        f"{result.output[-4000:]}"
    )
