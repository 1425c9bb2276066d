"""Bus-off and its recovery (ISO 11898-1 fault confinement), collisions between the bus's own
nodes, on exact simulated times.

A collision: two controllers start the same identifier with different data. Both send the
identifier (arbitration cannot separate them); the one that sends a recessive bit where the
other sends a dominant one reads back the wrong bit: a bit error. An error-active node then sends
an active (dominant) error flag that destroys the frame for every transmitter (each: TEC + 8);
an error-passive node's flag is recessive: nobody else sees it, and the frame goes on for the
node that sent the dominant bit (which then needs some other node to acknowledge it). A bus-off
node rejoins, error-active with TEC = REC = 0, after it has seen 128 occurrences of 11
consecutive recessive bits: on an idle bus 1408 bit times after it went bus-off.

Expected values are worked by hand from those rules, not computed with the code under test.
"""
from __future__ import annotations

import can
import pytest

from bench.bus.can import bittiming, errors
from bench.bus.can import protocol as p
from bench.bus.can.busmodel import BOARD, FLIGHT, BusModel
from bench.bus.can.injector import FaultInjector

T0 = 10**12
MS = 1_000_000
US = 1_000
PROTO = p.Protocol()
LISTENER = "listener"


def std(frame_id: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=frame_id, is_extended_id=False, data=data)


# 0x555 = 101 0101 0101: SOF and identifier alternate; RTR, IDE, r0 and DLC 0001 give 0 0 0 0 0,
# a stuff bit 1, then 0 1. Bits 0..19 are equal for any one-byte data; bit 20 is the first data
# bit: 0 for 0x00 (dominant: wins), 1 for 0x80 (recessive: the bit error is this node's).
WINS, LOSES = std(0x555, b"\x00"), std(0x555, b"\x80")
ACTIVE_COLLISION_BITS = 20 + 1 + 23      # up to the bit error, then the error frame (flag, echo, delimiter, intermission)
SUSPEND_BITS = 8                         # an error-passive transmitter waits this long after intermission


def model(nodes=(FLIGHT, BOARD), bitrate_bps: int = 500_000) -> BusModel:
    return BusModel(FaultInjector([], PROTO, seed=1), PROTO, T0, nodes=nodes, bitrate_bps=bitrate_bps)


def reports_to(deliveries, node: str) -> list[can.Message]:
    return [d.msg for d in deliveries if d.msg.is_error_frame and d.destinations == (node,)]


def t_ns(msg: can.Message) -> int:
    return round(msg.timestamp * 1e9)


