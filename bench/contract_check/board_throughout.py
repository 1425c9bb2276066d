"""The board check's record and what it judges over the whole run rather than in one step.

The record: the problems found, the numbers measured, the windows in which the steps expect EMCYs
or no set-point echo, the genuine frames this host may have delivered stale, and the check's own
stalls. The judgements over the whole run: the heartbeat period and its longest gap, the telemetry
period and its longest gap (a gap excused where this host held the board up for as long as it is
over: bench/contract_check/host_stalls.py), the E2E check of every protected frame the board sends,
each applied command's set-point echo, the commands excused as late on arrival
(bench/contract_check/late_arrivals.py), and no EMCY for a genuine command.
The steps themselves are bench/contract_check/board_check.py.
"""
from __future__ import annotations

import subprocess
from dataclasses import dataclass, field

import numpy as np

from bench.bus.can import protocol as p
from bench.bus.can.host_lateness import HostLate
from bench.contract_check.board_flight import (PROTECTED, BoardContract, FlightSide, Heard, Sent, echoed_am2, fmt, ms,
                                         state_name)
from bench.contract_check.check import OUTSIDE_LOG
from bench.contract_check.host_stalls import StallWatch, held_up_s, silence_s
from bench.contract_check.late_arrivals import explained_emcys, may_have_arrived_stale

LATE_SHARE_LIMIT = 0.1        # more genuine commands than this share late on arrival: the host is too busy to judge


