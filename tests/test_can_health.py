"""Driver health that means what it says (issue 13): per-frame telemetry deadlines, a hold after
spoofs and implausible telemetry, bus-off recovery, error-active reported, host overruns apart."""
from __future__ import annotations

import can
import numpy as np
import pytest

from bench.bus.can import errors
from bench.bus.can import protocol as p
from bench.bus.can.driver import CommandLoop
from test_can_board_driver import Rig


def test_silent_dipole_telemetry_makes_health_not_ok_while_coil_telemetry_continues():
    rig = Rig()
    try:
        rig.run(0.3)
        assert rig.driver.health().ok
        real_send = rig.board._send
        rig.board._send = lambda msg: None if msg.arbitration_id == 0x190 else real_send(msg)  # TLM_DIPOLE only
        rig.run(1.0)
        health = rig.driver.health()
        assert [e.frame for e in rig.events if e.kind == "telemetry_timeout"] == [p.TLM_DIPOLE]
        assert not health.telemetry_fresh and not health.ok
        rig.board._send = real_send
        rig.run(0.2)
        # Fresh again; its alive counter jumped by the silent frames: out of sequence, held.
        assert rig.driver.health().telemetry_fresh
        assert rig.driver.health().recent_faults == ["telemetry_out_of_sequence"]
        rig.run(rig.driver_config.fault_hold_s)
        assert rig.driver.health().ok
    finally:
        rig.close()


def test_a_spoofed_command_makes_health_not_ok_for_the_hold_time():
    rig = Rig()
    try:
        rig.run(0.3)
        rig.rogue_bus.send(p.Protocol().command((0.2, 0.2, 0.2), counter=3))
        rig.run(0.01)
        assert "spoofed_command" in rig.kinds() and not rig.driver.health().ok
        rig.run(rig.driver_config.fault_hold_s - 0.05)
        assert rig.driver.health().recent_faults == ["spoofed_command"]
        rig.run(0.1)
        assert rig.driver.health().ok
    finally:
        rig.close()


def test_an_implausible_applied_dipole_makes_health_not_ok():
    rig = Rig()
    try:
        rig.run(0.3, dipole_am2=(0.1, 0.0, 0.0))
        rig.board._advance_coils = lambda target_current_a, now_s: None   # coil currents stuck
        rig.run(0.5, dipole_am2=(0.0, 0.1, 0.0))
        assert "actuator_mismatch" in rig.kinds()
        assert rig.driver.health().recent_faults == ["actuator_mismatch"] and not rig.driver.health().ok
    finally:
        rig.close()


def test_a_stray_bus_off_error_frame_does_not_leave_the_driver_bus_off():
    # As `cansend` of an error frame would: bus-off, and no restart ever reported.
    rig = Rig()
    try:
        rig.run(0.2)
        rig.rogue_bus.send(errors.error_frame(errors.ErrorState.BUS_OFF, 256))
        rig.run(0.001)
        assert rig.driver.health().bus_state == "bus_off" and not rig.driver.health().ok
        rig.run(0.1)
        recovery_s = 128 * 11 / 1_000_000
        assert rig.driver.bus_off_recovery_s == recovery_s
        assert rig.driver.health().bus_state == "error_active" and rig.driver.health().ok
        assert rig.kinds() == ["bus_off", "error_active"]
    finally:
        rig.close()


def test_the_return_to_error_active_is_reported():
    rig = Rig()
    try:
        rig.run(0.1)
        rig.rogue_bus.send(errors.error_frame(errors.ErrorState.PASSIVE, 130))
        active = can.Message(arbitration_id=errors.CAN_ERR_CRTL | errors.CAN_ERR_CNT, is_error_frame=True,
                             is_extended_id=False, data=bytes([0, errors.CAN_ERR_CRTL_ACTIVE, 0, 0, 0, 0, 90, 0]))
        rig.rogue_bus.send(active)
        rig.run(0.01)
        assert rig.kinds() == ["error_passive", "error_active"]
    finally:
        rig.close()


def test_a_late_command_thread_is_a_host_overrun_and_the_timeout_it_causes_says_so():
    rig = Rig()
    try:
        rig.run(0.3)
        # The driver's thread stalls for 150 ms (no command, no poll) while the board runs on.
        for _ in range(150):
            rig.board.step(rig.clock.t)
            rig.clock.t += 0.001
        rig.run(0.1)
        timeouts = [e for e in rig.events if e.kind == "board_command_timeout"]
        assert len(timeouts) == 1 and timeouts[0].detail.startswith("cause host_overrun")
    finally:
        rig.close()


