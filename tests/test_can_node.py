"""The board as a CANopen node (CiA 301): emergency codes, EMCY inhibit time, remote frames."""
from __future__ import annotations

import can

from bench.bus.can import protocol as p
from bench.bus.can.board import MagnetorquerBoard
from bench.bus.can.config import BoardConfig, DriverConfig
from bench.bus.can.driver import MagnetorquerDriver
from test_can_board_driver import Clock, Rig


def test_a_burst_of_bad_frames_is_reported_by_few_emergencies_and_the_commands_still_apply():
    rig = Rig()
    try:
        rig.run(0.2)
        emcy_before = rig.board.sent[p.EMCY]
        accepted_before, sent_before = rig.board.accepted, rig.driver.sent_frames
        bad = bytearray(p.Protocol().command((0.2, 0.2, 0.2), counter=0).data)
        bad[0] ^= 0xFF                                   # wrong CRC
        for _ in range(30):                              # 300 bad frames over 30 ms
            for _ in range(10):
                rig.rogue_bus.send(can.Message(arbitration_id=0x210, is_extended_id=False, data=bad))
            rig.run(0.001)
        rig.run(0.1)
        inhibit_s = rig.board_config.emcy_inhibit_s
        assert rig.board.rejected["WRONG_CRC"] == 300
        # One at the first bad frame, then at most one per inhibit time while they last.
        assert 2 <= rig.board.sent[p.EMCY] - emcy_before <= 1 + round(0.03 / inhibit_s) + 1
        assert not rig.board.state.safe_state
        assert rig.board.accepted - accepted_before == rig.driver.sent_frames - sent_before   # every genuine one
    finally:
        rig.close()


def test_command_timeout_is_reported_with_the_rpdo_timeout_code():
    rig = Rig()
    try:
        rig.run(0.2)
        emergencies = []
        rig.run(0.3, commanding=False)
        while (msg := rig.rogue_bus.recv(timeout=0)) is not None:   # a third node hears everything
            if msg.arbitration_id == 0x090:
                emergencies.append(p.Protocol().decode(msg).signals["ErrorCode"])
        assert p.EMCY_COMMAND_TIMEOUT == 0x8250 and 0x8250 in emergencies and 0x8130 not in emergencies
        assert rig.kinds().count("board_command_timeout") == 1
    finally:
        rig.close()


def test_a_remote_frame_on_the_command_identifier_is_not_a_length_error():
    rig = Rig()
    try:
        rig.run(0.1)
        rig.rogue_bus.send(can.Message(arbitration_id=0x210, is_extended_id=False, is_remote_frame=True, dlc=8))
        rig.run(0.05)
        assert rig.board.rejected == {}
        assert rig.board.protocol.bad.counts == {"remote_request": 1}
        assert "command_rejected" not in rig.kinds()
    finally:
        rig.close()


def _heard(bus: can.Bus, frame_id: int) -> list[bytes]:
    out = []
    while (msg := bus.recv(timeout=0)) is not None:
        if msg.arbitration_id == frame_id:
            out.append(bytes(msg.data))
    return out


def test_the_board_is_pre_operational_until_an_nmt_master_starts_it():
    # By hand, not with Rig: Rig boots the board with the driver's NMT auto-start.
    channel = "test-can-nmt-by-hand"
    clock = Clock()
    board_bus, driver_bus, sniffer = (can.Bus(interface="virtual", channel=channel) for _ in range(3))
    try:
        board = MagnetorquerBoard(board_bus, BoardConfig(), p.Protocol(), clock=clock)
        driver = MagnetorquerDriver(driver_bus, DriverConfig(nmt_auto_start=False), BoardConfig(), p.Protocol(), clock=clock)

        def run(seconds, command=True):
            for _ in range(round(seconds / 0.001)):
                if command and round(clock.t * 1000) % 20 == 0:
                    driver.command((0.1, 0.0, 0.0))
                board.step(clock.t)
                driver.poll()
                clock.t += 0.001

        run(0.35)
        heartbeats = _heard(sniffer, 0x710)
        assert heartbeats[0] == bytes([p.NMT_BOOT_UP]) and set(heartbeats[1:]) == {bytes([p.NMT_PRE_OPERATIONAL])}
        assert board.accepted == 0 and sum(board.ignored.values()) == driver.sent_frames
        assert board.sent[p.TLM_DIPOLE] == 0 and board.sent[p.EMCY] == 0
        assert not driver.health().ok and driver.health().nmt_state == p.NMT_PRE_OPERATIONAL
        driver.nmt(p.NMT_START)
        run(0.3)
        assert board.nmt_state == p.NMT_OPERATIONAL and board.accepted > 10 and board.sent[p.TLM_DIPOLE] > 0
        assert _heard(sniffer, 0x710)[-1] == bytes([p.NMT_OPERATIONAL]) and driver.health().ok
        # NMT to another node id is not for this board.
        sniffer.send(p.Protocol().encode(p.NMT, {"Command": p.NMT_STOP, "NodeId": 0x11}))
        run(0.05)
        assert board.nmt_state == p.NMT_OPERATIONAL
        # Stop: coils off, only heartbeats (state 4), commands ignored, no EMCY.
        _heard(sniffer, 0)
        driver.nmt(p.NMT_STOP)
        run(0.3)
        assert board.nmt_state == p.NMT_STOPPED and board.state.safe_state
        assert board.output_dipole_am2.tolist() == [0.0, 0.0, 0.0]
        frames = []
        while (msg := sniffer.recv(timeout=0)) is not None:
            frames.append(msg.arbitration_id)
        assert set(frames) - {0x210, 0x000} == {0x710}
        # Reset node: boot-up again, pre-operational; the driver hears a reboot.
        driver.nmt(p.NMT_RESET_NODE)
        run(0.05)
        assert board.nmt_state == p.NMT_PRE_OPERATIONAL
        assert "board_rebooted" in [e.kind for e in driver.events]
    finally:
        for bus in (board_bus, driver_bus, sniffer):
            bus.shutdown()


def test_commands_back_after_a_timeout_clear_the_error_with_an_error_reset_emergency():
    rig = Rig()
    try:
        rig.run(0.2)
        rig.run(0.2, commanding=False)
        rig.run(0.1)
        assert rig.kinds() == ["board_command_timeout", "board_error_reset"]
        assert not rig.board.state.safe_state
    finally:
        rig.close()
