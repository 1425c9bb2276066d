"""can-utils against the board on a kernel vcan: frames built from the DBC, sent with `cansend`
and `canplayer`, are applied, rejected or ignored exactly as the protocol says.

Runs inside user-mode Linux (tests/test_can_utils_uml.py boots it). The board runs here on vcan0
(CAN FD capable: mtu 72); the frames come from the can-utils processes, as an avionics test
engineer would send them. The board's command timeout is set long (30 s) so that the slow start
of a can-utils process in UML cannot reset its E2E state between two frames; the E2E receiver
still widens its tolerated counter jump every command period without a command (AUTOSAR P02), so
the cases below are chosen to be decided whatever the gaps: repeated (delta 0), wrong CRC, wrong
length, remote frame, extended identifier, NMT state, and on the secoc profile MAC and freshness.
"""
from __future__ import annotations

import shutil
import subprocess
import threading
import time
from pathlib import Path

import can
import pytest

from bench.bus.can import protocol as p
from bench.bus.can import secoc
from bench.bus.can.board import MagnetorquerBoard
from bench.bus.can.config import BENCH_KEY_HEX, BoardConfig, SecurityConfig
from bench.bus.can.transport import kernel_has_can

pytestmark = pytest.mark.skipif(not (kernel_has_can() and shutil.which("cansend")),
                                reason="runs inside user-mode Linux with can-utils (tests/test_can_utils_uml.py)")
CHANNEL = "vcan0"
KEY = bytes.fromhex(BENCH_KEY_HEX)
WAIT_S = 10.0
FRESHNESS_MARGIN_S = 0.5      # stated for this test: a can-utils process starts slowly in UML


def cansend_text(msg: can.Message) -> str:
    """The frame as cansend and canplayer write it: 123#data, 123#R, 12345678#data, 123##<flags>data."""
    frame_id = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
    if msg.is_remote_frame:
        return f"{frame_id}#R"
    if msg.is_fd:
        return f"{frame_id}##0{bytes(msg.data).hex().upper()}"
    return f"{frame_id}#{bytes(msg.data).hex().upper()}"


def cansend(*frames: can.Message) -> None:
    for msg in frames:
        subprocess.run(["cansend", CHANNEL, cansend_text(msg)], check=True, timeout=30)


def canplayer(path: Path, frames: list[can.Message], period_s: float = 0.02) -> None:
    """Write a candump log, one frame per period, and play it with its timing."""
    path.write_text("".join(f"({k * period_s:.6f}) {CHANNEL} {cansend_text(m)}\n" for k, m in enumerate(frames)))
    subprocess.run(["canplayer", "-I", str(path)], check=True, timeout=60)


class BoardOnVcan:
    def __init__(self, profile: str):
        self.bus = can.Bus(interface="socketcan", channel=CHANNEL, fd=True, ignore_config=True)
        security = SecurityConfig(profile=profile, freshness_margin_s=FRESHNESS_MARGIN_S)
        self.board = MagnetorquerBoard(self.bus, BoardConfig(command_timeout_s=30.0),
                                       p.Protocol(profile=profile, key=KEY if profile == "secoc" else None),
                                       security=security)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.board.run, args=(self.stop,), daemon=True)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join(5)
        self.bus.shutdown()

    def wait(self, what, predicate) -> None:
        deadline = time.monotonic() + WAIT_S
        while not predicate(self.board):
            assert time.monotonic() < deadline, f"{what}: accepted {self.board.accepted}, rejected " \
                f"{dict(self.board.rejected)}, ignored {dict(self.board.ignored)}, bad {dict(self.board.protocol.bad.counts)}"
            time.sleep(0.01)
        time.sleep(0.1)   # and nothing more arrives after it


def nmt(command: int, node_id: int = p.DBC_NODE_ID) -> can.Message:
    return p.Protocol().encode(p.NMT, {"Command": command, "NodeId": node_id})


