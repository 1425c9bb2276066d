"""Bus model and fault injector on exact, simulated times: deterministic, no processes."""
from __future__ import annotations

import itertools
import random

import can
import pytest

from bench.bus.can import bittiming, errors
from bench.bus.can import protocol as p
from bench.bus.can.busmodel import BOARD, FLIGHT, BusModel
from bench.bus.can.driver import MagnetorquerDriver
from bench.bus.can.config import BoardConfig, DriverConfig
from bench.bus.can.faults import FaultSpec
from bench.bus.can.injector import FaultInjector

T0 = 10**12
MS = 1_000_000
CMD_PERIOD_NS = 20 * MS
PROTO = p.Protocol()


def frame(arbitration_id: int, data: bytes = bytes(8)) -> can.Message:
    return can.Message(arbitration_id=arbitration_id, is_extended_id=False, data=data)


# --- bit timing ---------------------------------------------------------------------------------
def test_stuffing_never_leaves_six_equal_bits_and_stays_within_the_textbook_bound():
    rng = random.Random(3)
    for _ in range(500):
        msg = frame(rng.randrange(0x800), bytes(rng.randrange(256) for _ in range(rng.randrange(9))))
        raw = bittiming.frame_bits_unstuffed(msg.arbitration_id, bytes(msg.data))
        stuffed = bittiming.stuff(raw)
        assert all(len(set(stuffed[i:i + 6])) == 2 for i in range(len(stuffed) - 5))
        n_data = len(msg.data)
        assert 47 + 8 * n_data <= bittiming.frame_bits(msg) <= bittiming.worst_case_bits(n_data)


def test_frame_durations_at_one_megabit():
    # 8 zero bytes at identifier 0: 111 bits plus 16 stuff bits (counted by hand from the
    # dominant runs), 127 us at 1 Mbit/s.
    assert bittiming.frame_bits(frame(0x000)) == 127
    assert bittiming.duration_ns(bittiming.frame_bits(frame(0x000)), 1_000_000) == 127_000
    assert bittiming.duration_ns(bittiming.frame_bits(frame(0x000)), 500_000) == 254_000


# --- arbitration and delivery -------------------------------------------------------------------
def model(*faults: FaultSpec, capture=None, tx_queue_frames: int = 8) -> BusModel:
    return BusModel(FaultInjector(list(faults), PROTO, seed=1), PROTO, T0, tx_queue_frames=tx_queue_frames,
                    capture=capture)


def test_lower_identifier_wins_and_frames_leave_after_their_last_bit():
    bus = model()
    telemetry = PROTO.encode(p.TLM_DIPOLE, {}, counter=0)        # 0x190
    command = PROTO.command([0.1, 0, 0], counter=0)                # 0x210
    bus.submit(FLIGHT, command, T0)
    bus.submit(BOARD, telemetry, T0)
    deliveries = bus.run_until(T0 + MS)
    assert [d.msg.arbitration_id for d in deliveries] == [0x190, 0x210]
    assert [d.destinations for d in deliveries] == [(FLIGHT,), (BOARD,)]
    first_end = T0 + bittiming.duration_ns(bittiming.frame_bits(telemetry), 1_000_000)
    second_end = first_end + bittiming.duration_ns(bittiming.frame_bits(command), 1_000_000)
    assert deliveries[1].msg.timestamp == pytest.approx(second_end / 1e9)
    assert bus.run_until(T0 + 2 * MS) == []


def commanding(bus: BusModel, duration_ns: int, start_ns: int = T0, telemetry: bool = False):
    """The flight side commanding every 20 ms (and the board answering every 50 ms)."""
    deliveries = []
    t = start_ns
    counter = itertools.count()
    tlm = itertools.count()
    while t < start_ns + duration_ns:
        if (t - start_ns) % CMD_PERIOD_NS == 0:
            bus.submit(FLIGHT, PROTO.command([0.1, 0, 0], counter=next(counter)), t)
        if telemetry and (t - start_ns) % (50 * MS) == 0:
            bus.submit(BOARD, PROTO.encode(p.TLM_DIPOLE, {}, counter=next(tlm)), t)
        deliveries += bus.run_until(t + 10 * MS)
        t += 10 * MS
    return deliveries + bus.run_until(t + 10 * MS)


