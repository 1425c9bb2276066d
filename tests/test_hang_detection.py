"""Hung or slow: a stopped process (state T, no CPU progress) is hung after a short grace; one that
is merely starved (runnable, CPU time advancing) is given until hang_timeout_s."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from bench.launcher import Child, NodeFailed, TokenLoss, _check_liveliness
from bench.runtime.ownership import process_state
from bench.scenario import LivelinessConfig

LIVELINESS = LivelinessConfig(lease_s=2.0, stopped_grace_s=1.0, hang_timeout_s=15.0)
BUSY = [sys.executable, "-c", "while True: pass"]


@pytest.fixture
def busy_child(tmp_path):
    process = subprocess.Popen(BUSY)
    yield Child("controller", process, tmp_path / "controller.log")
    process.send_signal(signal.SIGCONT)
    process.kill()
    process.wait()


def wait_state(pid: int, wanted: str) -> None:
    deadline = time.monotonic() + 30
    while process_state(pid).state != wanted:
        assert time.monotonic() < deadline, process_state(pid)
        time.sleep(0.01)


def test_process_state_agrees_with_ps(busy_child):
    pid = busy_child.process.pid
    busy_child.process.send_signal(signal.SIGSTOP)
    wait_state(pid, "T")
    ps = subprocess.run(["ps", "-o", "stat=", "-p", str(pid)], capture_output=True, text=True).stdout.strip()
    assert ps.startswith("T")
    before = process_state(pid).cpu_ticks
    time.sleep(0.3)
    assert process_state(pid).cpu_ticks == before         # stopped: no CPU progress
    assert process_state(2**22 + 1) is None                # no such pid


def test_a_slow_process_whose_token_lapsed_is_not_called_hung(busy_child):
    lost = {"controller": TokenLoss(time.monotonic() - 10.0, process_state(busy_child.process.pid).cpu_ticks)}
    _check_liveliness([busy_child], lost, LIVELINESS)        # 10 s < hang_timeout_s: still only slow


def test_a_stopped_process_is_hung_after_the_grace(busy_child):
    pid = busy_child.process.pid
    busy_child.process.send_signal(signal.SIGSTOP)
    wait_state(pid, "T")
    lost = {"controller": TokenLoss(time.monotonic() - 0.2, process_state(pid).cpu_ticks)}
    _check_liveliness([busy_child], lost, LIVELINESS)        # inside the grace: not yet
    lost["controller"] = TokenLoss(time.monotonic() - 1.5, process_state(pid).cpu_ticks)
    with pytest.raises(NodeFailed, match=r"process 'controller' .* is stopped \(state T, no CPU progress\)"):
        _check_liveliness([busy_child], lost, LIVELINESS)


def test_a_token_gone_past_the_hang_timeout_is_hung_even_if_running(busy_child):
    lost = {"controller": TokenLoss(time.monotonic() - 16.0, -1)}     # it used CPU since
    with pytest.raises(NodeFailed, match="stopped answering on Zenoh.*CPU time still advancing"):
        _check_liveliness([busy_child], lost, LIVELINESS)


class _Uncollected:
    """A process whose exit its parent has not collected yet, as a zygote-forked node's can look
    to the launcher for a while (poll() None, /proc state Z)."""

    def __init__(self, pid: int):
        self.pid = pid

    def poll(self):
        return None


def test_an_exited_process_not_yet_collected_is_not_called_hung(tmp_path):
    pid = os.fork()
    if pid == 0:
        os._exit(0)
    try:
        wait_state(pid, "Z")
        child = Child("plant", _Uncollected(pid), tmp_path / "plant.log")
        lost = {"plant": TokenLoss(time.monotonic() - 16.0, 0)}       # past hang_timeout_s: exited, not hung
        _check_liveliness([child], lost, LIVELINESS)
        _check_liveliness([child], lost, LIVELINESS, final=True)
        lost["plant"] = TokenLoss(time.monotonic() - 31.0, 0)         # uncollected for another hang_timeout_s
        with pytest.raises(NodeFailed, match=r"process 'plant' .* exited, but its exit status was not collected"):
            _check_liveliness([child], lost, LIVELINESS)
    finally:
        os.waitpid(pid, 0)


def test_a_peer_whose_token_comes_back_is_not_lost():
    import logging

    from bench.runtime.node import NodeContext
    from bench.scenario import parse_scenario

    ctx = NodeContext("plant", "r", parse_scenario({"name": "x"}), None, None, logging.getLogger("t"))
    ctx.lost_since_s["controller"] = time.monotonic() - 3.0
    assert ctx.lost_peer(15.0) is None and ctx.lost_peer(1.0) == "controller"
    ctx.lost_since_s.pop("controller")         # what watch_peers does when the token reappears
    assert ctx.lost_peer(0.0) is None
