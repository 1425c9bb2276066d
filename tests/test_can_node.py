"""The board as a CANopen node (CiA 301): emergency codes, EMCY inhibit time, remote frames."""
from __future__ import annotations

import can

from bench.bus.can import protocol as p
from test_can_board_driver import Rig


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