def test_a_babbling_node_at_higher_priority_starves_the_commands():
    quiet = model()
    commanding(quiet, 1000 * MS)
    babbled = model(FaultSpec("flood", start_s=0.3, duration_s=0.4))
    commanding(babbled, 1000 * MS)
    calm, flooded = quiet.report(), babbled.report()
    assert calm["command_latency_us"]["without_flood"]["p99"] < 200      # one frame time
    assert flooded["peak_load_pct"] == pytest.approx(100.0, abs=0.5)
    assert flooded["dropped"]["tx_overflow"] > 0                          # controller buffers overflow
    assert flooded["command_latency_us"]["with_flood"]["median"] > 100 * calm["command_latency_us"]["without_flood"]["p99"]
    assert flooded["bus_load_pct"] > 30 > calm["bus_load_pct"]


def test_a_slower_babbler_delays_commands_without_dropping_them():
    bus = model(FaultSpec("flood", start_s=0.0, duration_s=1.0, params={"period_s": 0.0002}))
    commanding(bus, 1000 * MS)
    report = bus.report()
    assert "tx_overflow" not in report["dropped"]
    assert 50 < report["bus_load_pct"] < 70      # 127 us in every 200 us
    assert report["command_latency_us"]["with_flood"]["max"] < 400


# --- the faults, frame by frame -----------------------------------------------------------------
def run_commands(*faults: FaultSpec, duration_ms: int = 200):
    captured = []
    bus = model(*faults, capture=captured.append)
    deliveries = commanding(bus, duration_ms * MS, telemetry=True)
    return bus, deliveries, captured


def delivered(deliveries, destination, arbitration_id=0x210):
    return [d.msg for d in deliveries if destination in d.destinations and d.msg.arbitration_id == arbitration_id]


def test_every_submitted_frame_is_on_the_wire_dropped_or_replaced():
    faults = [FaultSpec("drop", start_s=0.02, count=2), FaultSpec("corrupt", start_s=0.05, count=2),
              FaultSpec("duplicate", start_s=0.1, count=1), FaultSpec("delay", start_s=0.12, count=1)]
    bus, deliveries, captured = run_commands(*faults)
    by_channel = {c: [m for m in captured if m.channel == c] for c in ("bus", "dropped", "replaced")}
    submitted = 10 + 4          # 10 commands, 4 telemetry frames
    injected = sum(1 for r in bus.injector.records if r.action == "injected")
    assert len(by_channel["bus"]) - injected + len(by_channel["dropped"]) == submitted
    assert len(by_channel["dropped"]) == 2 and len(by_channel["replaced"]) == 2 and injected == 1


def test_drop_delay_and_duplicate():
    bus, deliveries, _ = run_commands(FaultSpec("drop", start_s=0.05, count=3))
    assert len(delivered(deliveries, BOARD)) == 7
    bus, deliveries, _ = run_commands(FaultSpec("delay", start_s=0.05, count=1, params={"delay_s": 0.03}))
    counters = [m.data[1] & 0xF for m in delivered(deliveries, BOARD)]
    assert counters[:7] == [0, 1, 2, 4, 3, 5, 6]       # 30 ms late: the next frame overtakes it
    bus, deliveries, _ = run_commands(FaultSpec("duplicate", start_s=0.05, count=2, every=3, params={"copies": 2}))
    assert len(delivered(deliveries, BOARD)) == 14
    assert len(delivered(deliveries, FLIGHT)) == 4            # the copies are heard by the driver too


def test_corruption_without_recomputed_crc_never_passes_and_with_it_always_does():
    for recompute in (False, True):
        bus, deliveries, _ = run_commands(FaultSpec("corrupt", start_s=0.0, params={"recompute_crc": recompute, "bits": 3}))
        frames = [PROTO.decode(m) for m in delivered(deliveries, BOARD)]
        assert all(f.crc_ok == recompute for f in frames)


def test_spoofed_commands_fail_e2e_unless_the_spoofer_knows_the_data_ids():
    for knows in (False, True):
        bus, deliveries, _ = run_commands(FaultSpec("spoof", start_s=0.05, count=2, every=4,
                                                    params={"knows_data_id": knows, "dipole_am2": 0.15}))
        spoofed = [f for f in map(PROTO.decode, delivered(deliveries, BOARD)) if f.signals["DipoleY"] == pytest.approx(0.15)]
        assert len(spoofed) == 2 and all(f.crc_ok == knows for f in spoofed)


