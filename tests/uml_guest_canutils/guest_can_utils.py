"""can-utils against the board on a kernel vcan: frames built from the DBC, sent with `cansend`
and `canplayer`, are applied, rejected or ignored exactly as the protocol says.

Runs inside user-mode Linux (tests/test_kernel_can_uml.py boots it). The board runs here on vcan0
(CAN FD capable: mtu 72); the frames come from the can-utils processes, as an avionics test
engineer would send them. The board's command timeout is set long (30 s) so that the slow start
of a can-utils process in UML cannot reset its E2E state between two frames; the E2E receiver
still widens its tolerated counter jump every command period without a command (AUTOSAR P02), so
the cases below are chosen to be decided whatever the gaps: repeated (delta 0), wrong CRC, wrong
length, remote frame, extended identifier, NMT state, and on the secoc profile MAC and freshness.
Error frames sent with `cansend`/`canplayer` reach the flight-side driver on the same vcan (python-can
sets CAN_RAW_ERR_FILTER), which must come back to error-active from each, as ISO 11898 says.
"""
from __future__ import annotations

import shutil
import subprocess
import threading
import time
from collections import Counter
from pathlib import Path

import can
import pytest

from bench.bus.can import errors
from bench.bus.can import protocol as p
from bench.bus.can import secoc
from bench.bus.can.board import MagnetorquerBoard
from bench.bus.can.config import BoardConfig, DriverConfig, SecurityConfig
from bench.bus.can.driver import CommandLoop, MagnetorquerDriver
from bench.bus.can.transport import kernel_has_can

pytestmark = pytest.mark.skipif(not (kernel_has_can() and shutil.which("cansend")),
                                reason="runs inside user-mode Linux with can-utils (tests/test_kernel_can_uml.py)")
CHANNEL = "vcan0"
KEY = bytes(range(16))   # a test key: the bench has no built-in one
WAIT_S = 10.0
FRESHNESS_MARGIN_S = 2.0      # stated for this test: a can-utils process starts slowly in UML (over 0.5 s seen)


CAN_ERR_FLAG = 0x20000000       # linux/can.h: in the identifier of an error frame
BOARD_CONFIG = BoardConfig(command_timeout_s=30.0)
BUS_STATE_KINDS = {"error_warning", "error_passive", "bus_off", "bus_restarted", "error_active"}


def cansend_text(msg: can.Message) -> str:
    """The frame as cansend and canplayer write it: 123#data, 123#R, 12345678#data, 123##<flags>data;
    an error frame as 8 digits with CAN_ERR_FLAG (cansend sends it as an error frame, not extended)."""
    if msg.is_error_frame:
        return f"{CAN_ERR_FLAG | msg.arbitration_id:08X}#{bytes(msg.data).hex().upper()}"
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


class _OnVcan:
    """A node on its own bus and thread; `run(stop)` is its loop, started and stopped with `with`."""

    def __init__(self, run):
        self.stop = threading.Event()
        self.thread = threading.Thread(target=run, args=(self.stop,), daemon=True)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join(5)
        self.bus.shutdown()


class BoardOnVcan(_OnVcan):
    def __init__(self, profile: str):
        self.bus = can.Bus(interface="socketcan", channel=CHANNEL, fd=True, ignore_config=True)
        security = SecurityConfig(profile=profile, freshness_margin_s=FRESHNESS_MARGIN_S)
        self.board = MagnetorquerBoard(self.bus, BOARD_CONFIG,
                                       p.Protocol(profile=profile, key=KEY if profile == "secoc" else None),
                                       security=security)
        super().__init__(self.board.run)

    def wait(self, what, predicate) -> None:
        deadline = time.monotonic() + WAIT_S
        while not predicate(self.board):
            assert time.monotonic() < deadline, f"{what}: accepted {self.board.accepted}, rejected " \
                f"{dict(self.board.rejected)}, ignored {dict(self.board.ignored)}, bad {dict(self.board.protocol.bad.counts)}"
            time.sleep(0.01)
        time.sleep(0.1)   # and nothing more arrives after it


class DriverOnVcan(_OnVcan):
    """The flight-side driver on the same vcan, commanding every period on its own thread."""

    def __init__(self):
        self.bus = can.Bus(interface="socketcan", channel=CHANNEL, fd=True, ignore_config=True)
        self.driver = MagnetorquerDriver(self.bus, DriverConfig(), BOARD_CONFIG, p.Protocol())
        self.events = []
        self.loop = CommandLoop(self.driver, DriverConfig().command_period_s, on_events=self.events.extend)
        self.loop.set_dipole([0.05, -0.05, 0.02])
        super().__init__(self.loop.run)

    def bus_states(self) -> list[str]:
        return [e.kind for e in list(self.events) if e.kind in BUS_STATE_KINDS]

    def wait(self, what, predicate) -> None:
        deadline = time.monotonic() + WAIT_S
        while not predicate(self):
            assert time.monotonic() < deadline, f"{what}: bus states {self.bus_states()}, health {self.loop.health}"
            time.sleep(0.01)


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