@pytest.mark.parametrize("bitrate_bps, recovery_ns", [
    (500_000, 2_816_000),       # 1408 bit times of 2 us
    (125_000, 11_264_000),      # 1408 bit times of 8 us
])
def test_collisions_take_a_node_through_passive_to_bus_off_and_it_rejoins_after_1408_bit_times(bitrate_bps, recovery_ns):
    """Three nodes; an attacker makes the flight side and the board start 0x555 together with
    different data, once every 10 ms (19 times). The board's data loses at bit 20 each time.

    Pair 1: 16 collisions with both error-active (TEC 8, 16, ... 128: warning at 96, passive at
    128). The 17th attempt: the board is error-passive, its flag recessive; the flight side's frame
    goes on, the listener acknowledges it (flight TEC 127: error-active again), board TEC 136. The
    board sends its frame alone after that: acknowledged, TEC 135.
    Pairs 2..19: flight error-active, board error-passive: the board loses (+8), the flight side's
    frame goes through, the board's follows (-1): TEC 143, 150, ... 255 (pair 18: still passive,
    255 is not above 255), then 262 at pair 19: bus-off, its queue flushed. The bus is idle from
    then on: the board rejoins 128 x 11 bit times later, counters at zero."""
    bit_ns = 10**9 // bitrate_bps
    period_ns = 10 * MS          # longer than pair 1 takes at 125 kbit/s (about 830 bits)
    bus = model(nodes=(FLIGHT, BOARD, LISTENER), bitrate_bps=bitrate_bps)
    deliveries = []
    for k in range(19):
        bus.submit(FLIGHT, WINS, T0 + k * period_ns)
        bus.submit(BOARD, LOSES, T0 + k * period_ns)
        deliveries += bus.run_until(T0 + (k + 1) * period_ns - 1)
    deliveries += bus.run_until(T0 + 200 * MS)

    board = reports_to(deliveries, BOARD)
    tec = [m.data[6] for m in board]
    expected_tec = [8 * k for k in range(1, 17)] + [136] + [143 + 7 * k for k in range(17)] + [255]
    assert tec[:len(expected_tec)] == expected_tec                      # error frame's TEC byte: at most 255
    states = [errors.read_error_frame(m) for m in board]
    assert states[10][0] is errors.ErrorState.ACTIVE and states[11][0] is errors.ErrorState.WARNING   # 88, 96
    assert states[14][0] is errors.ErrorState.WARNING and states[15][0] is errors.ErrorState.PASSIVE  # 120, 128
    assert all(s is errors.ErrorState.PASSIVE for s, _ in states[16:34])                          # 136 .. 255
    assert states[34:] == [(errors.ErrorState.BUS_OFF, False), (errors.ErrorState.ACTIVE, True)]

    # Bus-off when the 19th pair's winning frame ends (it started at the pair's time, the bus idle).
    bus_off_ns, back_ns = t_ns(board[34]), t_ns(board[35])
    assert bus_off_ns == T0 + 18 * period_ns + bittiming.frame_bits(WINS) * bit_ns
    assert back_ns - bus_off_ns == recovery_ns == 1408 * bit_ns
    assert (bus.counters[BOARD].tec, bus.counters[BOARD].rec, bus.counters[BOARD].bus_off) == (0, 0, False)

    # The flight side: 16 collisions (TEC 128, passive), then one success each pair: 127 - 18.
    flight_states = [errors.read_error_frame(m)[0] for m in reports_to(deliveries, FLIGHT)]
    assert flight_states[11] is errors.ErrorState.WARNING and flight_states[15] is errors.ErrorState.PASSIVE
    assert flight_states[16:] == [errors.ErrorState.WARNING]              # 127: back below 128, reported
    assert bus.counters[FLIGHT].tec == 127 - 18 and not bus.counters[FLIGHT].bus_off
    # Every frame of the flight side got through (heard by the listener; the board was each time
    # the transmitter that had lost), and 18 of the board's (the 19th flushed by bus-off).
    frames = [d for d in deliveries if not d.msg.is_error_frame]
    assert [d.destinations for d in frames if bytes(d.msg.data) == b"\x00"] == [(LISTENER,)] * 19
    assert [d.destinations for d in frames if bytes(d.msg.data) == b"\x80"] == [(FLIGHT, LISTENER)] * 18
    assert bus.report()["dropped"] == {"bus_off": 1}

    # Back on the bus: it hears the flight side's next frame.
    bus.submit(FLIGHT, WINS, back_ns + MS)
    after = bus.run_until(back_ns + 2 * MS)
    assert [d.destinations for d in after] == [(BOARD, LISTENER)]


def test_an_idle_bus_brings_a_bus_off_node_back_after_exactly_1408_bit_times_at_500_kbit():
    """The arithmetic of the brief, by hand: 128 x 11 = 1408 bit times; at 500 kbit/s a bit is
    2 us, so 2.816 ms. The node at TEC 248 (error-passive) loses one collision: 256, bus-off."""
    assert 128 * 11 == 1408 and 1408 * (1e9 / 500_000) == 2_816_000
    bus = model(nodes=(FLIGHT, BOARD, LISTENER))
    bus.counters[BOARD].tec = 248
    bus.submit(FLIGHT, WINS, T0)
    bus.submit(BOARD, LOSES, T0)
    deliveries = bus.run_until(T0 + 100 * MS)
    board = [errors.read_error_frame(m) for m in reports_to(deliveries, BOARD)]
    assert board == [(errors.ErrorState.BUS_OFF, False), (errors.ErrorState.ACTIVE, True)]
    bus_off_ns, back_ns = (t_ns(m) for m in reports_to(deliveries, BOARD))
    assert back_ns - bus_off_ns == 2_816_000
    # The flight side's frame went through in the attempt the board lost (error-passive flag).
    assert [d.destinations for d in deliveries if not d.msg.is_error_frame] == [(LISTENER,)]
    assert bus.counters[FLIGHT].tec == 0


