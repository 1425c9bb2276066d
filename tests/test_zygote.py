"""Nodes forked from the launcher's pre-imported zygote behave as nodes started by exec: the same
output and exit codes (the exec path is the reference), the run's process group, death with their
owner, and the exec path whenever the zygote cannot start a node as exec would."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from bench.bus.session import free_loopback_port
from bench.runtime import zygote as zyg
from bench.runtime.ownership import ORPHAN_EXIT_CODE, child_environment, kill_group, process_state
from bench.runtime.process import start_node
from conftest import REPO

BENCH = [sys.executable, "-m", "bench.cli"]
WAIT_S = 60.0


@pytest.fixture
def zygote(monkeypatch):
    monkeypatch.chdir(REPO)
    started = zyg.Zygote.start(child_environment())
    assert started is not None
    yield started
    started.close()


def _by_exec(cmd, log_path) -> int:
    with open(log_path, "w") as log:
        return subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, cwd=REPO,
                              env=child_environment(), timeout=WAIT_S).returncode


@pytest.mark.parametrize("args,expected_code", [(["scenarios"], 0),
                                                (["node", "no-such-node", "--run-id", "x"], 2)])
def test_a_forked_command_prints_and_exits_as_by_exec(zygote, tmp_path, args, expected_code):
    reference_code = _by_exec(BENCH + args, tmp_path / "exec.log")
    process = zygote.spawn(BENCH + args, tmp_path / "fork.log")
    assert process.wait(timeout=WAIT_S) == reference_code == expected_code
    assert (tmp_path / "fork.log").read_text() == (tmp_path / "exec.log").read_text()
    assert (tmp_path / "fork.log").stat().st_size > 0


def _waiting_plant(tmp_path, name: str) -> list[str]:
    """A plant that waits (up to 120 s) for an estimator that never comes: a node that runs on."""
    return BENCH + ["node", "plant", "--run-id", f"zygote-{name}", "--scenario", "rendezvous_lqr",
                    "--listen", f"tcp/127.0.0.1:{free_loopback_port()}", "--run-dir", str(tmp_path / name),
                    "--wait-for", "estimator"]


def _until_owned(process) -> None:
    """Until the node has set its death signal and forked its watchdog (ownership.die_with_launcher)."""
    deadline = time.monotonic() + WAIT_S
    while process.poll() is None and time.monotonic() < deadline:
        for entry in os.listdir("/proc"):
            try:
                with open(f"/proc/{entry}/stat") as f:
                    if entry.isdigit() and int(f.read().rsplit(")", 1)[1].split()[1]) == process.pid:
                        return
            except (OSError, ValueError):
                pass
        time.sleep(0.05)


def test_forked_nodes_share_the_run_group_and_report_the_signal_that_killed_them(zygote, tmp_path):
    first = zygote.spawn(_waiting_plant(tmp_path, "a"), tmp_path / "a.log", process_group=0)
    second = zygote.spawn(_waiting_plant(tmp_path, "b"), tmp_path / "b.log", process_group=first.pid)
    assert os.getpgid(first.pid) == first.pid and os.getpgid(second.pid) == first.pid
    # ps shows the node once the child has rewritten its command line, just after the fork
    deadline = time.monotonic() + WAIT_S
    while "bench.cli\0node\0plant" not in (cmdline := open(f"/proc/{first.pid}/cmdline", "rb").read().decode()):
        assert time.monotonic() < deadline, cmdline
        time.sleep(0.01)
    assert first.poll() is None and second.poll() is None
    second.kill()
    assert second.wait(timeout=WAIT_S) == -signal.SIGKILL          # as subprocess.Popen reports it
    assert first.poll() is None
    kill_group(first.pid, signal.SIGKILL)
    assert first.wait(timeout=WAIT_S) == -signal.SIGKILL
    second.kill()                                                    # already reaped: no error, no signal sent


def test_wait_with_a_timeout_raises_as_popen_does(zygote, tmp_path):
    process = zygote.spawn(_waiting_plant(tmp_path, "t"), tmp_path / "t.log")
    with pytest.raises(subprocess.TimeoutExpired):
        process.wait(timeout=0.2)
    process.terminate()
    assert process.wait(timeout=WAIT_S) is not None


def test_nodes_die_with_their_zygote_and_count_as_orphaned(zygote, tmp_path):
    process = zygote.spawn(_waiting_plant(tmp_path, "o"), tmp_path / "o.log")
    _until_owned(process)
    assert process.poll() is None
    zygote.process.kill()               # as the kernel does when the launcher dies (PDEATHSIG)
    deadline = time.monotonic() + WAIT_S
    while process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert process.returncode == ORPHAN_EXIT_CODE
    state = process_state(process.pid)
    assert state is None or state.state == "Z"
    with pytest.raises(zyg.ZygoteFailed):                        # and the next node goes by exec
        zygote.spawn(BENCH + ["scenarios"], tmp_path / "after.log")


def test_start_node_takes_the_exec_path_when_the_zygote_cannot_match_it(tmp_path, monkeypatch):
    monkeypatch.chdir(REPO)
    kwargs = {"process_group": 0, "env": child_environment()}
    zygote = zyg.Zygote(subprocess.Popen(["sleep", "60"], stdin=subprocess.PIPE), os.open(os.devnull, os.O_RDONLY),
                        kwargs["env"], os.getcwd())     # can_start never asks the zygote itself
    cmd = BENCH + ["scenarios"]
    assert zygote.can_start(cmd, kwargs)
    assert not zygote.can_start(cmd, {**kwargs, "env": {**kwargs["env"], "EXTRA": "1"}})   # another environment
    assert not zygote.can_start(cmd, {"env": kwargs["env"]})                              # no group of its own
    assert not zygote.can_start(["/bin/true"], kwargs)
    monkeypatch.chdir(tmp_path)                                                           # another directory
    assert not zygote.can_start(cmd, kwargs)
    monkeypatch.chdir(REPO)
    monkeypatch.setenv("EXTRA", "1")
    process = start_node("plant", "x", tmp_path / "none.json", "tcp/127.0.0.1:1", tmp_path, tmp_path / "p.log",
                         popen_kwargs={"process_group": 0, "env": child_environment()}, zygote=zygote,
                         extra_args=["--help"])
    assert isinstance(process, subprocess.Popen)
    assert process.wait(timeout=WAIT_S) == 0
    zygote.process.kill()
    zygote.close()


def test_bench_node_start_exec_turns_the_zygote_off(monkeypatch):
    monkeypatch.setenv(zyg.NODE_START_ENV, "exec")
    assert not zyg.enabled()
    monkeypatch.setenv(zyg.NODE_START_ENV, "zygote")
    assert zyg.enabled()



def test_the_zygote_started_early_serves_the_launcher_only_if_it_matches(monkeypatch):
    """`bench run` starts the zygote before the launcher's imports; the launcher takes it only if
    its nodes' environment and directory are the launcher's, else starts its own and kills it."""
    monkeypatch.chdir(REPO)
    zyg.Zygote.start_early()
    early = zyg._early
    assert early is not None
    taken = zyg.Zygote.for_launcher(child_environment())
    try:
        assert taken is early and zyg._early is None
    finally:
        taken.close()
    zyg.Zygote.start_early()
    early = zyg._early
    other = zyg.Zygote.for_launcher(child_environment({"BENCH_SOMETHING_ELSE": "1"}))
    try:
        assert other is not early and early.process.poll() is not None
        assert other.env["BENCH_SOMETHING_ELSE"] == "1"
    finally:
        other.close()
    zyg.Zygote.start_early()
    early = zyg._early
    zyg.Zygote.close_early()       # bad input: nobody took it
    assert zyg._early is None and early.process.wait(timeout=WAIT_S) is not None

# Imported by no node: each costs every run's zygote 0.2-0.5 s of start-up; the few functions that
# need them import them where they are called (the tube MPC's pole placement, the nonlinear plant's
# integrator, the report's figures).
NOT_AT_START = ("scipy.stats", "scipy.signal", "scipy.integrate", "matplotlib")


def test_the_zygote_preloads_no_package_a_node_needs_only_for_some_scenarios():
    code = ("import sys; from bench.runtime import zygote; zygote._preload(); "
            f"print(sorted(m for m in {NOT_AT_START!r} if m in sys.modules))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO,
                            env=child_environment(), timeout=WAIT_S)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]", f"imported at every node's start: {result.stdout.strip()}"
