"""The magnetorquer protocol: DBC frames, E2E profile-2 protection and the receive-side check."""
from __future__ import annotations

import itertools
import random

import can
import pytest

from bench.bus.can import protocol as p


@pytest.fixture
def proto():
    return p.Protocol()


def test_command_round_trip_through_the_dbc(proto):
    msg = proto.command([0.1234, -0.05, 0.0], counter=7)
    assert msg.arbitration_id == 0x210 and len(msg.data) == 8
    frame = proto.decode(msg)
    assert frame.name == p.CMD and frame.counter == 7 and frame.crc_ok
    assert frame.signals["DipoleX"] == pytest.approx(0.1234)
    assert frame.signals["DipoleY"] == pytest.approx(-0.05)
    assert frame.signals["Mode"] == p.MODE_DIPOLE


def test_dipole_beyond_the_dbc_range_saturates_instead_of_wrapping(proto):
    frame = proto.decode(proto.command([10.0, -10.0, 0.0], counter=0))
    assert frame.signals["DipoleX"] == pytest.approx(3.2767)
    assert frame.signals["DipoleY"] == pytest.approx(-3.2768)


def test_the_set_point_echo_is_a_protected_tpdo3_in_the_commands_units(proto):
    from bench.bus.can.config import SETPOINT_ECHO_MAX_AM2

    msg = proto.encode(p.TLM_SETPOINT, {"SetpointX": 0.1234, "SetpointY": -1.6384, "SetpointZ": 0.2, "CommandCounter": 9,
                                        "CommandApplied": 1, "ActuationPaused": 1}, counter=4)
    assert msg.arbitration_id == 0x390 and len(msg.data) == 8 and not msg.is_fd     # classic CAN: both profiles
    frame = proto.decode(msg)
    assert frame.name == p.TLM_SETPOINT and frame.crc_ok and frame.counter == 4
    assert (frame.signals["CommandCounter"], frame.signals["CommandApplied"], frame.signals["ActuationPaused"],
            frame.signals["SafeState"]) == (9, 1, 1, 0)
    # The command's 1e-4 A m^2 step: a commanded value comes back as the same integer count.
    command = proto.decode(proto.command([0.1234, -1.6384, 0.2], counter=0))
    for axis in p.AXES:
        assert round(frame.signals[f"Setpoint{axis}"] / 1e-4) == round(command.signals[f"Dipole{axis}"] / 1e-4)
    # 15 bits: beyond the range the config allows an echoing board it saturates, never wraps.
    assert proto.decode(proto.encode(p.TLM_SETPOINT, {"SetpointX": 3.0}, counter=0)).signals["SetpointX"] == \
        pytest.approx(SETPOINT_ECHO_MAX_AM2)
    # Its own data ids: the same bytes are no other protected frame (and the reverse).
    for other in (p.CMD, p.TLM_DIPOLE, p.TLM_COIL):
        assert not p.e2e_crc_ok(bytes(msg.data), proto.data_ids[other]), other
    # Counted by name by the driver and the bus model (frame_kind), not as an unknown identifier.
    assert p.TLM_SETPOINT in p.BOARD_FRAMES and p.frame_kind(proto, msg) == p.TLM_SETPOINT and not proto.bad.total


