"""The plant's join of each step's command to the board's report of the frame that carried it
(bench/plant/mtq_chain.py), in a magnetometer window: the coils are off (the report's output dipole
is zero) but the frame reached the board, and its chain says when."""
import numpy as np

from bench.bus.schemas import DipoleCommand, MtqApplied, header
from bench.plant.mtq_chain import CommandChains

MS = 1_000_000
DIPOLE_AM2 = [0.01, -0.002, 0.0005]
CAN_SENT_NS = 100 * MS


def command(counter: int = 6) -> DipoleCommand:
    return DipoleCommand(header("r", 10, 1.0, sensed=CAN_SENT_NS - 4 * MS, commanded=CAN_SENT_NS - MS,
                                can_sent=CAN_SENT_NS), DIPOLE_AM2, alive_counter=counter, law="pd")


def report(counter: int, received_ns: int, paused: bool, target=DIPOLE_AM2, say_target: bool = True) -> MtqApplied:
    return MtqApplied(header("r", counter, 0.0, board_received=received_ns, applied=received_ns + 50_000),
                      dipole_am2=[0.0, 0.0, 0.0] if paused else list(target), coil_current_a=[0.0] * 3,
                      safe_state=False, actuation_paused=paused, alive_counter=counter,
                      target_dipole_am2=list(target) if say_target else None)


def close_with(reports: list[MtqApplied], counter: int = 6) -> CommandChains:
    chains = CommandChains(1, expire_after_s=1.0)
    chains.open(0, command(counter), np.array(DIPOLE_AM2))
    # the plant receives each report 0.5 ms after the board decoded its frame and integrates later
    chains.close([(r.header.stamps_ns["board_received"] + MS // 2, r) for r in reports],
                 applied_ns=CAN_SENT_NS + 90 * MS)
    return chains


def board_received(chains: CommandChains) -> int:
    return int(chains.stamps.stamps["board_received"][0])


def test_a_paused_report_of_the_frame_closes_its_chain_at_that_frames_decode():
    # frame 6 decoded 2 ms after it was sent, the coils off for the window; frame 11 after the window
    chains = close_with([report(6, CAN_SENT_NS + 2 * MS, paused=True), report(11, CAN_SENT_NS + 55 * MS, paused=False)])
    assert board_received(chains) == CAN_SENT_NS + 2 * MS
    assert chains.board_counter[0] == 6


def test_without_the_target_a_paused_report_cannot_be_told_apart_and_the_next_applied_frame_answers():
    # an external board's telemetry says only what the coils do: the old join, on the output
    chains = close_with([report(6, CAN_SENT_NS + 2 * MS, paused=True, say_target=False),
                         report(11, CAN_SENT_NS + 55 * MS, paused=False, say_target=False)])
    assert board_received(chains) == CAN_SENT_NS + 55 * MS and chains.board_counter[0] == 11


def test_a_report_of_another_dipole_or_from_before_the_send_does_not_answer():
    other = [0.02, 0.0, 0.0]
    chains = close_with([report(6, CAN_SENT_NS - MS, paused=True),              # the counter's previous use
                         report(7, CAN_SENT_NS + 12 * MS, paused=True, target=other),
                         report(8, CAN_SENT_NS + 22 * MS, paused=False, target=other)])
    assert chains.board_counter[0] == -1 and len(chains.expire()) == 1, "no report answered: the chain stays open"
