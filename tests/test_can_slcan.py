"""A hardware path proved without hardware: the attitude detumble with the flight-side driver on
python-can's `slcan` interface (an interface the bench does not implement), its tty one end of a
pseudo-terminal, and an SLCAN adapter emulated on the other end (tests/slcan_adapter.py) that puts
the frames on the bench's flight channel (the portable Zenoh transport), where the bus model and
the board are. Lock-step: the trajectory equals the in-process loop to 1e-9, as the portable
transport's run does (tests/test_attitude_processes.py), so the two runs equal each other."""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
import tty
from importlib import resources

import can
import numpy as np
import pytest

from bench.bus.session import SessionOptions, free_loopback_port, loopback_endpoint, open_session
from bench.report.rundata import load_run
from bench.sim import simulate_attitude_in_process
from conftest import REPO
from slcan_adapter import SlcanAdapter, format_frame, parse_frame

STEPS = 60
RUN_TIMEOUT_S = 600

pytestmark = pytest.mark.timeout(RUN_TIMEOUT_S + 60)


@pytest.mark.parametrize("msg", [
    can.Message(arbitration_id=0x210, data=bytes(range(8)), is_extended_id=False),
    can.Message(arbitration_id=0x310, data=bytes(range(20)), is_extended_id=False, is_fd=True),
    can.Message(arbitration_id=0x1ABCDE0, data=b"\x01\x02", is_extended_id=True),
    can.Message(arbitration_id=0x123, data=bytes(64), is_extended_id=True, is_fd=True, bitrate_switch=True),
])
def test_adapter_frames_round_trip_and_match_python_can_slcan(msg):
    line = format_frame(msg)
    back = parse_frame(line[:-1].decode())
    assert back.equals(msg, timestamp_delta=None)
    # python-can's host side reads what the adapter writes: one end of a pty each.
    master, slave = os.openpty()
    tty.setraw(slave)
    bus = can.Bus(interface="slcan", channel=os.ttyname(slave), sleep_after_open=0, ignore_config=True)
    try:
        os.read(master, 100)          # the host's "O" (open)
        os.write(master, line)
        got = bus.recv(2.0)
        assert got is not None and got.equals(msg, timestamp_delta=None, check_channel=False)
        bus.send(msg)
        sent = b""
        while not sent.endswith(b"\r"):
            sent += os.read(master, 200)
        assert parse_frame(sent[:-1].decode()).equals(msg, timestamp_delta=None)
    finally:
        bus.shutdown()
        os.close(slave)
        os.close(master)


def wait_listening(port: int, process: subprocess.Popen, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise AssertionError(f"bench run exited with {process.returncode} before its hub listened")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    raise AssertionError(f"the hub did not listen on {port} within {timeout_s} s")


@pytest.fixture(scope="module")
def slcan_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("slcan")
    master, slave = os.openpty()
    tty.setraw(slave)     # no echo or line editing before the driver's pyserial sets its own modes
    adapter = SlcanAdapter(master)
    base = resources.files("bench.scenarios").joinpath("attitude_detumble.toml").read_text()
    scenario = tmp / "detumble_slcan.toml"
    scenario.write_text(base + f'\n[can.driver_bus]\ninterface = "slcan"\nchannel = "{os.ttyname(slave)}"\n'
                               'bitrate = 1000000\noptions = { sleep_after_open = 0, tty_baudrate = 115200 }\n')
    port, run_id, runs = free_loopback_port(), "slcan", tmp / "runs"
    process = subprocess.Popen(
        [sys.executable, "-m", "bench.cli", "run", str(scenario), "--run-id", run_id, "--runs-dir", str(runs),
         "--port", str(port), "--steps", str(STEPS), "--no-progress", "--no-report"],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    session = bus = None
    try:
        wait_listening(port, process)
        session = open_session(SessionOptions(connect=(loopback_endpoint(port),)))
        bus = can.Bus(interface="zenoh", channel="flight", run_id=run_id, session=session, fd=True, ignore_config=True)
        adapter.attach(bus)
        out, err = process.communicate(timeout=RUN_TIMEOUT_S)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
        adapter.stop()
        if bus is not None:
            bus.shutdown()
        if session is not None:
            session.close()
        os.close(slave)
        os.close(master)
    assert process.returncode == 0, err + out
    return load_run(runs / run_id), adapter


def test_detumble_through_slcan_on_a_pty_equals_the_in_process_loop(slcan_run):
    run, _ = slcan_run
    reference = simulate_attitude_in_process(run.scenario)
    assert run.trajectory["att_q_wxyz"].shape == (STEPS, 4)
    for name in ("att_q_wxyz", "att_omega_radps", "att_dipole_applied_am2", "att_dipole_commanded_am2"):
        np.testing.assert_allclose(run.trajectory[name], reference[name], rtol=0, atol=1e-9, err_msg=name)
    # The loop closed through the board: every step's command came back with the board's stamps.
    assert np.all(run.trajectory["stamp_board_received_ns"] > 0)
    assert np.abs(run.trajectory["att_dipole_applied_am2"]).max() > 0


def test_every_command_crossed_the_pty(slcan_run):
    run, adapter = slcan_run
    assert run.scenario.can.bus_spec("driver").interface == "slcan"
    board = json.loads((run.run_dir / "can" / "board.json").read_text())
    # The driver's only bus is the tty: what the board accepted came through the adapter.
    assert board["accepted"] >= STEPS and adapter.to_bus >= board["accepted"]
    assert adapter.to_tty > 0 and not adapter.bad_lines
    # python-can's slcan sets the bitrate closed ("C", "S8": 1 Mbit/s), opens ("O", and once more
    # after its constructor), closes on shutdown: once for the launcher's check before anything
    # started, once for the driver.
    assert adapter.commands == ["C", "S8", "O", "O", "C"] * 2