def _flip(data: bytes, bits) -> bytes:
    corrupted = bytearray(data)
    for bit in bits:
        corrupted[bit // 8] ^= 1 << (bit % 8)
    return bytes(corrupted)


def test_one_to_three_flipped_bits_outside_the_counter_always_fail_the_crc(proto):
    data = bytes(proto.command([0.1, 0.2, -0.1], counter=3).data)
    bits = [b for b in range(64) if b not in p.COUNTER_BITS]
    rng = random.Random(5)
    flips = [(b,) for b in range(64)] + list(itertools.combinations(bits, 2)) \
        + rng.sample(list(itertools.combinations(bits, 3)), 3000)
    for flip in flips:
        frame = proto.decode(can.Message(arbitration_id=0x210, is_extended_id=False, data=_flip(data, flip)))
        assert not frame.crc_ok, f"flip {flip} passed the CRC"


def test_flips_in_the_counter_can_pass_because_the_counter_picks_the_data_id(proto):
    # Profile 2's weakness, kept visible: a counter bit and a data bit flipped together select
    # another data id whose CRC may match. The fault injector therefore corrupts data bits only.
    data = bytes(proto.command([0.1, 0.2, -0.1], counter=3).data)
    passed = [f for f in itertools.combinations(range(64), 2)
              if set(f) & set(p.COUNTER_BITS) and p.e2e_crc_ok(_flip(data, f), proto.data_ids[p.CMD])]
    assert passed, "no double flip through the counter passes: the weakness this test documents is gone"


def test_a_frame_protected_with_a_foreign_data_id_fails_for_every_counter(proto):
    for counter in range(16):
        genuine = proto.command([0.1, 0.0, 0.0], counter=counter)
        forged = proto.reprotect(genuine, data_ids=(0x00,) * 16)
        assert not proto.decode(forged).crc_ok


def test_receiver_tells_repeated_lost_and_out_of_sequence_apart():
    # E2E_P02Check by hand: every call widens MaxDeltaCounter by one (init 1), an accepted frame
    # narrows it back; a wrong sequence re-synchronises after sync_counter (here 0) valid frames.
    rx = p.E2EReceiver(max_delta_counter=1, sync_counter=0)
    statuses = [rx.check(c, True) for c in (5, 6, 6, 8, 12, 13)] + [rx.check(14, False)]
    # 6 again: REPEATED (max delta now 2); 8: delta 2 <= 3, OK_SOME_LOST; 12: delta 4 > 2, WRONG_SEQUENCE
    # and, with sync_counter 0, no re-sync: 13 is delta 5 from 8 > 3, WRONG_SEQUENCE again.
    assert statuses == [p.E2EStatus.INITIAL, p.E2EStatus.OK, p.E2EStatus.REPEATED, p.E2EStatus.OK_SOME_LOST,
                        p.E2EStatus.WRONG_SEQUENCE, p.E2EStatus.WRONG_SEQUENCE, p.E2EStatus.WRONG_CRC]
    rx = p.E2EReceiver(max_delta_counter=1)
    assert [rx.check(c, True) for c in (14, 15, 0, 1)] == [p.E2EStatus.INITIAL] + [p.E2EStatus.OK] * 3  # wraps at 16


def test_bad_frames_are_counted_by_reason_never_raised(proto):
    bad = [
        can.Message(arbitration_id=0x210, is_extended_id=False, data=b"\x01\x02"),      # wrong length
        can.Message(arbitration_id=0x123, is_extended_id=False, data=bytes(8)),         # unknown id
        can.Message(arbitration_id=0x210, is_extended_id=True, data=bytes(8)),          # extended id
        can.Message(arbitration_id=0x710, is_extended_id=False, data=b"\x42"),          # no NMT state
        can.Message(arbitration_id=0x4, is_error_frame=True, is_extended_id=False, data=bytes(8)),
        can.Message(arbitration_id=0x210, is_extended_id=False, is_remote_frame=True, dlc=8),   # RTR
        can.Message(arbitration_id=0x210, is_extended_id=False, is_fd=True, data=bytes(8)),     # FD, classic id
    ]
    assert [proto.decode(m) for m in bad] == [None] * 7
    assert proto.bad.counts == {"wrong_length": 1, "unknown_id": 2, "garbage": 1, "error_frame": 1,
                                "remote_request": 1, "wrong_format": 1}


def test_node_id_moves_every_identifier_like_canopen():
    proto = p.Protocol(node_id=0x22)
    assert proto.frame_ids == {p.CMD: 0x222, p.CMD_AUTH: 0x322, p.TLM_DIPOLE: 0x1A2, p.TLM_COIL: 0x2A2,
                               p.TLM_SETPOINT: 0x3A2,
                               p.HEARTBEAT: 0x722, p.EMCY: 0xA2, p.NMT: 0x000,   # NMT: 0 for every node
                               p.NMT_AUTH: 0x422}
    assert proto.decode(proto.command([0, 0, 0], counter=1)).crc_ok
    with pytest.raises(ValueError):
        p.Protocol(node_id=0x80)