def test_cansend_and_canplayer_on_the_e2e_profile(tmp_path):
    proto = p.Protocol()
    commands = [proto.command([0.01 * k, 0.0, -0.01 * k], counter=k) for k in range(10)]
    with BoardOnVcan("e2e") as rig:
        board = rig.board
        cansend(commands[0])                              # pre-operational: not processed
        rig.wait("ignored before start", lambda b: sum(b.ignored.values()) == 1)
        assert board.accepted == 0 and board.nmt_state == p.NMT_PRE_OPERATIONAL
        cansend(nmt(p.NMT_START, node_id=0x11))           # another node's start
        cansend(nmt(p.NMT_START))
        rig.wait("started", lambda b: b.nmt_state == p.NMT_OPERATIONAL)
        canplayer(tmp_path / "commands.log", commands)    # ten in sequence, 20 ms apart
        rig.wait("ten applied", lambda b: b.accepted == 10)
        assert board.rejected == {} and board.state.last_command_counter == 9
        cansend(commands[9])                              # the same frame again
        rig.wait("repeated", lambda b: b.rejected["REPEATED"] == 1)
        bad_crc = bytearray(proto.command([0.2, 0.2, 0.2], counter=10).data)
        bad_crc[0] ^= 0x01
        cansend(can.Message(arbitration_id=0x210, is_extended_id=False, data=bytes(bad_crc)))
        rig.wait("wrong CRC", lambda b: b.rejected["WRONG_CRC"] == 1)
        cansend(can.Message(arbitration_id=0x210, is_extended_id=False, data=b"\x01\x02"))
        rig.wait("wrong length", lambda b: b.rejected["wrong_length"] == 1)
        cansend(can.Message(arbitration_id=0x210, is_extended_id=False, is_remote_frame=True, dlc=8),
                can.Message(arbitration_id=0x210, is_extended_id=True, data=bytes(commands[0].data)))
        rig.wait("remote and extended", lambda b: b.protocol.bad.counts["remote_request"] == 1
                 and b.protocol.bad.counts["unknown_id"] == 1)
        assert board.accepted == 10 and dict(board.rejected) == {"REPEATED": 1, "WRONG_CRC": 1, "wrong_length": 1}
        cansend(nmt(p.NMT_STOP), proto.command([0.1, 0.1, 0.1], counter=10))
        rig.wait("stopped", lambda b: any(k.endswith("while stopped") for k in b.ignored))
        assert board.nmt_state == p.NMT_STOPPED and board.accepted == 10 and board.state.safe_state


def test_cansend_and_canplayer_on_the_secoc_profile(tmp_path):
    proto = p.Protocol(profile="secoc", key=KEY)
    with BoardOnVcan("secoc") as rig:
        board = rig.board
        cansend(nmt(p.NMT_START))
        rig.wait("started", lambda b: b.nmt_state == p.NMT_OPERATIONAL)
        # Fresh authenticated commands: freshness values on this clock, one command period apart.
        now_s = time.monotonic()
        fresh = [proto.command([0.02, 0.0, 0.0], counter=k, sent_s=now_s + 0.02 * k) for k in range(5)]
        canplayer(tmp_path / "fresh.log", fresh)
        rig.wait("five applied", lambda b: b.accepted == 5)
        assert board.rejected == {}
        # The same log a second later: every frame older than a period plus the margin.
        time.sleep(2 * FRESHNESS_MARGIN_S)
        canplayer(tmp_path / "replay.log", fresh)
        rig.wait("replays stale", lambda b: b.rejected["STALE"] == 5)
        # A plain MTQ_CMD, and one with a MAC under another key (all else right).
        cansend(p.Protocol().command([0.2, 0.2, 0.2], counter=5))
        forged = p.Protocol(profile="secoc", key=bytes(16)).command([0.2, 0.2, 0.2], counter=5,
                                                                     sent_s=time.monotonic())
        cansend(forged)
        rig.wait("unauthenticated and forged", lambda b: b.rejected["NOT_AUTHENTICATED"] == 1
                 and b.rejected["WRONG_MAC"] == 1)
        assert board.accepted == 5 and dict(board.rejected) == {"STALE": 5, "NOT_AUTHENTICATED": 1, "WRONG_MAC": 1}
        assert board.last_command_age_s is not None and board.last_command_age_s <= 0.02 + FRESHNESS_MARGIN_S


def test_the_frames_sent_are_the_dbc_frames_decoded_by_cantools():
    # The text cansend gets round-trips through python-can's parser of the same notation.
    import cantools
    db = cantools.database.load_file(str(p.DBC_PATH))
    msg = p.Protocol(profile="secoc", key=KEY).command([0.1, -0.1, 0.05], counter=3, sent_s=1.0)
    text = cansend_text(msg)
    assert text.startswith("310##0") and len(text) == len("310##0") + 40
    decoded = db.decode_message(0x310, bytes.fromhex(text.split("##")[1][1:]))
    assert decoded["AliveCounter"] == 3 and decoded["DipoleY"] == pytest.approx(-0.1)
    assert decoded["Freshness"] == secoc.freshness_ticks(1.0) % 2**32
