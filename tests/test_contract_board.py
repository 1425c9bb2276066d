"""`bench contract check board` (issue 47): a magnetorquer board checked from outside, on its CAN
bus, by a flight side that speaks only mtq.dbc (bench/contract_check/board_check.py).

The bench's own board (`bench node mtq`, started by the check's --command and connected to the
check's hub) passes on both command profiles, and so does one already running on its own bus (the
check boots it with an NMT reset node). Broken on purpose (`bench node mtq --break MODE`,
bench/bus/can/board_breaks.py), it fails, each mode naming its problem. Each run takes some 10 s.
"""
from __future__ import annotations

import json
import subprocess
import sys
import time

import msgspec
import numpy as np
import pytest

from bench.bus.can import protocol as p
from bench.bus.can import run_key
from bench.bus.can.config import BusSpec
from bench.bus.can.transport import open_bus
from bench.bus.session import SessionOptions, free_loopback_port, loopback_endpoint, open_session
from bench.contract_check.board_flight import BoardContract
from bench.contract_check.board_run import board_scenario, run_board_check
from bench.runtime.priority import set_realtime_priority
from conftest import REPO, run_bench_cli

pytestmark = pytest.mark.timeout(900)


def _board_command(*extra: str) -> str:
    return " ".join([sys.executable, "-m", "bench.cli", "node", "mtq", "--run-id {run_id} --scenario {scenario}",
                     "--connect {connect} --run-dir {run_dir}", *extra])


def _check(runs_dir, run_id: str, *args: str) -> tuple[subprocess.CompletedProcess, dict]:
    result = run_bench_cli("contract", "check", "board", "--runs-dir", str(runs_dir), "--run-id", run_id, *args,
                           timeout_s=240)
    path = runs_dir / run_id / "contract_check.json"
    return result, (json.loads(path.read_text()) if path.is_file() else {})


@pytest.fixture(scope="module")
def runs_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("board_check")


# --- fast -------------------------------------------------------------------------------------
def test_the_contract_is_the_board_configuration_and_its_set_point_rule():
    contract = BoardContract.of(board_scenario(None).can, 0.03, None, real_time_only=False)
    assert (contract.profile, contract.heartbeat_period_s, contract.command_timeout_s, contract.max_dipole_am2,
            contract.dipole_resolution_am2, contract.command_period_s) == ("secoc", 0.1, 0.1, 0.2, 1e-3, 0.02)
    assert contract.setpoint_echo and contract.heartbeat_timeout_s == pytest.approx(0.25)
    setpoint, saturated = contract.setpoint(np.array([0.0404, -0.0803, 0.35]), p.MODE_DIPOLE)
    np.testing.assert_allclose(setpoint, [0.040, -0.080, 0.2], atol=1e-12)
    assert saturated
    assert contract.setpoint(np.array([0.1, 0.1, 0.1]), p.MODE_OFF)[0].tolist() == [0.0, 0.0, 0.0]


def test_a_board_break_is_refused_on_another_node(tmp_path):
    result = run_bench_cli("node", "plant", "--run-id", "brk", "--scenario", "rendezvous_lqr", "--run-dir",
                           str(tmp_path / "brk"), "--break", "accept-bad-crc")
    assert result.returncode == 2, result.stdout + result.stderr
    assert "--break accept-bad-crc breaks the board (node mtq), not plant" in result.stderr


