"""The bus model at bit level: arbitration on the identifier's bits, collisions, any number of
nodes with ISO 11898-1 error counters, ACK errors, SocketCAN error-frame classes.

Expected values are worked by hand from ISO 11898-1 (the frame layout, fault confinement rules)
and linux/can/error.h, not computed with the code under test.
"""
from __future__ import annotations

import can
import pytest

from bench.bus.can import bittiming, errors
from bench.bus.can import protocol as p
from bench.bus.can.busmodel import BOARD, FLIGHT, BusModel
from bench.bus.can.faults import FaultSpec
from bench.bus.can.injector import FaultInjector

T0 = 10**12
MS = 1_000_000
PROTO = p.Protocol()


def model(*faults, nodes=(FLIGHT, BOARD)) -> BusModel:
    return BusModel(FaultInjector(list(faults), PROTO, seed=1), PROTO, T0, nodes=nodes)


def std(frame_id, data=b"\x00", remote=False):
    return can.Message(arbitration_id=frame_id, is_extended_id=False, is_remote_frame=remote,
                       data=None if remote else data, dlc=len(data))


def ext(frame_id, data=b"\x00"):
    return can.Message(arbitration_id=frame_id, is_extended_id=True, data=data)


# --- hand-worked arbitration fields --------------------------------------------------------------
def test_arbitration_fields_bit_by_bit():
    # 0x200 = 010 0000 0000; then RTR (0 data), IDE (0 standard).
    assert bittiming.arbitration_bits(0x200) == (0, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    # Extended 0x04000001: base 0x100 = 001 0000 0000, SRR 1, IDE 1, extension 00..01, RTR 0.
    assert bittiming.arbitration_bits(0x04000001, extended=True) == \
        (0, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0) + (1, 1) + (0,) * 17 + (1,) + (0,)
    # A remote frame: RTR recessive.
    assert bittiming.arbitration_bits(0x200, remote=True)[11] == 1


@pytest.mark.parametrize("first, second, bit", [
    # extended base 0x100 against standard 0x200: the extended frame sends 0 at bit 1, wins.
    (ext(0x100 << 18), std(0x200), 1),
    # standard 0x100 against extended base 0x100: equal 11 bits, then RTR 0 against SRR 1.
    (std(0x100), ext(0x100 << 18), 11),
    # a standard remote frame against extended base 0x100: RTR 1 = SRR 1, then IDE 0 against 1.
    (std(0x100, remote=True), ext(0x100 << 18), 12),
    # data against remote on the same identifier: RTR 0 against 1.
    (std(0x210, bytes(8)), std(0x210, remote=True), 11),
])
def test_the_frame_with_the_first_dominant_bit_wins_arbitration(first, second, bit):
    a, b = bittiming.message_arbitration_bits(first), bittiming.message_arbitration_bits(second)
    assert a[:bit] == b[:bit] and (a[bit], b[bit]) == (0, 1)
    for order in ((first, second), (second, first)):
        bus = model()
        bus.submit(FLIGHT, order[0], T0)
        bus.submit(BOARD, order[1], T0)
        delivered = [d.msg for d in bus.run_until(T0 + MS)]
        assert [(m.arbitration_id, m.is_extended_id, m.is_remote_frame) for m in delivered] == \
            [(m.arbitration_id, m.is_extended_id, m.is_remote_frame) for m in (first, second)]


def test_equal_identifiers_with_different_data_collide_in_a_bit_error():
    # 0x555 = 101 0101 0101: SOF 0 and the identifier alternate (no stuffing). Then RTR, IDE, r0
    # and DLC 0001: 0 0 0 0 0 -> stuff bit 1 after the fifth 0, then 0 1. Bits 0..19 are equal;
    # the first data bit (bit 20) is 0 in 0x00 and 1 in 0x80: a bit error there, then an error
    # frame of 23 bits. Both transmitters: TEC + 8. The frame is retried; the next attempts
    # collide the same way until one of them goes error-passive... so look at the first one.
    bus = model()
    bus.submit(FLIGHT, std(0x555, b"\x00"), T0)
    bus.submit(BOARD, std(0x555, b"\x80"), T0)
    deliveries = bus.run_until(T0 + (20 + 1 + 23) * 1000)
    assert {d.destinations for d in deliveries} == {(FLIGHT,), (BOARD,)}
    for d in deliveries:
        assert d.msg.is_error_frame and d.msg.timestamp == pytest.approx((T0 + 44_000) / 1e9)
        assert d.msg.arbitration_id & errors.CAN_ERR_PROT
        assert d.msg.data[2] == 0x01 | 0x80           # CAN_ERR_PROT_BIT | CAN_ERR_PROT_TX (0x02 is FORM)
        assert d.msg.data[6] == 8                     # TEC
    assert bus.counters[FLIGHT].tec == bus.counters[BOARD].tec == 8


def test_equal_frames_from_two_nodes_go_on_the_wire_once_and_both_succeed():
    bus = model(nodes=(FLIGHT, BOARD, "rogue"))
    bus.counters[FLIGHT].tec = bus.counters[BOARD].tec = 5
    bus.submit(FLIGHT, std(0x123, b"\x42"), T0)
    bus.submit(BOARD, std(0x123, b"\x42"), T0)
    deliveries = bus.run_until(T0 + MS)
    assert len(deliveries) == 1 and deliveries[0].destinations == ("rogue",)
    assert bus.counters[FLIGHT].tec == bus.counters[BOARD].tec == 4


def test_three_nodes_each_keep_their_own_tec_and_rec_by_the_iso_rules():
    # The flight side's commands are destroyed 20 times: its TEC +8 each (160: error-passive,
    # reported once at 96 and once at 128); each of the two receivers REC +1 each (20).
    bus = model(FaultSpec("error_frames", start_s=0.0, count=20, params={"restart_delay_s": 0.0}),
                nodes=(FLIGHT, BOARD, "rogue"))
    bus.submit(FLIGHT, PROTO.command([0.1, 0, 0], counter=0), T0)
    deliveries = bus.run_until(T0 + 10 * MS)
    tec_rec = {n: (c.tec, c.rec) for n, c in bus.counters.items()}
    # 20 errors, then one success: TEC 160 - 1; every receiver REC 20 - 1.
    assert tec_rec == {FLIGHT: (159, 0), BOARD: (0, 19), "rogue": (0, 19)}
    flight_states = [errors.read_error_frame(d.msg)[0] for d in deliveries
                     if d.destinations == (FLIGHT,) and d.msg.is_error_frame]
    assert len(flight_states) == 20 and flight_states[11] is errors.ErrorState.WARNING \
        and flight_states[15] is errors.ErrorState.PASSIVE
    # The rogue and the board both hear the command once it gets through.
    command = [d for d in deliveries if not d.msg.is_error_frame]
    assert len(command) == 1 and command[0].destinations == (BOARD, "rogue")


def test_error_counter_table_of_iso_11898():
    c = errors.ErrorCounters()
    table = []
    for step in ["tx_err"] * 12 + ["tx_ok"] + ["tx_err"] * 4 + ["rx_err"] * 130 + ["rx_ok", "rx_ok"] \
            + ["tx_err"] * 13:
        {"tx_err": c.on_transmit_error, "tx_ok": c.on_transmit_success,
         "rx_err": c.on_receive_error, "rx_ok": c.on_receive_success}[step]()
        table.append((c.tec, c.rec, c.state))
    assert table[11] == (96, 0, errors.ErrorState.WARNING)         # 12 x 8
    assert table[12] == (95, 0, errors.ErrorState.ACTIVE)          # - 1
    assert table[16] == (127, 0, errors.ErrorState.WARNING)        # 95 + 32
    assert table[17] == (127, 1, errors.ErrorState.WARNING)
    assert table[16 + 128] == (127, 128, errors.ErrorState.PASSIVE)  # REC 128: error-passive
    assert table[16 + 130] == (127, 130, errors.ErrorState.PASSIVE)
    assert table[16 + 131] == (127, 119, errors.ErrorState.WARNING)  # rule 8: from above 127 to 119
    assert table[16 + 132] == (127, 118, errors.ErrorState.WARNING)
    assert table[-13][0] == 135 and table[-1] == (231, 118, errors.ErrorState.PASSIVE)
    c.on_transmit_error()
    c.on_transmit_error(errors.BusError.ACK)        # error-passive: an ACK error costs nothing
    assert c.tec == 239
    c.on_transmit_error()
    c.on_transmit_error()
    assert c.tec == 255 and not c.bus_off
    assert c.on_transmit_error() is errors.ErrorState.BUS_OFF         # above 255


def test_a_node_alone_on_the_bus_gets_ack_errors_up_to_error_passive_and_no_further():
    bus = model(nodes=(FLIGHT,))
    bus.submit(FLIGHT, std(0x210, bytes(8)), T0)
    deliveries = bus.run_until(T0 + 20 * MS)
    reports = [d.msg for d in deliveries]
    assert all(m.is_error_frame and m.arbitration_id & errors.CAN_ERR_ACK for m in reports)
    # Reported on each change of state (ACK errors one by one only with berr-reporting): warning at
    # TEC 96 (12 attempts), error-passive at 128 (16), then retries for ever at 128.
    assert [(m.data[6], errors.read_error_frame(m)[0]) for m in reports] == [
        (96, errors.ErrorState.WARNING), (128, errors.ErrorState.PASSIVE)]
    assert bus.stats.bus_errors["ack"] > 100
    assert bus.counters[FLIGHT].tec == 128 and not bus.counters[FLIGHT].bus_off


def test_the_return_to_error_active_is_reported_to_the_node_and_the_driver_reads_it():
    # 12 destroyed attempts: TEC 96 (warning, reported). Then successful frames, one TEC each:
    # at TEC 95 the controller is error-active again, reported with CAN_ERR_CRTL_ACTIVE.
    from bench.bus.can.config import BoardConfig, DriverConfig
    from bench.bus.can.driver import MagnetorquerDriver
    bus = model(FaultSpec("error_frames", start_s=0.0, count=12))
    for k in range(3):
        bus.submit(FLIGHT, PROTO.command([0.1, 0, 0], counter=k), T0 + k * MS)
    deliveries = bus.run_until(T0 + 10 * MS)
    reports = [d.msg for d in deliveries if d.destinations == (FLIGHT,) and d.msg.is_error_frame]
    assert len(reports) == 13 and reports[-1].data[1] == errors.CAN_ERR_CRTL_ACTIVE and reports[-1].data[6] == 95
    assert bus.counters[FLIGHT].tec == 96 - 3                 # three frames got through
    driver = MagnetorquerDriver(can.Bus(interface="virtual", channel="arbitration-active"), DriverConfig(),
                                BoardConfig(), PROTO)
    for msg in reports:
        driver.handle(msg)
    assert [e.kind for e in driver.events] == ["error_warning", "error_active"]
    driver.bus.shutdown()
