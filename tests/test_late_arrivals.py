"""The board check's bound on a frame's age on arrival (bench.contract_check.late_arrivals), on made-up
timelines: a stale refusal the host can explain is excused, one it cannot is the board's."""
import numpy as np
import pytest

from bench.bus.can import protocol as p
from bench.contract_check.board_check import BoardCheck
from bench.contract_check.board_flight import BoardContract, Heard, Sent
from bench.contract_check.board_run import board_scenario
from bench.contract_check.late_arrivals import answered_at_s, explained_emcys, may_have_arrived_stale

WINDOW_S = 0.13        # freshness window: command period 0.1 s + margin 0.03 s


def command(t_s: float, counter: int) -> Sent:
    return Sent(t_s, "command", counter, judged=True)


def echo(t_s: float, counter: int) -> Heard:
    return Heard(t_s, p.TLM_SETPOINT, {"CommandApplied": 1, "CommandCounter": counter}, None, True)


def emcy(t_s: float, status: p.E2EStatus, counter: int) -> Heard:
    return Heard(t_s, p.EMCY, {"ErrorCode": p.EMCY_E2E_CHECK_FAILED, "E2eStatus": int(status),
                               "RejectedCounter": counter}, None, True)


def heartbeat(t_s: float) -> Heard:
    return Heard(t_s, p.HEARTBEAT, {"NmtState": p.NMT_OPERATIONAL}, None, True)


def test_a_command_answered_only_after_the_window_may_have_arrived_stale():
    # Counter 3 held up: its refusal and the next command's echo come 0.2 s after it was sent.
    sent = [command(1.0, 2), command(1.1, 3), command(1.2, 4)]
    heard = [echo(1.001, 2), heartbeat(1.15), emcy(1.30, p.E2EStatus.STALE, 3), echo(1.301, 4)]
    assert answered_at_s(1, sent, heard) == 1.30
    assert may_have_arrived_stale(1, sent, heard, WINDOW_S)


def test_a_stale_refusal_heard_within_the_window_is_the_boards():
    # Refused as stale 5 ms after it was sent: it was fresh when the board had it.
    sent = [command(1.0, 2), command(1.1, 3)]
    heard = [echo(1.001, 2), emcy(1.105, p.E2EStatus.STALE, 3)]
    assert answered_at_s(1, sent, heard) == 1.105
    assert not may_have_arrived_stale(1, sent, heard, WINDOW_S)


def test_a_later_commands_echo_bounds_the_age_as_the_board_takes_frames_in_order():
    sent = [command(1.0, 2), command(1.1, 3), command(1.2, 4)]
    heard = [echo(1.001, 2), echo(1.25, 4)]             # counter 3 not applied, 4 echoed 0.15 s after 3 was sent
    assert answered_at_s(1, sent, heard) == 1.25
    assert may_have_arrived_stale(1, sent, heard, WINDOW_S)
    heard = [echo(1.001, 2), echo(1.202, 4)]            # 4 echoed at once: 3 was had within 0.102 s, fresh
    assert not may_have_arrived_stale(1, sent, heard, WINDOW_S)
    heard = [echo(1.001, 2), echo(1.105, 4)]            # an echo of 4 before 4 was sent does not count
    assert answered_at_s(1, sent, heard) is None
    assert not may_have_arrived_stale(1, sent, heard, WINDOW_S)


def test_an_earlier_commands_late_echo_bounds_nothing():
    sent = [command(1.0, 2), command(1.1, 3)]
    heard = [echo(1.35, 2)]                              # counter 2's echo, heard after 3 was sent
    assert answered_at_s(1, sent, heard) is None


def test_an_nmt_frame_is_named_by_a_refusal_with_counter_zero():
    sent = [command(1.0, 5), Sent(1.05, "nmt")]
    heard = [echo(1.001, 5), emcy(1.25, p.E2EStatus.STALE, 0)]
    assert may_have_arrived_stale(1, sent, heard, WINDOW_S)


def test_the_refusal_and_the_next_commands_loss_report_are_explained_and_nothing_else():
    sent = [command(1.0, 2), command(1.1, 3), command(1.2, 4), command(1.3, 5)]
    own = emcy(1.30, p.E2EStatus.STALE, 3)
    lost = emcy(1.31, p.E2EStatus.OK_SOME_LOST, 4)
    other = emcy(1.40, p.E2EStatus.WRONG_CRC, 5)        # not a consequence of a late frame
    unrelated_stale = emcy(1.41, p.E2EStatus.STALE, 5)  # counter 5 was not excused
    heard = [echo(1.001, 2), own, lost, other, unrelated_stale]
    assert explained_emcys([sent[1]], sent, heard) == [own, lost]
    assert explained_emcys([], sent, heard) == []