# --- the bench's board passes -----------------------------------------------------------------
def test_the_bench_board_passes_the_board_check(runs_dir):
    result, verdict = _check(runs_dir, "board-pass", "--command", _board_command())
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.startswith("contract check board: pass (secoc, node 0x10 on zenoh board; heartbeat "), result.stdout
    assert "refused with EMCY 0x8100: bad-crc, repeated-counter, bad-mac, old-freshness, plain-command, plain-nmt-stop" \
        in result.stdout
    assert verdict["passed"] and verdict["problems"] == []
    m, c = verdict["measured"], verdict["contract"]
    assert m["boot"]["first_heartbeat_state"] == "boot-up"
    assert m["heartbeat"]["states"] == ["boot-up", "pre-operational", "operational", "pre-operational", "operational",
                                        "stopped", "operational", "boot-up", "pre-operational"]
    assert abs(m["heartbeat"]["period_median_s"] - c["heartbeat_period_s"]) <= 0.1 * c["heartbeat_period_s"]
    assert m["echo"]["echoed"] == m["echo"]["commands"] > 100
    assert c["command_timeout_s"] <= m["command_timeout"]["emcy_after_s"] <= c["command_timeout_s"] + c["margin_s"]
    assert [r["moved"] for r in m["refusals"]] == [[]] * 6
    held = {r["hold"]: r for r in m["commands"]}
    assert held["saturated"]["expected_am2"] == [0.2, -0.2, 0.1] and held["saturated"]["saturated_flag"] == [True]
    assert held["quantised"]["echo_am2"] == pytest.approx([0.040, -0.080, 0.003], abs=1e-9)
    assert (runs_dir / "board-pass" / "can.log").stat().st_size > 0


def test_the_bench_board_on_the_e2e_profile_passes(runs_dir):
    scenario = runs_dir / "board_e2e.json"
    scenario.write_text(json.dumps({"name": "board_e2e", "run": {"seed": 1},
                                    "can": {"board": {"setpoint_echo": True}, "security": {"profile": "e2e"}}}))
    result, verdict = _check(runs_dir, "board-e2e", "--scenario", str(scenario), "--command", _board_command())
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.startswith("contract check board: pass (e2e, ")
    assert [r["probe"] for r in verdict["measured"]["refusals"]] == ["bad-crc", "repeated-counter"]


def test_a_board_already_running_on_its_own_bus_is_reset_and_passes(tmp_path):
    """No --command: the board is up and operational on its bus before the check; the check boots it
    with an NMT reset node first (no boot-up to see at start), then checks the rest."""
    scenario = run_key.with_run_key(board_scenario(None))
    path = tmp_path / "scenario.json"
    run_key.write_private(path, msgspec.json.encode(scenario))
    hub = loopback_endpoint(free_loopback_port())
    set_realtime_priority(scenario.can.realtime_priority, inherited=True)   # the Zenoh threads, as the CLI's
    session = open_session(SessionOptions(listen=(hub,)))
    set_realtime_priority(0)
    board = None
    try:
        # The board's own run directory: the check never sees it.
        board = subprocess.Popen([sys.executable, "-m", "bench.cli", "node", "mtq", "--run-id", "own", "--scenario",
                                  str(path), "--connect", hub, "--run-dir", str(tmp_path / "board")], cwd=REPO,
                                 stdout=open(tmp_path / "board.log", "w"), stderr=subprocess.STDOUT)
        bus = open_bus(BusSpec(interface="zenoh", channel="board"), run_id="own", session=session)
        protocol = scenario.can.protocol()
        deadline = time.monotonic() + 60
        state = None
        while state != p.NMT_OPERATIONAL:
            assert time.monotonic() < deadline and board.poll() is None, (tmp_path / "board.log").read_text()
            msg = bus.recv(0.1)
            frame = protocol.decode(msg) if msg is not None else None
            if frame is not None and frame.name == p.HEARTBEAT:
                state = frame.signals["NmtState"]
                if state != p.NMT_OPERATIONAL:
                    bus.send(protocol.nmt(p.NMT_START, sent_s=time.monotonic()))
        bus.shutdown()
        verdict = run_board_check(scenario, "own", tmp_path / "check", None, BusSpec(interface="zenoh", channel="board"),
                                  None, None, bus_session=session)
    finally:
        set_realtime_priority(0)
        if board is not None:
            board.terminate()           # the board this test started, by its handle
            board.wait(timeout=20)
        session.close()
    assert verdict.passed, verdict.text("board")
    measured = json.loads((tmp_path / "check" / "contract_check.json").read_text())["measured"]
    assert measured["boot"] == {"first_heartbeat_state": "operational", "first_heartbeat_after_s": measured["boot"][
        "first_heartbeat_after_s"], "reset_node_at_start": True, "pre_operational_heartbeats": 4}


