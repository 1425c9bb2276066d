"""Board and driver in one process on python-can's virtual bus, on a simulated clock.

No bus model here: the two talk directly, and each test breaks one thing by hand.
"""
from __future__ import annotations

import itertools
import time

import can
import numpy as np
import pytest

from bench.bus.can import protocol as p
from bench.bus.can.board import MagnetorquerBoard
from bench.bus.can.config import BoardConfig, DriverConfig
from bench.bus.can.driver import MagnetorquerDriver

_channels = itertools.count()
TICK_S = 0.001


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


class Rig:
    def __init__(self, board_config: BoardConfig | None = None, driver_config: DriverConfig | None = None):
        channel = f"test-can-{next(_channels)}"
        self.clock = Clock()
        self.board_bus = can.Bus(interface="virtual", channel=channel)
        self.driver_bus = can.Bus(interface="virtual", channel=channel)
        self.rogue_bus = can.Bus(interface="virtual", channel=channel)   # another node on the bus
        self.board_config = board_config or BoardConfig()
        self.driver_config = driver_config or DriverConfig()
        self.applied = []
        self.coil_changes = []
        self.board = MagnetorquerBoard(self.board_bus, self.board_config, p.Protocol(), clock=self.clock,
                                       on_applied=self.applied.append,
                                       on_coils_changed=lambda s: self.coil_changes.append((s.safe_state, s.actuation_paused)))
        self.driver = MagnetorquerDriver(self.driver_bus, self.driver_config, self.board_config, p.Protocol(),
                                         clock=self.clock)
        self.events = []
        self.board_alive = True
        # Boot: the board's boot-up heartbeat, the driver's NMT start, the board operational.
        self.run(0.005, commanding=False)
        assert self.board.nmt_state == p.NMT_OPERATIONAL, self.board.nmt_state

    def run(self, duration_s: float, dipole_am2=(0.1, -0.05, 0.02), commanding: bool = True):
        next_command = self.clock.t
        for _ in range(round(duration_s / TICK_S)):
            if commanding and self.clock.t >= next_command:
                self.driver.command(dipole_am2)
                next_command += self.driver_config.command_period_s
            if self.board_alive:
                self.board.step(self.clock.t)
            self.events += self.driver.poll()
            self.clock.t += TICK_S

    def kinds(self):
        return [e.kind for e in self.events]

    def close(self):
        for bus in (self.board_bus, self.driver_bus, self.rogue_bus):
            bus.shutdown()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def test_clean_loop_applies_the_quantised_command_and_reports_nothing(rig):
    rig.run(0.5, dipole_am2=(0.1234, -0.05, 0.02))
    health = rig.driver.health()
    assert rig.events == []
    assert health.ok and health.alive and health.nmt_state == p.NMT_OPERATIONAL
    np.testing.assert_allclose(health.applied_dipole_am2, [0.123, -0.05, 0.02], atol=2e-4)
    np.testing.assert_allclose(health.coil_current_a, np.array([0.123, -0.05, 0.02]) / 2.0, atol=1e-3)
    assert rig.board.accepted == rig.driver.sent_frames
    assert rig.driver.health().bad_frames == {}


def test_dipole_beyond_the_board_limit_saturates_and_says_so(rig):
    rig.run(0.2, dipole_am2=(0.5, -0.5, 0.0))
    np.testing.assert_allclose(rig.board.state.target_dipole_am2, [0.2, -0.2, 0.0])
    assert rig.board.state.saturated
    assert "actuator_mismatch" not in rig.kinds()   # the driver knows the board's limit


def test_coil_current_follows_with_the_coil_time_constant(rig):
    rig.run(0.1, dipole_am2=(0.0, 0.0, 0.0))
    rig.driver.command((0.2, 0.0, 0.0))
    rig.board.step(rig.clock.t)
    tau = rig.board_config.coil_time_constant_s
    rig.clock.t += tau
    rig.board.step(rig.clock.t)
    # After one time constant, 1 - 1/e of the step.
    assert rig.board.applied_dipole_am2[0] == pytest.approx(0.2 * (1 - np.exp(-1)), rel=1e-6)