def test_a_colliding_attacker_takes_both_ends_bus_off_again_and_again_and_the_bus_works_when_it_stops():
    """The bench's bus (flight side and board, no one else). An attacker sends as both ends at once,
    every 4 ms for 0.4 s, the losing side alternating; meanwhile the driver commands every 10 ms and
    the board sends telemetry every 50 ms. Each bus-off recovers on its own, while the attack goes
    on, after 128 x 11 recessive bits: never sooner than 1408 bit times, and never later than 128
    of the longest attempt (a lone error-passive transmitter retrying without acknowledgement
    supplies at least one occurrence per attempt). When the attack stops, commands reach the
    board again at once, with no restart."""
    bitrate = 500_000
    bit_ns = 10**9 // bitrate
    bus = model(bitrate_bps=bitrate)
    attack_end_ns = T0 + 400 * MS
    events = []
    for t in range(T0, attack_end_ns, 4 * MS):
        events.append((t, "attack", None))
    for k, t in enumerate(range(T0, T0 + 800 * MS, 10 * MS)):
        events.append((t + 1, FLIGHT, PROTO.command([0.1, 0, 0], counter=k % 16)))
    for k, t in enumerate(range(T0, T0 + 800 * MS, 50 * MS)):
        events.append((t + 2, BOARD, PROTO.encode(p.TLM_DIPOLE, {}, counter=k % 16)))
    deliveries = []
    for i, (t, who, msg) in enumerate(sorted(events, key=lambda e: e[0])):
        deliveries += bus.run_until(t)
        if who == "attack":
            flight_loses = (t - T0) // (4 * MS) % 2 == 1
            bus.submit(FLIGHT, LOSES if flight_loses else WINS, t)
            bus.submit(BOARD, WINS if flight_loses else LOSES, t)
        else:
            bus.submit(who, msg, t)
    deliveries += bus.run_until(T0 + 900 * MS)

    longest_attempt_bits = bittiming.worst_case_bits(8) + 23 + SUSPEND_BITS
    for node in (FLIGHT, BOARD):
        states = [(errors.read_error_frame(m), t_ns(m)) for m in reports_to(deliveries, node)]
        offs = [t for (state, restarted), t in states if state is errors.ErrorState.BUS_OFF]
        backs = [t for (state, restarted), t in states if restarted]
        assert len(offs) >= 2, (node, len(offs))                 # again and again, during the attack
        assert len(backs) == len(offs)                           # each one recovered
        for off, back in zip(offs, backs):
            assert 1408 * bit_ns <= back - off <= 128 * longest_attempt_bits * bit_ns, (node, off - T0, back - off)
        assert offs[-1] < attack_end_ns                          # and while it went on
        assert not bus.counters[node].bus_off

    # After the attack (and the last recovery), every command reaches the board within one frame
    # time of its submission: one frame (at most 160 bits) plus at most one frame ahead of it.
    quiet_ns = attack_end_ns + 20 * MS
    commands = [d for d in deliveries if not d.msg.is_error_frame and d.msg.arbitration_id == PROTO.frame_ids[PROTO.command_name]
                and t_ns(d.msg) > quiet_ns]
    assert len(commands) == len(range(42, 80)) and all(d.destinations == (BOARD,) for d in commands)
    for d in commands:
        submitted = T0 + 1 + 10 * MS * ((t_ns(d.msg) - T0) // (10 * MS))
        assert t_ns(d.msg) - submitted <= 2 * bittiming.worst_case_bits(8) * bit_ns


def test_the_issue_44_collision_attack_on_simulated_time_leaves_the_board_commanded(tmp_path):
    """Issue 44's attack, rerun on simulated time through the lock-step loop's driver, bus model and
    board: 9 frames sent as both ends of the bus at once within 0.34 s, the losing end alternating
    (the flight side's first). On the old model it took both controllers bus-off each time (both
    TECs + 8 at every attempt, error-passive or not) and kept them off for a 0.1 s restart delay:
    the board's coils went to their safe state (command timeout). Now the error-passive loser's
    flag no longer destroys the other's frame, and suspend transmission lets the error-active end
    go first: only the first pair (both TECs equal) ends in a bus-off, of the losing end, and it
    rejoins after its 128 x 11 recessive bits (the other end's retries supply them). The commands
    the attack costs are single ones (a bus-off flushes its controller's queue), the board never
    times out, the driver sees its controller go bus-off and come back, and the board applies the
    commands that follow."""
    from bench.bus.can.busmodel import BOARD as BOARD_NODE, FLIGHT as FLIGHT_NODE
    from bench.bus.can.sim_window import mission_s
    from bench.runtime.can_bench import write_scenario
    from bench.runtime.can_bench_simulated import SimulatedCanBench

    scenario = write_scenario(tmp_path / "scenario", {})
    bench = SimulatedCanBench(scenario, tmp_path / "run", "canbusoff-attack")
    try:
        bench.start()
        bench.drive(0.5)
        attack_start_ns = bench.t_ns
        for k in range(17):
            if k % 2 == 0:
                flight_loses = (k // 2) % 2 == 0
                bench.bus.model.submit(FLIGHT_NODE, LOSES if flight_loses else WINS, bench.t_ns)
                bench.bus.model.submit(BOARD_NODE, WINS if flight_loses else LOSES, bench.t_ns)
            bench.drive(bench.period_ns / 1e9)
        attack_end_ns = bench.t_ns
        bench.drive(0.5)
        last_commands = bench.sent[-5:]
    except BaseException:
        bench.close()
        raise
    r = bench.stop()
    assert attack_end_ns - attack_start_ns == 340 * MS
    bit_ns = 10**9 // bench.config.bitrate_bps
    # The board's coils per window (what the plant would integrate): never in the safe state while
    # commanded.
    commanded = [m for m in r.mtq_applied
                 if mission_s(attack_start_ns) <= m.header.sim_time_s < mission_s(bench.last_command_ns)]
    assert len(commanded) >= 40 and not any(m.safe_state for m in commanded)
    assert r.first_event("board_command_timeout", attack_start_ns).detected_ns > bench.last_command_ns
    # The flight side's controller went bus-off and came back, each time after at least 1408 bit
    # times; the driver saw both, and the report lists every episode with its recovery.
    assert r.report["bus_off"].get("flight", 0) >= 1
    assert r.report["bus_off_recovered"] == r.report["bus_off"]
    episodes = r.report["bus_off_episodes"]
    assert len(episodes) == sum(r.report["bus_off"].values())
    assert all(e["recovered_ns"] - e["bus_off_ns"] >= 1408 * bit_ns for e in episodes)
    assert all(attack_start_ns <= e["bus_off_ns"] < attack_end_ns for e in episodes)
    kinds = [e.kind for e in r.events if attack_start_ns <= e.detected_ns <= attack_end_ns + 100 * MS]
    assert kinds.count("bus_off") == r.report["bus_off"]["flight"] == kinds.count("bus_restarted")
    assert kinds.count("command_lost") <= r.report["bus_off"]["flight"]
    applied = {entry["counter"] for entry in r.board["applied"][-10:]}
    assert {counter for counter, _ in last_commands} <= applied


def test_the_real_time_bridge_lets_frames_sent_at_one_time_by_both_ends_collide():
    """In real time the bus model runs behind a bridge that submits each frame at its sender's
    timestamp. Frames both ends sent at the same time must start together: with equal identifiers
    and different data, a collision (a bit error for both). The bridge advanced the model to a
    frame's time before submitting it, so the first started alone and the second waited: the
    two ends never collided, whatever they sent."""
    import threading
    import time

    from bench.bus.can.realtime_bridge import RealTimeBridge

    bus = BusModel(FaultInjector([], PROTO, seed=1), PROTO, time.monotonic_ns(), nodes=(FLIGHT, BOARD))
    ends = {FLIGHT: can.Bus(interface="virtual", channel="bridge-collision-flight"),
            BOARD: can.Bus(interface="virtual", channel="bridge-collision-board")}
    bridge = RealTimeBridge(bus, ends)
    try:
        sent_s = time.time() - 0.001
        for side, msg in ((FLIGHT, WINS), (BOARD, LOSES)):
            stamped = can.Message(timestamp=sent_s, arbitration_id=msg.arbitration_id, is_extended_id=False,
                                  data=msg.data)
            bridge._inbox.put((side, stamped, time.monotonic_ns()))
        stop = threading.Event()
        runner = threading.Thread(target=bridge.run, args=(stop,))
        runner.start()
        time.sleep(0.2)
        stop.set()
        runner.join(5)
    finally:
        for end in ends.values():
            end.shutdown()
    assert bus.stats.bus_errors["bit"] >= 16          # the two ends collided (both TECs to 128 first)
    assert bus.report()["bus_off"] == {BOARD: 1} and bus.report()["bus_off_recovered"] == {BOARD: 1}