# --- broken on purpose, it fails ----------------------------------------------------------------
BROKEN = {
    "slow-heartbeat": "heartbeat: period 200.0 ms (median of",
    "no-boot-up": "boot-up: no boot-up message at start (CiA 301: a heartbeat with state 0 first)",
    "obey-plain-nmt": "plain NMT stop on secoc (identifier 0, no MAC): not refused: heartbeat said stopped",
    "no-saturation": "commands: saturated [0.35, -0.5, 0.1] A m^2: telemetry applied [0.35, -0.5, 0.1], the contract's "
                     "[0.2, -0.2, 0.1]",
    "no-safe-state": "command timeout: no safe state: the telemetry never said coils off",
    "accept-bad-crc": "bad CRC (a command whose E2E CRC is wrong, its MAC authentic on secoc): not refused: set-point "
                      "echoed [-0.15, 0.15, -0.15]",
    "accept-stale": "old freshness (an authentic command whose freshness value is ten windows old): not refused: "
                    "set-point echoed [-0.15, 0.15, -0.15]",
    "no-echo": "set-point echo: no MTQ_TLM_SETPOINT with CommandApplied 1",
}


@pytest.mark.parametrize("mode", sorted(BROKEN))
def test_a_broken_board_fails_the_check_naming_the_problem(runs_dir, mode):
    result, verdict = _check(runs_dir, f"board-{mode}", "--command", _board_command("--break", mode))
    assert result.returncode == 1, result.stdout + result.stderr
    assert result.stdout.startswith("contract check board: FAIL (")
    assert any(problem.startswith(BROKEN[mode]) for problem in verdict["problems"]), result.stdout
    assert f"  - {BROKEN[mode]}" in result.stdout


class _HoldsUpOneNmtReset:
    """The check's bus, as a loaded host makes it once: the first NMT reset node leaves 0.2 s after
    the check stamped it (its freshness value), four freshness windows late."""
    HOLD_S = 0.2

    def __init__(self, bus, protocol: p.Protocol):
        self.bus, self.protocol, self.held = bus, protocol, 0

    def send(self, msg, timeout=None):
        frame = self.protocol.decode(msg)
        if frame is not None and frame.name == p.NMT_AUTH and frame.signals["Command"] == p.NMT_RESET_NODE \
                and not self.held:
            self.held += 1
            time.sleep(self.HOLD_S)
        self.bus.send(msg, timeout)

    def __getattr__(self, name):
        return getattr(self.bus, name)


def test_an_nmt_frame_this_host_delivered_stale_is_sent_again_not_blamed_on_the_board(tmp_path, monkeypatch):
    """The board refuses the late NMT reset (EMCY 0x8100 STALE, counter 0) as it must; the check
    sees the refusal came back after the freshness window, sends the reset again, and passes."""
    import bench.contract_check.board_run as board_run
    scenario = run_key.with_run_key(board_scenario(None))
    contract = BoardContract.of(scenario.can, 0.03, None, real_time_only=False)
    held = []

    def open_held_bus(spec, **kwargs):
        held.append(_HoldsUpOneNmtReset(open_bus(spec, **kwargs), p.Protocol(contract.node_id, "secoc",
                                                                              scenario.can.security.key)))
        return held[-1]

    monkeypatch.setattr(board_run, "open_bus", open_held_bus)
    verdict = run_board_check(scenario, "late-nmt", tmp_path / "check", _board_command(), None, None, None)
    assert verdict.passed, verdict.text("board")
    assert held[0].held == 1
    measured = json.loads((tmp_path / "check" / "contract_check.json").read_text())["measured"]
    assert measured["late_on_arrival"]["nmt"] == 1
    assert "1 NMT frame(s)" in verdict.summary
    assert measured["heartbeat"]["states"][-2:] == ["boot-up", "pre-operational"]