def test_board_goes_to_safe_state_when_commands_stop_and_driver_hears_it(rig):
    rig.run(0.3)
    rig.run(0.3, commanding=False)
    assert rig.board.state.safe_state
    assert np.allclose(rig.board.applied_dipole_am2, 0.0, atol=1e-6)
    assert rig.kinds().count("board_command_timeout") == 1
    assert rig.driver.health().safe_state and not rig.driver.health().ok
    assert rig.coil_changes == [(True, False)]          # whoever publishes the output hears of it
    assert np.all(rig.board.output_dipole_am2 == 0.0)
    # Detected within the timeout plus one telemetry period of the last command.
    event = next(e for e in rig.events if e.kind == "board_command_timeout")
    assert event.detected_ns  # stamped
    rig.run(0.2)
    assert not rig.board.state.safe_state and rig.driver.health().ok


def test_lost_board_is_detected_within_three_heartbeat_periods(rig):
    rig.run(0.5)
    rig.board_alive = False
    lost_at = rig.clock.t
    period = rig.board_config.heartbeat_period_s
    rig.run(3 * period)
    assert "heartbeat_timeout" in rig.kinds() and "telemetry_timeout" in rig.kinds()
    assert not rig.driver.health().alive
    rig.board_alive = True
    rig.run(0.3)
    assert "heartbeat_resumed" in rig.kinds()
    assert lost_at  # the bound is the run length above: 3 heartbeat periods


def test_corrupted_repeated_and_stale_commands_are_never_applied(rig):
    rig.run(0.2, dipole_am2=(0.1, 0.0, 0.0))
    proto = p.Protocol()
    last = rig.board.state.last_command_counter
    corrupted = bytearray(proto.command((0.2, 0.2, 0.2), counter=last + 1).data)
    corrupted[3] ^= 0x10
    rig.rogue_bus.send(can.Message(arbitration_id=0x210, is_extended_id=False, data=corrupted))
    rig.rogue_bus.send(proto.command((0.2, 0.2, 0.2), counter=last))            # repeated
    rig.rogue_bus.send(proto.command((0.2, 0.2, 0.2), counter=last + 8))        # out of sequence
    rig.run(0.001, commanding=False)
    assert dict(rig.board.rejected) == {"WRONG_CRC": 1, "REPEATED": 1, "WRONG_SEQUENCE": 1}
    assert all(np.allclose(a.dipole_am2, [0.1, 0.0, 0.0]) for a in rig.applied)
    # EMCY inhibit time: the first rejection is reported at once, the last of the others when
    # the inhibit time has passed (the board's running count says how many there were).
    rig.run(rig.board_config.emcy_inhibit_s + 0.002, commanding=False)
    rejected = [e.detail.split()[0] for e in rig.events if e.kind == "command_rejected"]
    assert rejected == ["WRONG_CRC", "WRONG_SEQUENCE"]
    assert rig.board.sent[p.EMCY] == 2
    assert rig.kinds().count("spoofed_command") == 3   # frames with our id we did not send


def test_corrupted_telemetry_is_detected_and_not_believed(rig):
    rig.run(0.2, dipole_am2=(0.1, 0.0, 0.0))
    proto = p.Protocol()
    fake = proto.encode(p.TLM_DIPOLE, {"AppliedDipoleX": -0.2}, counter=0)
    data = bytearray(fake.data)
    data[4] ^= 0x01
    rig.rogue_bus.send(can.Message(arbitration_id=0x190, is_extended_id=False, data=data))
    rig.run(0.001, commanding=False)
    assert "telemetry_corrupted" in rig.kinds()
    assert rig.driver.health().applied_dipole_am2[0] == pytest.approx(0.1, abs=1e-3)


def test_malformed_frames_are_counted_by_board_and_driver(rig):
    rig.run(0.1)
    garbage = [can.Message(arbitration_id=0x210, is_extended_id=False, data=b"\x00"),
               can.Message(arbitration_id=0x190, is_extended_id=False, data=b"\x00\x01\x02"),
               can.Message(arbitration_id=0x7FF, is_extended_id=False, data=bytes(8)),
               can.Message(arbitration_id=0x710, is_extended_id=False, data=b"\x99")]
    for msg in garbage:
        rig.rogue_bus.send(msg)
    rig.run(0.1)
    # The board hears all four; only the short command concerns it (and earns an emergency).
    assert rig.board.protocol.bad.counts == {"wrong_length": 2, "unknown_id": 1, "garbage": 1}
    assert rig.board.rejected == {"wrong_length": 1}
    assert "command_rejected" in rig.kinds()
    assert rig.driver.health().bad_frames == {"wrong_length": 1, "unknown_id": 1, "garbage": 1}
    # A frame on the command identifier that the driver did not send is a spoof attempt: health
    # is not ok for fault_hold_s, then ok again.
    assert rig.driver.health().recent_faults == ["spoofed_command"] and not rig.driver.health().ok
    rig.run(rig.driver_config.fault_hold_s)
    assert rig.driver.health().ok