@dataclass
class CheckRecord:
    """What the check found and measured, and the judgements over the whole run (BoardCheck's
    steps fill the windows and the late frames these read)."""
    flight: FlightSide
    contract: BoardContract
    started_by_check: bool
    process: subprocess.Popen | None = None
    log_path: str = OUTSIDE_LOG          # where the board's command writes its output
    problems: list[str] = field(default_factory=list)
    measured: dict = field(default_factory=dict)
    probe_windows: list[tuple[float, float]] = field(default_factory=list)   # EMCYs expected in these
    timeout_windows: list[tuple[float, float]] = field(default_factory=list)  # the command timeout's attempts'
    echo_free: list[tuple[float, float]] = field(default_factory=list)      # no echo expected here
    late: list[Sent] = field(default_factory=list)   # genuine frames this host may have delivered stale
    stalls: StallWatch | None = None                 # the check's own stalls (None: not watched)

    def problem(self, text: str) -> None:
        self.problems.append(text)

    def held_up(self, from_s: float, to_s: float) -> str | None:
        """What says this host held the board or the check up within [from_s, to_s]: the board's
        frames silent for longer than a telemetry period and the margin, or a stall of the check's;
        None: nothing."""
        c = self.contract
        silent = silence_s([h.t_s for h in self.flight.frames(None, from_s, to_s)], from_s, to_s)
        if silent > c.telemetry_period_s + c.margin_s:
            return f"the board silent for {ms(silent)}"
        stalled = self.stalls.longest_s(from_s, to_s) if self.stalls is not None else 0.0
        return f"the check held up {ms(stalled)}" if stalled else None

    # --- over the whole check ----------------------------------------------------------------
    def throughout(self, host_records: list[HostLate] = ()) -> None:
        """host_records: what says when this host held the board up (host_stalls.board_records);
        a gap they explain is excused and counted."""
        c, f = self.contract, self.flight
        if f.stamped_on_arrival and self.stalls is not None:   # the check's own stalls show in these frames' times
            host_records = [*host_records, *self.stalls.records()]
        self._late_commands()
        beats = f.frames(p.HEARTBEAT)
        pairs = [(a.t_s, b.t_s) for a, b in zip(beats, beats[1:]) if b.signals["NmtState"] != p.NMT_BOOT_UP]
        gaps = [b - a for a, b in pairs]
        hb = {"count": len(beats), "states": [state_name(s) for s in _runs(int(b.signals["NmtState"]) for b in beats)]}
        self.measured["heartbeat"] = hb
        if gaps:
            median, longest = float(np.median(gaps)), float(max(gaps))
            hb.update(period_median_s=round(median, 5), period_max_s=round(longest, 5),
                      contract_period_s=c.heartbeat_period_s, consumer_timeout_s=round(c.heartbeat_timeout_s, 5))
            if abs(median - c.heartbeat_period_s) > 0.1 * c.heartbeat_period_s:
                self.problem(f"heartbeat: period {ms(median)} (median of {len(gaps)}), the contract's "
                             f"{ms(c.heartbeat_period_s)} (within 10 %)")
            longest = self._longest_unexcused("heartbeat", pairs, c.heartbeat_timeout_s, host_records)
            if longest > c.heartbeat_timeout_s:
                self.problem(f"heartbeat: a gap of {ms(longest)}, longer than the flight side's consumer time "
                             f"{ms(c.heartbeat_timeout_s)}: the board was lost")
        tlm = f.frames(p.TLM_DIPOLE)
        nmt_sent = [s.t_s for s in f.sent if s.kind in ("nmt", "plain-nmt-stop")]
        op_pairs = [(a.t_s, b.t_s) for a, b in zip(tlm, tlm[1:]) if f.state_at(a.t_s) == p.NMT_OPERATIONAL
                    and not any(a.t_s <= t < b.t_s for t in nmt_sent)]
        op = [b - a for a, b in op_pairs]
        if op:
            median = float(np.median(op))
            self.measured["telemetry"] = {"period_median_s": round(median, 5), "period_max_s": round(max(op), 5),
                                          "contract_period_s": c.telemetry_period_s, "frames": len(tlm)}
            if abs(median - c.telemetry_period_s) > 0.1 * c.telemetry_period_s:
                self.problem(f"telemetry: period {ms(median)} (median), the contract's {ms(c.telemetry_period_s)}")
            longest = self._longest_unexcused("telemetry", op_pairs, c.telemetry_timeout_s, host_records)
            if longest > c.telemetry_timeout_s:
                self.problem(f"telemetry: a gap of {ms(longest)} while operational, over the flight side's "
                             f"{ms(c.telemetry_timeout_s)}")
        self._e2e_of_board_frames()
        self._echoes()
        self._unexpected_emcys()

    def _longest_unexcused(self, what: str, pairs: list[tuple[float, float]], allowed_s: float,
                           host_records: list[HostLate]) -> float:
        """The longest gap between frames (a, b) in pairs that host_records do not explain: a gap
        over allowed_s is excused if the host held the board up for as long as it is over, and
        recorded in measured["held_up_by_host"]."""
        longest = 0.0
        for a, b in pairs:
            if b - a > allowed_s:
                held = held_up_s(host_records, a, b)
                if b - a - held <= allowed_s:
                    self.measured.setdefault("held_up_by_host", []).append(
                        {"gap": what, "at_s": round(a, 4), "gap_s": round(b - a, 5), "host_held_s": round(held, 5)})
                    continue
            longest = max(longest, b - a)
        return longest

    def _late_commands(self) -> None:
        """Genuine commands the board did not apply (no echo) or refused as stale, that this host
        may have delivered past the freshness window: excused, counted, and too many of them is a
        problem of its own (the check cannot judge the board on a host this busy)."""
        c, f = self.contract, self.flight
        if c.profile != "secoc":
            return
        heard = f.frames()
        answers: dict[str, dict[int, list[float]]] = {"echo": {}, "stale": {}}   # counter -> times heard
        for h in heard:
            if h.name == p.TLM_SETPOINT and h.signals["CommandApplied"]:
                answers["echo"].setdefault(int(h.signals["CommandCounter"]), []).append(h.t_s)
            elif (h.name == p.EMCY and h.signals["ErrorCode"] == p.EMCY_E2E_CHECK_FAILED
                  and h.signals["E2eStatus"] == p.E2EStatus.STALE):
                answers["stale"].setdefault(int(h.signals["RejectedCounter"]), []).append(h.t_s)
        judged = [(i, s) for i, s in enumerate(f.sent) if s.judged]
        for i, s in judged:
            later = next((t.t_s for t in f.sent[i + 1:] if t.counter == s.counter), float("inf"))
            named = {kind: any(s.t_s < t < later for t in times.get(s.counter, ())) for kind, times in answers.items()}
            if ((named["stale"] or (c.setpoint_echo and not named["echo"]))
                    and may_have_arrived_stale(i, f.sent, heard, c.freshness_max_age_s)):
                self.late.append(s)
        commands = [s for s in self.late if s.kind == "command"]
        self.measured["late_on_arrival"] = {"commands": len(commands), "nmt": len(self.late) - len(commands),
                                            "freshness_window_s": c.freshness_max_age_s}
        if len(commands) > LATE_SHARE_LIMIT * max(1, len(judged)):
            self.problem(f"this host held {len(commands)} of {len(judged)} commands past the freshness window "
                         f"({ms(c.freshness_max_age_s)}) before the board had them: too many to judge the board; "
                         f"run the check on a less loaded host")

    def _e2e_of_board_frames(self) -> None:
        f = self.flight
        receivers = {name: p.E2EReceiver() for name in PROTECTED}
        bad: dict[str, int] = {}
        for h in f.frames((*PROTECTED, p.HEARTBEAT)):
            if h.name == p.HEARTBEAT:
                if h.signals["NmtState"] == p.NMT_BOOT_UP:     # a booted node counts from zero again
                    for r in receivers.values():
                        r.reset()
                continue
            status = receivers[h.name].check(h.counter, h.crc_ok)
            if status in (p.E2EStatus.WRONG_CRC, p.E2EStatus.REPEATED):
                bad[f"{h.name} {status.name}"] = bad.get(f"{h.name} {status.name}", 0) + 1
        self.measured["board_frames_e2e"] = bad
        if bad:
            self.problem("E2E of the board's frames: " + ", ".join(f"{k} x{n}" for k, n in sorted(bad.items()))
                         + " (CRC-8 0x2F over bytes 1-7 and the data id, counter +1 per frame: mtq.dbc)")

    def _echoes(self) -> None:
        c, f = self.contract, self.flight
        if not c.setpoint_echo:
            self.measured["echo"] = "not checked (--real-time-only)"
            return
        judged = [s for s in f.sent if s.judged]
        echoes = [h for h in f.frames(p.TLM_SETPOINT) if h.signals["CommandApplied"]]
        latencies, missing, wrong = [], [], []
        late = {id(s) for s in self.late}
        for i, s in enumerate(f.sent):
            if not s.judged or id(s) in late:
                continue
            later = next((t.t_s for t in f.sent[i + 1:] if t.counter == s.counter), float("inf"))
            echo = next((h for h in echoes if s.t_s <= h.t_s < later and h.signals["CommandCounter"] == s.counter),
                        None)
            if echo is None:
                missing.append(s)
                continue
            latencies.append(echo.t_s - s.t_s)
            if np.max(np.abs(echoed_am2(echo) - s.expected_am2)) > 0.5e-4 or echo.signals["SafeState"]:
                wrong.append((s, echo))
        result = {"commands": len(judged), "echoed": len(latencies)}
        if latencies:
            result.update(latency_p50_s=round(float(np.median(latencies)), 6), latency_max_s=round(max(latencies), 6))
        self.measured["echo"] = result
        if not echoes:
            self.problem(f"set-point echo: no MTQ_TLM_SETPOINT with CommandApplied 1 for {len(judged)} applied commands "
                         f"(lock-step pairs each step's command with it: a board without it runs in real time only; "
                         f"--real-time-only to check it so)")
            return
        if missing:
            self.problem(f"set-point echo: {len(missing)} of {len(judged)} applied commands not acknowledged with their "
                         f"alive counter (first: counter {missing[0].counter})")
        if wrong:
            s, e = wrong[0]
            self.problem(f"set-point echo: {len(wrong)} echo(es) with a set-point other than the command's (first: counter "
                         f"{s.counter}: {fmt(echoed_am2(e))}, the contract's {fmt(s.expected_am2)})")
        slow = [x for x in latencies if x > c.command_timeout_s]
        if slow:
            self.problem(f"set-point echo: {len(slow)} echo(es) later than the command timeout ({ms(c.command_timeout_s)}) "
                         f"after their command, worst {ms(max(slow))} (it must follow the command it acknowledges)")
        stray = [h for a, b in self.echo_free for h in f.frames(p.TLM_SETPOINT, a, b)]
        if stray:
            self.problem(f"set-point echo: {len(stray)} echo(es) while not operational")

    def _timed_out_rightly(self, h: Heard) -> bool:
        """A command-timeout EMCY (0x8250) outside the steps that expect one is the board doing its
        job if it had no command for the command timeout before it: this host held the check's
        commands up (or delivered them late). Judged from the board's own last echo of an applied
        command (the check's last genuine command without the echo); recorded as held up by this host."""
        c, f = self.contract, self.flight
        if h.signals["ErrorCode"] != p.EMCY_COMMAND_TIMEOUT:
            return False
        if c.setpoint_echo:
            last_s = _last_before([e.t_s for e in f.frames(p.TLM_SETPOINT) if e.signals["CommandApplied"]], h.t_s)
        else:
            last_s = _last_before([s.t_s for s in f.sent if s.kind == "command"], h.t_s)
        if last_s is None or h.t_s - last_s < c.command_timeout_s - 0.002:
            return False
        self.measured.setdefault("held_up_by_host", []).append(
            {"gap": "command", "at_s": round(last_s, 4), "gap_s": round(h.t_s - last_s, 5), "host_held_s": None})
        return True

    def _unexpected_emcys(self) -> None:
        c, f = self.contract, self.flight
        windows = list(self.probe_windows)
        windows += self.timeout_windows
        explained = {id(h) for h in explained_emcys(self.late, f.sent, f.frames())}
        odd = [h for h in f.frames(p.EMCY)
               if h.signals["ErrorCode"] != p.EMCY_NO_ERROR and not any(a <= h.t_s < b for a, b in windows)
               and id(h) not in explained and not self._timed_out_rightly(h)]
        self.measured["unexpected_emcys"] = [emcy_words(h) for h in odd]
        self.measured["check_max_command_gap_s"] = round(f.max_gap_s, 5)
        if odd:
            host = (f" (the check itself once went {ms(f.max_gap_s)} without a command: this host held it up)"
                    if f.max_gap_s > c.freshness_max_age_s else "")
            self.problem(f"EMCY for genuine commands: {', '.join(emcy_words(h) for h in odd[:5])}"
                         f"{' ...' if len(odd) > 5 else ''}{host}")


def _last_before(times_s: list[float], t_s: float) -> float | None:
    return max((x for x in times_s if x < t_s), default=None)


def emcy_words(h: Heard) -> str:
    code, status = int(h.signals["ErrorCode"]), int(h.signals["E2eStatus"])
    name = p.E2EStatus(status).name if status in p.E2EStatus._value2member_map_ else str(status)
    return f"0x{code:04X}" + (f" {name} counter {int(h.signals['RejectedCounter'])}" if code == p.EMCY_E2E_CHECK_FAILED else "")


def _runs(values):
    out = []
    for v in values:
        if not out or out[-1] != v:
            out.append(v)
    return out

