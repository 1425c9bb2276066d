"""The board check tells this host's stalls from the board's faults (bench.contract_check.host_stalls):
frames timed on the wire, the check's own stalls watched, gaps the board's own lateness records
explain excused, and nothing excused that no record explains."""
import sys
import time

import can
import pytest

from bench.bus.can import protocol as p
from bench.bus.can.host_lateness import HostLate
from bench.bus.can.wire_time import WireClock
from bench.contract_check.board_check import BoardCheck
from bench.contract_check.board_flight import BoardContract, Heard
from bench.contract_check.board_run import board_scenario
from bench.contract_check.host_stalls import StallWatch, held_up_s, silence_s


def _contract() -> BoardContract:
    return BoardContract.of(board_scenario(None).can, 0.03, None, real_time_only=False)


class _Recorded:
    """A flight side that only replays what it heard."""
    sent: list = []
    max_gap_s = 0.0

    def __init__(self, heard):
        self.heard = heard

    def frames(self, names=None, after_s=0.0, before_s=float("inf")):
        names = (names,) if isinstance(names, str) else names
        return [h for h in self.heard if after_s <= h.t_s < before_s and (names is None or h.name in names)]


def _telemetry(times_s) -> list[Heard]:
    return [Heard(t, p.TLM_DIPOLE, {"SafeState": 0}, None, True) for t in times_s]


def test_silence_is_the_longest_stretch_without_a_frame_window_edges_included():
    assert silence_s([1.05, 1.10, 1.30], 1.0, 1.35) == pytest.approx(0.20)
    assert silence_s([], 1.0, 1.35) == pytest.approx(0.35)
    assert silence_s([0.5, 2.0], 1.0, 1.35) == pytest.approx(0.35)     # frames outside the window count for nothing


def test_a_timed_step_is_held_up_only_when_the_board_fell_silent_or_the_check_stalled():
    c = _contract()
    steady = _telemetry([10.0 + k * c.telemetry_period_s for k in range(8)])
    check = BoardCheck(_Recorded(steady), c, started_by_check=True)
    assert check.held_up(10.0, 10.3) is None                   # late but still sending: the board's own fault
    frozen = [h for h in steady if not 10.06 < h.t_s < 10.26]  # 0.2 s without a frame
    check = BoardCheck(_Recorded(frozen), c, started_by_check=True)
    assert check.held_up(10.0, 10.3).startswith("the board silent for 2")


@pytest.mark.parametrize("board_held_s, excused", [(0.19, True), (0.0, False), (0.03, False)])
def test_a_gap_is_excused_only_for_as_long_as_the_host_held_the_board(board_held_s, excused):
    c = _contract()
    gap = (10.0, 10.0 + c.telemetry_timeout_s + 0.05)     # 50 ms over the flight side's allowance
    records = [HostLate("board", round(gap[1] * 1e9), board_held_s)] if board_held_s else []
    check = BoardCheck(_Recorded([]), c, started_by_check=True)
    longest = check._longest_unexcused("telemetry", [(9.95, 10.0), gap], c.telemetry_timeout_s, records)
    assert (longest == pytest.approx(0.05)) is excused
    assert bool(check.measured.get("held_up_by_host")) is excused
    if excused:
        assert check.measured["held_up_by_host"][0]["host_held_s"] == pytest.approx(board_held_s)


def test_held_up_counts_one_hold_once_and_only_within_the_window():
    records = [HostLate("board", 2_000_000_000, 0.5), HostLate("check", 2_000_000_000, 0.3)]   # held 1.5-2.0 s
    assert held_up_s(records, 1.8, 2.5) == pytest.approx(0.2)
    assert held_up_s(records, 0.0, 1.4) == 0.0


def test_frames_are_timed_on_the_wire_unless_their_stamp_is_another_clocks():
    clock = WireClock()
    arrival_ns = time.monotonic_ns()
    wall_s = (arrival_ns + clock.wall_minus_monotonic_ns) / 1e9
    queued = can.Message(timestamp=wall_s - 0.030, arbitration_id=0x190, data=bytes(8))
    assert (arrival_ns - clock.sent_ns(queued, arrival_ns)) / 1e6 == pytest.approx(30.0, abs=0.01)
    for other_clock_s in (5.0, wall_s + 1.0, 0.0):            # an adapter's counter, a future stamp, none
        msg = can.Message(timestamp=other_clock_s, arbitration_id=0x190, data=bytes(8))
        assert clock.sent_ns(msg, arrival_ns) == arrival_ns


def test_the_stall_watch_notes_a_stretch_its_process_did_not_run_it():
    watch = StallWatch()
    interval = sys.getswitchinterval()
    try:
        time.sleep(0.05)
        before = watch.log.host_overruns
        sys.setswitchinterval(0.5)        # this thread keeps the GIL: the watch's thread does not run
        start_s = time.monotonic()
        while time.monotonic() - start_s < 0.15:
            pass
    finally:
        sys.setswitchinterval(interval)
    time.sleep(0.05)
    watch.close()
    assert watch.log.host_overruns > before
    assert watch.longest_s(start_s, start_s + 0.2) >= 0.1