def test_actuation_pauses_for_magnetometer_windows(rig):
    r = Rig(BoardConfig(mag_window_period_s=0.2, mag_window_s=0.05))
    try:
        paused, active = [], []
        for _ in range(40):
            r.run(0.01)
            (paused if r.board.state.actuation_paused else active).append(r.board.applied_dipole_am2[0])
        assert paused and active
        assert (False, True) in r.coil_changes and (False, False) in r.coil_changes
        assert max(abs(x) for x in paused[2:]) < 0.1  # coils decay during the window
        assert "actuator_mismatch" not in r.kinds()
    finally:
        r.close()


def test_applied_dipole_that_ignores_the_command_is_an_actuator_mismatch(rig):
    rig.run(0.3, dipole_am2=(0.1, 0.0, 0.0))
    rig.board._advance_coils = lambda target_current_a, now_s: None   # coil currents stuck
    rig.run(0.5, dipole_am2=(0.0, 0.1, 0.0))
    assert "actuator_mismatch" in rig.kinds()


def test_command_loop_commands_at_its_own_rate_from_another_thread():
    import threading

    from bench.bus.can.driver import CommandLoop

    channel = f"test-can-{next(_channels)}"
    board_bus, driver_bus = can.Bus(interface="virtual", channel=channel), can.Bus(interface="virtual", channel=channel)
    board = MagnetorquerBoard(board_bus, BoardConfig(), p.Protocol())
    driver = MagnetorquerDriver(driver_bus, DriverConfig(), BoardConfig(), p.Protocol())
    stop = threading.Event()
    sent = []
    loop = CommandLoop(driver, 0.02, on_command=lambda counter, dipole, ns: sent.append(dipole))
    board_thread = threading.Thread(target=board.run, args=(stop,))
    loop_thread = threading.Thread(target=loop.run, args=(stop,))
    try:
        board_thread.start()
        loop_thread.start()
        loop.set_dipole([0.0, 0.05, 0.0])        # as an attitude law on another thread would
        deadline = time.monotonic() + 5.0
        while not (loop.health.ok and loop.health.applied_dipole_am2[1] == pytest.approx(0.05, abs=1e-3)):
            assert time.monotonic() < deadline, loop.health
            time.sleep(0.01)
    finally:
        stop.set()
        loop_thread.join(2)
        board_thread.join(2)
        board_bus.shutdown()
        driver_bus.shutdown()
    assert sent and sent[-1] == [0.0, 0.05, 0.0]
    assert board.rejected == {}


def test_a_board_waiting_for_its_nmt_start_sleeps_between_its_frames():
    """A pre-operational board has only its heartbeat to send: its loop waits for that (or a
    frame, at most 10 ms), never spins. It once waited for its telemetry's time, which stands
    still until the NMT start, and so polled the bus without waiting: a CPU burnt, and at
    SCHED_FIFO on one CPU the driver that would start it never ran."""
    import threading

    channel = f"test-can-{next(_channels)}"
    bus = can.Bus(interface="virtual", channel=channel)
    polls = []
    receive = bus.recv
    bus.recv = lambda timeout=None: polls.append(timeout) or receive(timeout=timeout)
    board = MagnetorquerBoard(bus, BoardConfig(), p.Protocol())
    stop = threading.Event()
    thread = threading.Thread(target=board.run, args=(stop,))
    try:
        thread.start()
        time.sleep(0.5)
    finally:
        stop.set()
        thread.join(2)
        bus.shutdown()
    assert board.nmt_state == p.NMT_PRE_OPERATIONAL
    # 0.5 s at one wake-up per 10 ms at most, and a heartbeat each 0.1 s: some 55 polls
    assert 20 <= len(polls) <= 120, f"{len(polls)} polls in 0.5 s"
