"""python-can's socketcan interface on a real kernel vcan. Runs inside user-mode Linux only.

The host's test_kernel_can_uml.py boots UML and runs this file there (tools/uml/init.sh has
loaded can, can-raw, can-gw, vcan and brought vcan0 and vcan1 up).
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import can
import pytest

from bench.bus.can.transport import default_transport, kernel_has_can, open_can_bus

TESTS = Path(__file__).resolve().parents[1]
PEER = TESTS / "can_peer.py"
RECV_S = 5.0
# A raw socket's receive buffer holds a few hundred frames; a reader that falls further behind
# loses frames, as on a real bus. Bursts here stay well inside it.
BURST_FRAMES = 100

pytestmark = pytest.mark.skipif(not kernel_has_can(), reason="runs inside user-mode Linux (tests/uml.py)")


def socketcan(channel: str = "vcan0", **kwargs) -> can.BusABC:
    return can.Bus(interface="socketcan", channel=channel, ignore_config=True, **kwargs)


def frames() -> list[can.Message]:
    return [
        can.Message(arbitration_id=0x100, data=b"\x01\x02\x03", is_extended_id=False),
        can.Message(arbitration_id=0x1ABCDEF0, data=bytes(range(8)), is_extended_id=True),
        can.Message(arbitration_id=0x200, data=b"", is_extended_id=False),
        can.Message(arbitration_id=0x300, dlc=4, is_remote_frame=True, is_extended_id=False),
    ]


def test_kernel_vcan_is_the_default_transport():
    assert default_transport() == "socketcan"


def test_frames_cross_processes_on_vcan0():
    sent = frames()
    with socketcan() as bus:
        peer = subprocess.Popen([sys.executable, str(PEER), "echo", str(len(sent)), "--interface", "socketcan",
                                 "--channel", "vcan0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert peer.stdout.readline().strip() == "ready"
        for msg in sent:
            bus.send(msg)
        # Our own frames do not come back (receive_own_messages is off): only the echoes.
        echoed = [bus.recv(RECV_S) for _ in sent]
        out, err = peer.communicate(timeout=RECV_S)
        assert peer.returncode == 0, out + err
    for original, back in zip(sent, echoed):
        assert back is not None
        assert back.arbitration_id == original.arbitration_id + 1
        assert back.is_extended_id == original.is_extended_id
        assert back.is_remote_frame == original.is_remote_frame
        assert back.dlc == original.dlc and bytes(back.data) == bytes(original.data)
        assert back.channel == "vcan0"


def test_frames_of_one_sender_arrive_in_order():
    with socketcan() as rx:
        peer = subprocess.Popen([sys.executable, str(PEER), "burst", str(BURST_FRAMES), "--interface", "socketcan",
                                 "--channel", "vcan0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        got = [rx.recv(RECV_S) for _ in range(BURST_FRAMES)]
        rx.send(can.Message(arbitration_id=0x7FF, is_extended_id=False))   # "done"
        out, err = peer.communicate(timeout=RECV_S)
        assert peer.returncode == 0, out + err
    assert [int.from_bytes(m.data, "little") for m in got if m is not None] == list(range(BURST_FRAMES))


def test_vcan0_and_vcan1_are_separate_buses():
    with socketcan("vcan0") as a, socketcan("vcan0") as b, socketcan("vcan1") as c:
        a.send(can.Message(arbitration_id=0x10, data=b"\x01", is_extended_id=False))
        assert b.recv(RECV_S).arbitration_id == 0x10
        assert c.recv(0.2) is None


def test_open_can_bus_socketcan_and_own_messages():
    with open_can_bus("socketcan", "vcan0", run_id="uml", receive_own_messages=True) as a, \
            open_can_bus("socketcan", "vcan0", run_id="uml") as b:
        a.send(can.Message(arbitration_id=0x20, data=b"\x02", is_extended_id=False))
        assert b.recv(RECV_S).arbitration_id == 0x20
        assert a.recv(RECV_S).arbitration_id == 0x20
        assert b.recv(0.2) is None


def test_bench_vcan_up_and_down():
    def bench(*args):
        # A hang bound: `bench` imports every command's module at start-up, which on UML's one
        # emulated CPU took over 30 s once the campaign and deployment commands were added.
        return subprocess.run([sys.executable, "-m", "bench.cli", "vcan", *args], capture_output=True, text=True,
                              timeout=120)

    created = bench("up", "vcan7")
    assert created.returncode == 0 and "vcan7: created" in created.stdout, created.stderr
    assert Path("/sys/class/net/vcan7").exists()
    again = bench("up", "vcan7")
    assert again.returncode == 0 and "vcan7: already exists" in again.stdout
    with socketcan("vcan7") as a, socketcan("vcan7") as b:
        a.send(can.Message(arbitration_id=0x30, is_extended_id=False))
        assert b.recv(RECV_S).arbitration_id == 0x30
    deleted = bench("down", "vcan7")
    assert deleted.returncode == 0 and "vcan7: deleted" in deleted.stdout
    assert not Path("/sys/class/net/vcan7").exists()