def test_counter_freeze_and_offset_keep_a_valid_crc():
    bus, deliveries, _ = run_commands(FaultSpec("counter_freeze", start_s=0.05, duration_s=0.05))
    frames = [PROTO.decode(m) for m in delivered(deliveries, BOARD)]
    assert [f.counter for f in frames][:7] == [0, 1, 2, 3, 3, 5, 6] and all(f.crc_ok for f in frames)
    bus, deliveries, _ = run_commands(FaultSpec("counter_offset", start_s=0.05, count=2, params={"offset": 5}))
    assert [PROTO.decode(m).counter for m in delivered(deliveries, BOARD)][:7] == [0, 1, 2, 8, 9, 5, 6]


def test_replay_sends_an_old_frame_again():
    bus, deliveries, _ = run_commands(FaultSpec("replay", start_s=0.0, count=2, every=5, params={"after_s": 0.05}),
                                      duration_ms=400)
    to_driver = delivered(deliveries, FLIGHT)
    assert len(to_driver) == 2 and all(PROTO.decode(m).counter == 0 for m in to_driver)


def test_a_board_without_power_leaves_the_bus_and_the_lone_flight_side_goes_error_passive():
    """board_power_loss: the board is off the bus for its window, so nobody acknowledges the flight
    side's commands (ACK errors, TEC + 8 each, error-passive at 128 and no further: ISO 11898-1
    exception 1), its queued frames are gone, and after the window the commands get through."""
    bus = model(FaultSpec("board_power_loss", start_s=0.05, duration_s=0.1))
    bus.submit(BOARD, PROTO.encode(p.TLM_DIPOLE, {}, counter=0), T0 + 50 * MS)   # queued as power goes: lost
    deliveries = commanding(bus, 300 * MS)
    states = [errors.read_error_frame(d.msg)[0] for d in deliveries if d.msg.is_error_frame]
    # passive (TEC 128) and back to warning at the first acknowledged frame (127)
    assert states == [errors.ErrorState.WARNING, errors.ErrorState.PASSIVE, errors.ErrorState.WARNING]
    heard = [round(d.msg.timestamp * 1e9) - T0 for d in deliveries if not d.msg.is_error_frame and BOARD in d.destinations]
    assert not [t for t in heard if 50 * MS <= t < 150 * MS]          # nothing reaches a board without power
    assert len([t for t in heard if t >= 150 * MS]) >= 7               # and after it, the commands again
    report = bus.report()
    assert report["tec_max"]["flight"] == 128 and bus.stats.bus_errors["ack"] > 16
    assert report["dropped"]["power_loss"] == 1
    assert not delivered(deliveries, FLIGHT, 0x190)


def test_frozen_telemetry_acts_on_the_board_side():
    for freeze in (False, True):
        bus, deliveries, _ = run_commands(FaultSpec("telemetry_freeze", start_s=0.0, duration_s=1.0,
                                                    params={"freeze_counter": freeze}))
        frames = [PROTO.decode(m) for m in delivered(deliveries, FLIGHT, 0x190)]
        assert all(f.crc_ok for f in frames)
        assert len({f.counter for f in frames}) == (1 if freeze else 4)


def test_error_frames_drive_the_transmitter_to_bus_off_and_back():
    bus = model(FaultSpec("error_frames", start_s=0.0, count=32, params={"restart_delay_s": 0.05}))
    deliveries = commanding(bus, 200 * MS)
    reports = [errors.read_error_frame(d.msg) for d in deliveries if d.msg.is_error_frame]
    states = [state for state, restarted in reports if not restarted]
    assert states.index(errors.ErrorState.WARNING) == 11                # TEC 96 after 12 errors
    assert states.index(errors.ErrorState.PASSIVE) == 15                # TEC 128 after 16
    assert states[-1] == errors.ErrorState.BUS_OFF and len(states) == 32
    assert reports[-1] == (errors.ErrorState.ACTIVE, True)              # restarted
    report = bus.report()
    assert report["bus_off"] == {"flight": 1} and report["dropped"]["bus_off"] == 1
    # The driver reads the same error frames into events.
    driver = MagnetorquerDriver(can.Bus(interface="virtual", channel="busmodel-errors"), DriverConfig(),
                                BoardConfig(), PROTO)
    for d in deliveries:
        if d.msg.is_error_frame:
            driver.handle(d.msg)
    assert [e.kind for e in driver.events] == ["error_warning", "error_passive", "bus_off", "bus_restarted"]
    driver.bus.shutdown()