def test_command_loop_counts_its_own_late_periods_as_host_overruns():
    rig = Rig()
    try:
        loop = CommandLoop(rig.driver, 0.02)
        real_poll = rig.driver.poll
        calls = {"n": 0}

        def poll(timeout_s=0.0, max_frames=1000, lock=None):
            calls["n"] += 1
            rig.clock.t += 0.045 if calls["n"] == 20 else 0.001   # one stall of 45 ms
            rig.board.step(rig.clock.t)
            return real_poll(0.0, max_frames, lock)

        rig.driver.poll = poll
        heard = []
        loop.on_events = heard.extend
        loop.run(duration_s=0.5)
        assert rig.driver.host_overruns == 1
        assert [e.kind for e in rig.driver.events].count("host_overrun") == 1
        assert [e.kind for e in heard] == ["host_overrun"]        # whoever listens to the loop hears it
        assert loop.health.host_overruns == 1
        assert np.allclose(rig.board.state.target_dipole_am2, 0.0)   # the loop's default dipole
    finally:
        rig.close()


@pytest.mark.parametrize("transmission, sent_at_once", [("cyclic", False), ("on_change", True), ("mixed", True)])
def test_a_new_dipole_goes_out_at_once_in_the_on_change_modes(transmission, sent_at_once):
    """On simulated time (the rig's clock, 1 ms per poll): the law's dipole arrives at 50 ms, while
    the loop waits for frames. cyclic: it waits for the next period; on_change and mixed: it is on
    the bus before set_dipole returns. mixed keeps the periodic keep-alive, on_change sends nothing
    else."""
    rig = Rig()
    try:
        sent: list[tuple[float, list[float]]] = []
        loop = CommandLoop(rig.driver, 0.02, transmission=transmission,
                           on_command=lambda counter, dipole, ns: sent.append((rig.clock.t, list(dipole))))
        real_poll = rig.driver.poll
        went_at_once, polls = [], [0]

        def poll(timeout_s=0.0, max_frames=1000, lock=None):
            rig.clock.t += 0.001
            polls[0] += 1
            if polls[0] == 50:                               # the law's new dipole, between two polls
                before = len(sent)
                loop.set_dipole([0.05, 0.0, 0.0])
                went_at_once.append(len(sent) > before and sent[-1] == (rig.clock.t, [0.05, 0.0, 0.0]))
            rig.board.step(rig.clock.t)
            return real_poll(0.0, max_frames, lock)

        rig.driver.poll = poll
        loop.run(duration_s=0.2)
        assert went_at_once == [sent_at_once]
        assert sent[-1][1] == [0.05, 0.0, 0.0]               # whatever the mode, the new dipole went out
        if transmission == "on_change":
            assert len(sent) == 1                            # the change, nothing else
        else:
            assert len(sent) >= 9                            # every 20 ms over 0.2 s
    finally:
        rig.close()


@pytest.mark.parametrize("transmission", ["cyclic", "on_change", "mixed"])
def test_a_law_driven_loop_sends_nothing_before_the_laws_first_dipole(transmission):
    """first_command_by_law: the bus carries no command until the law's first dipole (at 50 ms on
    the rig's simulated clock), so the first command frame, from which bus faults count, is the
    loop's first step; from then on the mode's own timing (keep-alive every 20 ms but on_change)."""
    rig = Rig()
    try:
        sent: list[tuple[float, list[float]]] = []
        loop = CommandLoop(rig.driver, 0.02, transmission=transmission, first_command_by_law=True,
                           on_command=lambda counter, dipole, ns: sent.append((rig.clock.t, list(dipole))))
        real_poll = rig.driver.poll
        polls, law_s = [0], []

        def poll(timeout_s=0.0, max_frames=1000, lock=None):
            rig.clock.t += 0.001
            polls[0] += 1
            if polls[0] == 50:
                law_s.append(rig.clock.t)
                loop.set_dipole([0.05, 0.0, 0.0])
            rig.board.step(rig.clock.t)
            return real_poll(0.0, max_frames, lock)

        rig.driver.poll = poll
        loop.run(duration_s=0.2)
        assert sent, "the law's dipole never went out"
        first_s, first_dipole = sent[0]
        assert first_dipole == [0.05, 0.0, 0.0]
        assert 0 <= first_s - law_s[0] <= 0.0015                # at once or at the next poll
        assert loop.driver.host_overruns == 0                   # waiting for the law is not a late host
        if transmission == "on_change":
            assert len(sent) == 1
        else:
            assert 7 <= len(sent) <= 9                          # every 20 ms over the remaining 150 ms
    finally:
        rig.close()