class _Recorded:
    """A flight side that only replays what was sent and heard (BoardCheck reads nothing else here)."""
    max_gap_s = 0.02

    def __init__(self, sent, heard):
        self.sent, self.heard = sent, heard

    def frames(self, names=None, after_s=0.0, before_s=float("inf")):
        names = (names,) if isinstance(names, str) else names
        return [h for h in self.heard if after_s <= h.t_s < before_s and (names is None or h.name in names)]


def _judged(sent, heard) -> BoardCheck:
    contract = BoardContract.of(board_scenario(None).can, 0.03, None, real_time_only=False)
    check = BoardCheck(_Recorded(sent, heard), contract, started_by_check=True)
    check._late_commands()
    check._echoes()
    check._unexpected_emcys()
    return check


def _stream(held_counter: int | None, refused_after_s: float):
    """Commands every 20 ms, counters 0..9, each echoed 1 ms later, but `held_counter`: refused as
    stale `refused_after_s` after it was sent, and the next one's echo then says some were lost."""
    sent, heard = [], []
    for k in range(10):
        t = 1.0 + 0.02 * k
        sent.append(Sent(t, "command", k, expected_am2=np.zeros(3), judged=True))
        if k == held_counter:
            heard.append(emcy(t + refused_after_s, p.E2EStatus.STALE, k))
        elif held_counter is not None and k == held_counter + 1:
            heard.append(emcy(max(t, sent[-2].t_s + refused_after_s) + 0.001, p.E2EStatus.OK_SOME_LOST, k))
            heard.append(_echo_of(max(t, sent[-2].t_s + refused_after_s) + 0.002, k))
        else:
            heard.append(_echo_of(t + 0.001, k))
    heard.sort(key=lambda h: h.t_s)
    return sent, heard


def _echo_of(t_s: float, counter: int) -> Heard:
    return Heard(t_s, p.TLM_SETPOINT, {"CommandApplied": 1, "CommandCounter": counter, "SafeState": 0,
                                       **{f"Setpoint{a}": 0.0 for a in p.AXES}}, None, True)


def test_the_check_excuses_a_command_held_past_the_window_and_what_follows_from_it():
    check = _judged(*_stream(held_counter=4, refused_after_s=0.08))
    assert check.problems == []
    assert check.measured["late_on_arrival"]["commands"] == 1
    assert (check.measured["echo"]["commands"], check.measured["echo"]["echoed"]) == (10, 9)


def test_the_check_blames_the_board_for_refusing_a_fresh_command():
    check = _judged(*_stream(held_counter=4, refused_after_s=0.005))
    assert check.measured["late_on_arrival"]["commands"] == 0
    assert any(problem.startswith("set-point echo: 1 of 10 applied commands not acknowledged") for problem in
               check.problems), check.problems
    assert any("EMCY for genuine commands: 0x8100 STALE counter 4, 0x8100 OK_SOME_LOST counter 5" in problem
               for problem in check.problems), check.problems


def setpoint(t_s: float, am2) -> Heard:
    return Heard(t_s, p.TLM_SETPOINT, {f"Setpoint{a}": v for a, v in zip(p.AXES, am2)}, None, True)


def test_a_hold_settles_from_when_the_board_echoed_its_set_point_if_that_came_late():
    contract = BoardContract.of(board_scenario(None).can, 0.03, None, real_time_only=False)
    off, previous = np.zeros(3), np.array([0.1, -0.1, 0.05])
    start, end = 10.0, 10.25
    # The hold's first frames held up on this host: the board echoes the new set-point 60 ms in.
    heard = [setpoint(10.002, previous), setpoint(10.060, off), setpoint(10.080, off)]
    check = BoardCheck(_Recorded([], heard), contract, started_by_check=True)
    assert check.settled_from_s(start, end, off) == pytest.approx(10.060 + contract.settle_s)
    # Echoed at once: settle_s after the hold's start, as without an echo.
    check = BoardCheck(_Recorded([], [setpoint(start, off)]), contract, started_by_check=True)
    assert check.settled_from_s(start, end, off) == pytest.approx(start + contract.settle_s)
    no_echo = BoardContract.of(board_scenario(None).can, 0.03, None, real_time_only=True)
    check = BoardCheck(_Recorded([], heard), no_echo, started_by_check=True)
    assert check.settled_from_s(start, end, off) == pytest.approx(start + no_echo.settle_s)