def _bus_off_then(board_frames_after_restart: int):
    """Five commands queued at T0; the first is destroyed 32 times (bus-off); the board sends
    frames from the moment the flight controller's restart delay ends."""
    bus = model(FaultSpec("error_frames", start_s=0.0, count=32, params={"restart_delay_s": 0.01}))
    for k in range(5):
        bus.submit(FLIGHT, PROTO.command([0.1, 0, 0], counter=k), T0)
    deliveries = bus.run_until(T0 + 5 * MS)
    bus_off_ns = round(deliveries[-1].msg.timestamp * 1e9)
    assert errors.read_error_frame(deliveries[-1].msg) == (errors.ErrorState.BUS_OFF, False)
    restart_ns = bus_off_ns + 10 * MS
    telemetry = [PROTO.encode(p.TLM_DIPOLE, {}, counter=k) for k in range(board_frames_after_restart)]
    bus.run_until(restart_ns - 1)
    for msg in telemetry:
        bus.submit(BOARD, msg, restart_ns)
    deliveries = bus.run_until(T0 + 100 * MS)
    restarted = [d for d in deliveries if d.msg.is_error_frame and d.destinations == (FLIGHT,)]
    assert len(restarted) == 1 and errors.read_error_frame(restarted[0].msg) == (errors.ErrorState.ACTIVE, True)
    return bus, restart_ns, round(restarted[0].msg.timestamp * 1e9), telemetry


def test_bus_off_recovery_is_the_restart_delay_then_128_times_11_recessive_bits_and_the_queue_is_flushed():
    bus, restart_ns, back_ns, _ = _bus_off_then(0)
    assert back_ns - restart_ns == 1408 * 1000          # idle bus at 1 Mbit/s: 1408 bit times
    assert bus.report()["dropped"] == {"bus_off": 1, "bus_off_flush": 4}


def test_frames_during_recovery_count_by_their_recessive_bits_and_a_lone_transmitter_stops_at_error_passive():
    bus, restart_ns, back_ns, telemetry = _bus_off_then(3)
    # Worked by hand. With the flight side bus-off the board is alone: no ACK. Each attempt runs
    # to the ACK slot (frame bits - 13 tail + CRC delimiter + ACK slot), then an error frame.
    # Error-active (attempts 1-16, TEC 8..128): a dominant flag and its echo (12 bits), delimiter
    # and intermission: 11 recessive bits at the end, one of the 128 occurrences recovery waits
    # for. Error-passive (from attempt 17): the flag is recessive (6 + 8 + 3 bits), so CRC
    # delimiter, ACK slot and the error frame make 19 recessive bits, and suspend transmission 8
    # more before the next start of frame: 27, two occurrences per attempt (the 5 left over end at
    # the dominant start of frame; the 16th attempt's 11 and the suspend after it, 19, make one).
    # 16 + 2 x 55 = 126 after 71 attempts; the 72nd's tail makes 127 and leaves 8 bits of a run,
    # which 3 bits of its suspend complete: the 128th.
    frame = bittiming.frame_bits(telemetry[0])
    active_bits, passive_bits = frame - 13 + 2 + 23, frame - 13 + 2 + 17
    assert back_ns - restart_ns == (16 * active_bits + 8 + 55 * (passive_bits + 8) + passive_bits + 3) * 1000
    # ACK errors raise an error-passive transmitter's TEC no further (ISO 11898-1 rule 3, exception 1).
    assert bus.stats.tec_max["board"] == 128 and not bus.counters["board"].bus_off
    assert bus.stats.bus_errors["ack"] == 72           # then the flight side ACKs again