def test_a_board_this_host_froze_in_the_command_timeout_is_tried_again_not_failed(tmp_path, monkeypatch):
    """The host stops the bench's board (SIGSTOP) for 0.2 s just after the check's last command,
    as a loaded host can: its timeout EMCY comes 0.2 s late and its frames stop. The check sees the
    board fall silent, repeats the command timeout, which then holds, and excuses the telemetry gap
    the board's own lateness record explains; it passes, saying so (the negative: a board late on
    its timeout while it keeps sending fails, test_a_broken_board_fails_the_check_naming_the_problem
    [no-safe-state])."""
    import os
    import signal
    import threading

    from bench.contract_check.board_check import BoardCheck

    frozen = []
    attempt = BoardCheck._timeout_attempt

    def freeze(pid: int) -> None:
        os.kill(pid, signal.SIGSTOP)
        time.sleep(0.2)
        os.kill(pid, signal.SIGCONT)
        frozen.append(pid)

    def first_attempt_frozen(self):
        if not frozen:
            threading.Timer(0.03, freeze, (self.process.pid,)).start()
        return attempt(self)

    monkeypatch.setattr(BoardCheck, "_timeout_attempt", first_attempt_frozen)
    verdict = run_board_check(board_scenario(None), "frozen", tmp_path / "check", _board_command(), None, None, None)
    assert frozen
    assert verdict.passed, verdict.text("board")
    measured = json.loads((tmp_path / "check" / "contract_check.json").read_text())["measured"]
    repeated = measured["command_timeout"]["repeated_attempts"]
    assert len(repeated) == 1 and repeated[0]["held_up"].startswith("the board silent for ")
    assert any("EMCY 0x8250" in problem for problem in repeated[0]["problems"])
    assert measured["command_timeout"]["emcy_after_s"] <= measured["command_timeout"]["bound_s"]
    gaps = measured.get("held_up_by_host", [])
    assert all(g["gap_s"] - g["host_held_s"] <= 0.3 for g in gaps)
    assert "held up by this host: command timeout repeated 1x (the board silent for" in verdict.summary


@pytest.mark.parametrize("when", ["after", "before"])
def test_a_probe_this_host_held_the_commands_up_around_is_sent_again_not_failed(tmp_path, monkeypatch, when):
    """Around the repeated-counter probe the check's commands stop for 0.2 s, as a loaded host once
    made them (CI22: after it, CI24: before it): the board rightly times out (EMCY 0x8250), its coils
    leave the steady dipole, and the probe may look accepted. The check sees its own commands 0.2 s
    apart, over the command timeout, sends the probe again if it failed, which is then refused, takes
    the board's timeout EMCY as the board doing its job (it had no command applied for the timeout),
    and passes saying so."""
    from bench.contract_check.board_flight import FlightSide

    held = []
    probe = FlightSide.probe

    def probe_with_hold_up(self, kind, dipole_am2):
        hold = kind == "repeated-counter" and not held
        if hold and when == "before":
            held.append(kind)
            time.sleep(0.2)
        sent = probe(self, kind, dipole_am2)
        if hold and when == "after":
            held.append(kind)
            time.sleep(0.2)
        return sent

    monkeypatch.setattr(FlightSide, "probe", probe_with_hold_up)
    verdict = run_board_check(board_scenario(None), f"held-probe-{when}", tmp_path / "check", _board_command(), None,
                              None, None)
    assert held
    assert verdict.passed, verdict.text("board")
    measured = json.loads((tmp_path / "check" / "contract_check.json").read_text())["measured"]
    refused = next(r for r in measured["refusals"] if r["probe"] == "repeated-counter")
    for attempt in refused.get("repeated_attempts", []):
        assert attempt["held_up"].startswith("the check sent no command for 2"), attempt
    if when == "after":      # the board went to its safe state after the probe: it looked accepted
        assert len(refused["repeated_attempts"]) == 1
        assert refused["repeated_attempts"][0]["problems"][0].startswith(
            "repeated alive counter (the last command's counter again, otherwise valid): not refused")
    else:                    # its timeout EMCY came before the probe: outside the probe's window
        timeouts = [g for g in measured["held_up_by_host"] if g["gap"] == "command"]
        assert timeouts and all(g["gap_s"] >= 0.098 for g in timeouts), measured["held_up_by_host"]
        assert "a command timeout EMCY after" in verdict.summary