def send_stamped(rig: BoardOnVcan, stamp, send, what: str, done, stale_key: str, tries: int = 3) -> Counter:
    """Send frames stamped with the time now (`stamp(now_s)` builds them) until `done(board)`.

    Under load a can-utils process in UML can take longer to start than the freshness margin
    (over 2 s seen); a frame that reaches the board that late must be rejected as stale, and the
    board is right to. So: where the send took longer than the margin, stale rejections are
    expected, and the frames are stamped and sent again; where it took less, they must be
    accepted. Returns the stale rejections expected from the late sends."""
    board = rig.board
    late = Counter()
    for _ in range(tries):
        stamped_s = time.monotonic()
        frames = stamp(stamped_s)
        stale_before = board.rejected[stale_key]
        send(frames)
        send_s = time.monotonic() - stamped_s
        if send_s <= FRESHNESS_MARGIN_S:
            rig.wait(what, done)
            return late
        # Late: wait for the board to decide every frame, then check that it refused the late ones.
        rig.wait(f"{what} (sent {send_s:.1f} s after its stamp)",
                 lambda b: done(b) or b.rejected[stale_key] > stale_before)
        late[stale_key] += board.rejected[stale_key] - stale_before
        if done(board):
            return late
    pytest.fail(f"{what}: every one of {tries} sends took longer than the {FRESHNESS_MARGIN_S} s margin")


def test_cansend_and_canplayer_on_the_secoc_profile(tmp_path):
    proto = p.Protocol(profile="secoc", key=KEY)
    with BoardOnVcan("secoc") as rig:
        board = rig.board
        # On secoc the board obeys only the authenticated NMT frame: a plain "start" is refused.
        cansend(nmt(p.NMT_START))
        rig.wait("plain NMT refused", lambda b: b.rejected["NMT_NOT_AUTHENTICATED"] == 1)
        assert board.nmt_state != p.NMT_OPERATIONAL
        stale = send_stamped(rig, lambda now_s: [proto.nmt(p.NMT_START, sent_s=now_s)], lambda frames: cansend(*frames),
                             "started", lambda b: b.nmt_state == p.NMT_OPERATIONAL, stale_key="NMT_STALE")
        # Fresh authenticated commands: freshness values on this clock, one command period apart.
        fresh: list[can.Message] = []
        batch_from = 0        # board.accepted before the last batch: a late one may be partly accepted

        def five_fresh(now_s: float) -> list[can.Message]:
            nonlocal fresh, batch_from
            batch_from = board.accepted      # counters go on after a batch that came too late
            fresh = [proto.command([0.02, 0.0, 0.0], counter=batch_from + k, sent_s=now_s + 0.02 * k) for k in range(5)]
            return fresh
        stale += send_stamped(rig, five_fresh, lambda frames: canplayer(tmp_path / "fresh.log", frames),
                              "five applied", lambda b: b.accepted == batch_from + 5, stale_key="STALE")
        expected = Counter({"NMT_NOT_AUTHENTICATED": 1, **stale})
        assert board.rejected == expected
        # The same log a second later: every frame older than a period plus the margin.
        time.sleep(2 * FRESHNESS_MARGIN_S)
        canplayer(tmp_path / "replay.log", fresh)
        rig.wait("replays stale", lambda b: b.rejected["STALE"] == expected["STALE"] + 5)
        # A plain MTQ_CMD, and one with a MAC under another key (all else right).
        cansend(p.Protocol().command([0.2, 0.2, 0.2], counter=5))
        forged = p.Protocol(profile="secoc", key=bytes(16)).command([0.2, 0.2, 0.2], counter=5,
                                                                     sent_s=time.monotonic())
        cansend(forged)
        rig.wait("unauthenticated and forged", lambda b: b.rejected["NOT_AUTHENTICATED"] == 1
                 and b.rejected["WRONG_MAC"] == 1)
        expected.update({"STALE": 5, "NOT_AUTHENTICATED": 1, "WRONG_MAC": 1})
        assert board.accepted == batch_from + 5 and board.rejected == expected
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


def test_error_frames_from_cansend_leave_the_driver_error_active_again(tmp_path):
    # Issue 13: one error frame from `cansend` left the driver bus_off forever (on the virtual bus
    # that is tests/test_can_health.py; here the kernel carries the error frames).
    with BoardOnVcan("e2e") as rig, DriverOnVcan() as flight:
        flight.wait("board started and healthy", lambda f: f.loop.health.ok)   # the driver is its NMT master
        assert flight.bus_states() == []
        # One bare bus-off error frame, as typed at a terminal. Nothing reports a restart: the
        # driver is back when it hears the board after the ISO 11898 recovery time (128 x 11 bits).
        cansend_raw(f"{CAN_ERR_FLAG | errors.CAN_ERR_BUSOFF:08X}#")
        flight.wait("bus-off and back", lambda f: f.bus_states() == ["bus_off", "error_active"] and f.loop.health.ok)
        assert flight.loop.health.bus_state == "error_active"
        # Error-passive by the counters, then the controller's own error-active report.
        cansend(errors.error_frame(errors.ErrorState.PASSIVE, 130))
        flight.wait("error-passive", lambda f: f.bus_states()[2:] == ["error_passive"])
        assert flight.loop.health.bus_state == "error_passive"
        cansend(errors.error_frame(errors.ErrorState.ACTIVE, 90))
        flight.wait("error-active reported", lambda f: f.bus_states()[2:] == ["error_passive", "error_active"])
        # A few in a burst (bus-off with bit errors, 1 ms apart): error-active and healthy after it.
        accepted = rig.board.accepted
        burst = [errors.error_frame(errors.ErrorState.BUS_OFF, 256)] * 5
        canplayer(tmp_path / "error_frames.log", burst, period_s=0.001)
        flight.wait("after the burst", lambda f: "bus_off" in f.bus_states()[4:] and f.bus_states()[-1] == "error_active"
                    and f.loop.health.ok)
        assert flight.driver.received["error_frame"] == 1 + 2 + 5
        # The board went on applying commands throughout; error frames are not commands to it.
        rig.wait("commands applied after", lambda b: b.accepted > accepted + 10)
        assert rig.board.rejected == {} and not rig.board.state.safe_state


def cansend_raw(text: str) -> None:
    subprocess.run(["cansend", CHANNEL, text], check=True, timeout=30)