def test_stepping_from_event_to_event_through_a_bus_off_recovery_delivers_as_one_run():
    """The lock-step bus runs the model from one `next_event_ns` to the next. Each must lie after
    the time the model ran to, or that caller steps a nanosecond at a time: a frame in flight
    holds a bus-off node's recovery until its end. The frames equal one run over the whole span."""
    def bus_off_with_board_frames(board_at_ns=()) -> BusModel:
        bus = model(FaultSpec("error_frames", start_s=0.0, count=32, params={"restart_delay_s": 0.001}))
        for k in range(5):
            bus.submit(FLIGHT, PROTO.command([0.1, 0, 0], counter=k), T0)
        for k, t_ns in enumerate(board_at_ns):
            bus.submit(BOARD, PROTO.encode(p.TLM_DIPOLE, {}, counter=k), t_ns)
        return bus

    probe = bus_off_with_board_frames().run_until(T0 + 10 * MS)
    bus_off_ns = next(round(d.msg.timestamp * 1e9) for d in probe if d.msg.is_error_frame
                      and errors.read_error_frame(d.msg) == (errors.ErrorState.BUS_OFF, False))
    # Recovery is due 1408 bit times (1.408 ms) after the restart; a board frame starts 8 us
    # before that and is in flight when it falls due. Others come before and after.
    due_ns = bus_off_ns + MS + 1408 * 1000
    board_at_ns = (due_ns - 700_000, due_ns - 8_000, due_ns + 500_000)
    deliveries = bus_off_with_board_frames(board_at_ns).run_until(T0 + 50 * MS)
    reports = [errors.read_error_frame(d.msg) for d in deliveries if d.msg.is_error_frame]
    assert (errors.ErrorState.ACTIVE, True) in reports      # the flight side recovered
    whole = [(d.msg.arbitration_id, d.msg.timestamp, d.destinations) for d in deliveries]
    bus = bus_off_with_board_frames(board_at_ns)
    stepped, t_ns, steps = [], T0, 0
    while t_ns <= T0 + 50 * MS:
        stepped += [(d.msg.arbitration_id, d.msg.timestamp, d.destinations) for d in bus.run_until(t_ns)]
        next_ns = bus.next_event_ns()
        if next_ns is None:
            break
        assert next_ns > t_ns, (steps, t_ns, next_ns)
        t_ns, steps = next_ns, steps + 1
    assert stepped == whole


def test_a_copy_that_starts_with_the_next_command_collides_and_only_the_command_is_retried():
    """A starved driver sends its next command while the last one is still on the wire. The
    duplicate fault's copy (injected once the original is sent) and that command then start
    together: equal identifiers, different data, a bit error. The driver's controller retransmits
    its command; the injector has no controller, so its copy is destroyed, recorded as collided, and
    never reaches the board (the fault tests count it out: test_can_faults.injected_frames_on_the_wire)."""
    captured = []
    bus = model(FaultSpec("duplicate", start_s=0.0, count=1), capture=captured.append)
    first, second = PROTO.command([0.1, 0, 0], counter=0), PROTO.command([0.1, 0, 0], counter=1)
    bus.submit(FLIGHT, first, T0)
    bus.submit(FLIGHT, second, T0 + 10_000)          # 10 us on: the first is still on the wire
    deliveries = bus.run_until(T0 + 5 * MS)
    to_board = [bytes(d.msg.data) for d in deliveries if BOARD in d.destinations and not d.msg.is_error_frame]
    assert to_board == [bytes(first.data), bytes(second.data)]
    assert [r.action for r in bus.injector.records] == ["injected", "collided"]
    assert bus.stats.bus_errors and sum(bus.stats.bus_errors.values()) == 1
    # What the fault suite's accounting counts as on the wire: the two commands, not the copy.
    on_the_wire = [m for m in captured if m.channel == "bus" and not m.is_error_frame]
    assert [bytes(m.data) for m in on_the_wire] == [bytes(first.data), bytes(second.data)]


def test_the_fast_bit_counts_equal_the_bit_by_bit_stream():
    """The bus's frame lengths (counted from runs of equal bits, CRC-15 a byte at a time) against
    the stream built and stuffed bit by bit (frame_bits_unstuffed, crc15, stuff), on random
    classic, remote and FD frames with long runs of equal bits."""
    import random
    rng = random.Random(3)
    for _ in range(3000):
        extended = rng.random() < 0.3
        ident = rng.choice([0, (1 << (29 if extended else 11)) - 1, rng.getrandbits(29 if extended else 11)])
        data = bytes(rng.choice([0, 255, rng.getrandbits(8)]) for _ in range(rng.randint(0, 8)))
        remote = rng.random() < 0.1
        data = bytes(len(data)) if remote else data
        slow = len(bittiming.stuff(bittiming.frame_bits_unstuffed(ident, data, extended=extended, remote=remote)))
        assert bittiming._frame_bits.__wrapped__(ident, data, extended, remote) == slow + bittiming.TAIL_BITS
        fd_data = bytes(rng.choice([0, 255, rng.getrandbits(8)]) for _ in range(rng.choice([0, 8, 12, 20, 32, 64])))
        checked = 4 + (17 if len(fd_data) <= 16 else 21)
        slow_fd = len(bittiming.stuff(bittiming.fd_bits_unstuffed(ident, fd_data, extended))) + checked + 1 + checked // 4
        assert bittiming._fd_frame_bits.__wrapped__(ident, fd_data, extended) == slow_fd + bittiming.TAIL_BITS
