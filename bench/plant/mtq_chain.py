"""Each attitude step's stamp chain, joined across the CAN bus to the frame that carried its dipole.

The controller's DipoleCommand for step k carries the chain from sensing to `can_sent`: the
monotonic time the driver put the first frame with the new dipole on the bus, and that frame's
alive counter c. The board stamps `board_received` into its report (MtqApplied) of the frame it
decoded. A chain is only a chain when both halves belong to the same command: the report must be
of frame c (or, when frame c was lost, of a later frame c+1 .. c+7 carrying the same dipole) and
decoded after step k's frame was sent. Pairing step k with "the board's latest report" instead
joins the previous frame's report (8.5 ms before can_sent in a real-time run: negative latencies).
The dipole compared is the command the frame carried (the report's target_dipole_am2 where the
board gives it), not the coils' output: in a magnetometer window the coils are off, and joining on
the output waited for a later frame after the window (every tenth step of attitude_pointing_rt
reported 50-65 ms from sensing to the board for a frame the board had in 2 ms).

The rest of the chain is the plant's: `plant_received` is when the plant received that report
(actuator/mtq), `applied` when it first integrated a step with it. In lock-step the plant waits for
the report, so both fall in step k. In real time the plant integrates step k as soon as command k
is in, usually before the board has the new dipole: the report arrives during the step and is
first applied at a later tick, and the chain says so (`applied` is that later tick's time).
A chain whose report never comes (frames lost, board dead) ends at `can_sent`, with the board's
stages absent (-1), not filled with another frame's stamps.
"""
from __future__ import annotations

from dataclasses import dataclass

import msgspec
import numpy as np

from bench.bus.schemas import DipoleCommand, Header, MtqApplied
from bench.bus.spill import StepColumn
from bench.plant.stepping import StampLog

COUNTER_MODULO = 16
COUNTER_WINDOW = 8        # reports of frames c .. c+7 answer command c (later frames, same dipole)


def report_answers(report: MtqApplied, counter: int, expected_am2: np.ndarray, can_sent_ns: int | None) -> bool:
    """Whether the board's report is of the frame that carried this command (or of a later frame
    with the same dipole) and was decoded after that frame was sent."""
    board_received = report.header.stamps_ns.get("board_received")
    if board_received is None or counter < 0:
        return False     # a coils-changed report (no frame decoded), or a command no frame carried
    if can_sent_ns is not None and board_received < can_sent_ns:
        return False     # an earlier frame with the same counter and dipole
    carried = report.dipole_am2 if report.target_dipole_am2 is None else report.target_dipole_am2
    return ((report.alive_counter - counter) % COUNTER_MODULO < COUNTER_WINDOW
            and np.array_equal(carried, expected_am2))


@dataclass
class _Open:
    step: int
    command: DipoleCommand          # its header holds the chain from sensed to can_sent
    expected_am2: np.ndarray        # the dipole the board reports for this command (quantised)

    @property
    def can_sent_ns(self) -> int | None:
        return self.command.header.stamps_ns.get("can_sent")


class CommandChains:
    """Per step, the stamp chain of the command the step carried, joined to its board report.

    `open` a chain when step k's command is in; `close` chains with the reports received so far at
    each step's integration; `expire` the ones whose frame can no longer be told apart (the alive
    counter has wrapped) and, at the end of the run, all the rest. Every closed chain is recorded in
    `stamps` and returned, as the command with its whole chain in the header, so the plant can
    publish it (command/applied).
    """

    def __init__(self, n_steps: int, expire_after_s: float):
        self.stamps = StampLog(n_steps)
        self.board_counter = StepColumn(n_steps, (), np.int64, -1)   # the frame whose report closed step k
        self.expire_after_ns = int(expire_after_s * 1e9)
        self._open: list[_Open] = []

    def open(self, k: int, command: DipoleCommand, expected_am2: np.ndarray) -> None:
        self._open.append(_Open(k, command, np.asarray(expected_am2, float)))

    def close(self, reports: list[tuple[int, MtqApplied]], applied_ns: int) -> list[tuple[int, DipoleCommand]]:
        """Close every open chain answered by one of `reports` [(plant received ns, report)], the
        earliest answer first; `applied_ns` is when the plant integrates with what it holds now."""
        closed, still_open = [], []
        for chain in self._open:
            answer = next(((received_ns, report) for received_ns, report in reports
                           if received_ns <= applied_ns
                           and report_answers(report, chain.command.alive_counter, chain.expected_am2,
                                              chain.can_sent_ns)), None)
            if answer is None:
                still_open.append(chain)
                continue
            received_ns, report = answer
            header = (chain.command.header.stamped("board_received", report.header.stamps_ns["board_received"])
                      .stamped("plant_received", received_ns).stamped("applied", applied_ns))
            self.board_counter[chain.step] = report.alive_counter
            closed.append(self._record(chain.step, chain.command, header))
        self._open = still_open
        return closed

    def expire(self, now_ns: int | None = None) -> list[tuple[int, DipoleCommand]]:
        """Chains left open past the counter wrap (or all, with now_ns None): recorded without the
        board's stages."""
        expired, still_open = [], []
        for chain in self._open:
            stamps = chain.command.header.stamps_ns
            sent_ns = chain.can_sent_ns if chain.can_sent_ns is not None else stamps.get("commanded", 0)
            if now_ns is None or now_ns - sent_ns > self.expire_after_ns:
                expired.append(self._record(chain.step, chain.command, chain.command.header))
            else:
                still_open.append(chain)
        self._open = still_open
        return expired

    def record_direct(self, k: int, command: DipoleCommand, received_ns: int, applied_ns: int) -> tuple[int, DipoleCommand]:
        """A step without the bus (in-process board model): the plant's own stages complete it."""
        header = command.header.stamped("plant_received", received_ns).stamped("applied", applied_ns)
        return self._record(k, command, header)

    def _record(self, k: int, command: DipoleCommand, header: Header) -> tuple[int, DipoleCommand]:
        self.stamps.record(k, header.stamps_ns)
        return k, msgspec.structs.replace(command, header=header)
