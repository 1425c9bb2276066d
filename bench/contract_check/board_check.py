"""`bench contract check board`: accept a magnetorquer board from outside, on its CAN bus, as a
flight-software team accepts a board another team delivers.

The check is the flight side on the board's channel and nothing else: it sends the frames of
mtq.dbc (through bench.bus.can.protocol, i.e. cantools and the DBC, with the E2E CRC and alive
counter, and on the `secoc` profile the freshness value and CMAC under the board's key), listens
to what the board sends, and judges it against the contract's numbers: the board configuration of
the scenario (`[can.board]`, `[can.driver]`, `[can.security]`; the bench's defaults unless a
scenario is given). The board is the bench's own (`bench node mtq`), started by `--command` and
connected to the hub the check opens, or a user's, started by `--command` or already running, on a
python-can channel the user names.

In order, each step measured on the check's clock (CLOCK_MONOTONIC, the SecOC time base too):
1. boot: the boot-up message (CiA 301: a heartbeat carrying state 0) at start, then heartbeats in
   pre-operational; no telemetry while pre-operational; a command sent then is not applied.
2. NMT start (MTQ_NMT_AUTH on secoc, plain NMT on e2e) takes it to operational: the next heartbeat
   says so, telemetry starts, the coils off (the pre-operational command was not applied).
3. commands applied, one every command period, held in turn: a dipole, one between DAC steps
   (quantised), one beyond the limit (saturated, the Saturated flag), one with Mode off (zero), a
   steady one: the telemetry's applied dipole within tolerance, the set-point echo exact.
4. refusals, while the steady dipole goes on: a command with a wrong CRC (an authentic MAC over
   it on secoc), one repeating the last alive counter, and on secoc one with a wrong MAC, one with
   an old freshness value, a plain MTQ_CMD and a plain NMT stop; each carries another dipole, and
   is judged refused if the coils do not move (echo, telemetry, heartbeat) and an EMCY 0x8100 with
   its E2E status comes.
5. command timeout: the check stops sending; the command-timeout EMCY (0x8250) within the timeout
   plus the margin, the telemetry's coils off, the echo of the safe state; then commands again:
   the error-reset EMCY (0x0000).
6. NMT enter pre-operational and stop: the heartbeat says so, telemetry stops (only heartbeats
   while stopped), and after the next NMT start the coils are off; NMT reset node: boot-up again.
Throughout: the heartbeat period (median) and its longest gap, the telemetry period, the E2E
check of every protected frame the board sends, each applied command acknowledged by
MTQ_TLM_SETPOINT with its alive counter (what lock-step pairs by; `--real-time-only` for a board
without it), and no EMCY for a genuine command. On secoc a genuine frame the board refused as
stale is the board's fault only if its refusal (or the next answer) came back within the freshness
window; later than that, this host may have held it up (bench/contract_check/late_arrivals.py): the
frame is excused and counted (an NMT frame is sent again), and more than a tenth of the commands
so excused is a problem of its own (the host too busy to judge).
Frames are timed on the wire, and a command timeout or a refusal that fails while this host held
the board or the check up is repeated; a heartbeat or telemetry gap the board's own lateness record
explains is excused (bench/contract_check/host_stalls.py).

Here are the steps; the contract and the flight side are bench/contract_check/board_flight.py, the
judgements over the whole run bench/contract_check/board_throughout.py, the command and the verdict
bench/contract_check/board_run.py.
"""
from __future__ import annotations

import time

import numpy as np

from bench.bus.can import protocol as p
from bench.contract_check.board_flight import (PROTECTED, Heard, Sent, applied_am2, echoed_am2, fmt, ms, sleep_until,
                                         state_name)
from bench.contract_check.board_throughout import CheckRecord, emcy_words
from bench.contract_check.late_arrivals import may_have_arrived_stale

HOLD_S = 0.25                 # each commanded dipole is held this long
PROBE_LEAD_S = 0.1            # steady commands before each refused frame
LATE_NMT_RETRIES = 2          # an NMT frame refused only because this host delivered it stale: sent again
HELD_UP_RETRIES = 2           # a timed step that failed while this host held the board or the check up: repeated


# --- the check ----------------------------------------------------------------------------------
class BoardCheck(CheckRecord):
    """The check's steps, in order (the module's docstring); the record and the judgements over
    the whole run are CheckRecord's."""

    # --- steps ---------------------------------------------------------------------------
    def run(self, startup_timeout_s: float, t_started_s: float) -> bool:
        """The steps; whether they all ran (the judgements over the whole run, `throughout`, then
        follow once the board has stopped and said how late its host held it)."""
        if not self.boot(startup_timeout_s, t_started_s):
            return False
        if not self.start_operational("NMT start"):
            return False
        self.commands()
        self.refusals()
        self.command_timeout()
        self.nmt_states()
        self.reset_node()
        return True

    def boot(self, startup_timeout_s: float, t_started_s: float) -> bool:
        c, f = self.contract, self.flight
        first = None
        deadline = time.monotonic() + startup_timeout_s
        while first is None and time.monotonic() < deadline:
            first = f.wait_for(p.HEARTBEAT, t_started_s, min(deadline, time.monotonic() + 0.2) - t_started_s)
            if first is None and self.process is not None and self.process.poll() is not None:
                self.problem(f"the board's command exited with code {self.process.returncode} before its first "
                             f"heartbeat (its output: {self.log_path})")
                return False
        if first is None:
            self.problem(f"no heartbeat from the board (node id {c.node_id:#04x}, MTQ_HEARTBEAT "
                         f"{f.protocol.frame_ids[p.HEARTBEAT]:#05x}) within {startup_timeout_s:g} s")
            return False
        state = int(first.signals["NmtState"])
        boot = {"first_heartbeat_state": state_name(state), "first_heartbeat_after_s": round(first.t_s - t_started_s, 3)}
        self.measured["boot"] = boot
        booted_s = first.t_s
        if state != p.NMT_BOOT_UP:
            if self.started_by_check:
                self.problem(f"boot-up: no boot-up message at start (CiA 301: a heartbeat with state 0 first); the "
                             f"first heartbeat said {state_name(state)}")
            if state != p.NMT_PRE_OPERATIONAL:        # already running: boot it to a known state
                boot["reset_node_at_start"] = True
                if not self.reset_node(at_start=True):
                    return False
                booted_s = time.monotonic()      # after its pre-operational heartbeat: frames from before are gone
        after = f.frames(p.HEARTBEAT)[-1].t_s
        # Pre-operational, as it comes up: heartbeats only, and a command is not applied.
        sleep_until(after + 0.5 * c.heartbeat_period_s)
        f.command([0.5 * c.max_dipole_am2] * 3, judged=False, kind="pre-operational command")
        sleep_until(after + 4.5 * c.heartbeat_period_s)
        states = [int(h.signals["NmtState"]) for h in f.frames(p.HEARTBEAT, after + 1e-9)]
        wrong = sorted({state_name(s) for s in states if s != p.NMT_PRE_OPERATIONAL})
        if wrong:
            self.problem(f"boot: heartbeats said {', '.join(wrong)} before any NMT command (CiA 301: pre-operational "
                         f"after boot-up)")
        early = f.frames(PROTECTED, booted_s)
        if early:
            self.problem(f"boot: {len(early)} telemetry frame(s) while pre-operational ({early[0].name} first; "
                         f"PDOs only when operational)")
        boot["pre_operational_heartbeats"] = len(states)
        return True

    def start_operational(self, what: str) -> bool:
        """NMT start; the heartbeat says operational, telemetry starts, coils off. False if it did not."""
        c, f = self.contract, self.flight
        sent, beat = self.nmt(p.NMT_START, p.NMT_OPERATIONAL, 3 * c.heartbeat_period_s + c.margin_s)
        bound = c.heartbeat_period_s + c.margin_s
        tlm = f.wait_for(p.TLM_DIPOLE, sent.t_s, c.telemetry_period_s + c.margin_s + c.heartbeat_period_s)
        entry = {"operational_heartbeat_after_s": _after(beat, sent), "first_telemetry_after_s": _after(tlm, sent)}
        self.measured.setdefault("nmt", {}).setdefault(what, []).append(entry)
        if beat is None:
            self.problem(f"{what}: no heartbeat saying operational within {ms(3 * c.heartbeat_period_s + c.margin_s)} "
                         f"(it said {state_name(f.state_at(time.monotonic()))})")
            return False
        if beat.t_s - sent.t_s > bound:
            self.problem(f"{what}: operational heartbeat {ms(beat.t_s - sent.t_s)} after the NMT start, over one "
                         f"heartbeat period + margin ({ms(bound)})")
        if tlm is None:
            self.problem(f"{what}: no telemetry (MTQ_TLM_DIPOLE) within {ms(c.telemetry_period_s + c.margin_s)} of "
                         f"becoming operational")
        elif not tlm.signals["SafeState"] or np.max(np.abs(applied_am2(tlm))) > c.dipole_tolerance_am2:
            self.problem(f"{what}: coils not off when it became operational (SafeState {tlm.signals['SafeState']}, "
                         f"applied {fmt(applied_am2(tlm))} A m^2): a command it had while not operational was applied "
                         f"or kept")
        return True

    def commands(self) -> None:
        """Dipoles held in turn; the telemetry follows within tolerance, the echo is exact."""
        c, f = self.contract, self.flight
        m, r = c.max_dipole_am2, c.dipole_resolution_am2
        holds = [
            ("dipole", [0.5 * m, -0.25 * m, 0.1 * m], p.MODE_DIPOLE),
            ("quantised", [r * (round(0.2 * m / r) + 0.4), -r * (round(0.4 * m / r) + 0.3), r * 3.4], p.MODE_DIPOLE),
            ("saturated", [1.75 * m, -2.5 * m, 0.5 * m], p.MODE_DIPOLE),
            ("mode off", [0.5 * m, 0.5 * m, 0.5 * m], p.MODE_OFF),
            ("steady", STEADY(m), p.MODE_DIPOLE),
        ]
        results = []
        for name, dipole, mode in holds:
            start = time.monotonic()
            f.command_for(HOLD_S, dipole, mode)
            end = time.monotonic()
            sent = [s for s in f.sent if s.kind == "command" and start <= s.t_s < end]
            expected, saturated = sent[-1].expected_am2, sent[-1].saturated
            settled = f.frames(p.TLM_DIPOLE, self.settled_from_s(start, end, expected), end)
            result = {"hold": name, "commanded_am2": [float(x) for x in dipole], "mode": mode,
                      "expected_am2": expected.tolist(), "expected_saturated": saturated, "telemetry_frames": len(settled)}
            results.append(result)
            if not settled:
                self.problem(f"commands: no telemetry while the {name} hold was settled (MTQ_TLM_DIPOLE every "
                             f"{ms(c.telemetry_period_s)})")
                continue
            worst = max(settled, key=lambda h: np.max(np.abs(applied_am2(h) - expected)))
            error = float(np.max(np.abs(applied_am2(worst) - expected)))
            result["applied_am2"] = applied_am2(worst).round(6).tolist()
            result["max_error_am2"] = round(error, 6)
            flags = {bool(h.signals["Saturated"]) for h in settled}
            result["saturated_flag"] = sorted(flags)
            if error > c.dipole_tolerance_am2:
                self.problem(f"commands: {name} {fmt(dipole)} A m^2: telemetry applied {fmt(applied_am2(worst))}, the "
                             f"contract's {fmt(expected)} (quantised to {r:g}, saturated at {m:g}; tolerance "
                             f"{c.dipole_tolerance_am2:g} A m^2)")
            if flags != {saturated}:
                self.problem(f"commands: {name}: telemetry Saturated {'/'.join(str(int(x)) for x in sorted(flags))}, "
                             f"the contract's {int(saturated)}")
            if any(h.signals["SafeState"] or h.signals["CommandTimeout"] for h in settled):
                self.problem(f"commands: {name}: telemetry said safe state or command timeout while commanded every "
                             f"{ms(c.command_period_s)}")
            if c.setpoint_echo:
                echoes = f.frames(p.TLM_SETPOINT, start + c.settle_s, end)
                if echoes:
                    last = echoes[-1]
                    result["echo_am2"] = echoed_am2(last).round(6).tolist()
                    if np.max(np.abs(echoed_am2(last) - expected)) > 0.5e-4:
                        self.problem(f"commands: {name} {fmt(dipole)} A m^2: set-point echoed {fmt(echoed_am2(last))}, "
                                     f"the contract's {fmt(expected)} (DAC step {r:g}, each axis at most {m:g} A m^2)")
        self.measured["commands"] = results

    def settled_from_s(self, start_s: float, end_s: float, expected_am2: np.ndarray) -> float:
        """When a hold's coils have settled: settle_s after its first command, or, if the board
        echoes its set-point, settle_s after the first echo of this hold's set-point, if that is
        later. On a loaded host the hold's first frames may reach the board late (they wait in this
        host's queues), and the coils follow the command from when the board took it."""
        c = self.contract
        settled_s = start_s + c.settle_s
        if c.setpoint_echo:
            first = next((h for h in self.flight.frames(p.TLM_SETPOINT, start_s, end_s)
                          if np.max(np.abs(echoed_am2(h) - expected_am2)) <= 0.5e-4), None)
            if first is not None:
                settled_s = max(settled_s, first.t_s + c.settle_s)
        return settled_s

    def refusals(self) -> None:
        c, f = self.contract, self.flight
        steady = STEADY(c.max_dipole_am2)
        wrong = [-0.75 * c.max_dipole_am2, 0.75 * c.max_dipole_am2, -0.75 * c.max_dipole_am2]
        probes = [("bad-crc", p.E2EStatus.WRONG_CRC), ("repeated-counter", p.E2EStatus.REPEATED)]
        if c.profile == "secoc":
            probes += [("bad-mac", p.E2EStatus.WRONG_MAC), ("old-freshness", p.E2EStatus.STALE),
                       ("plain-command", p.E2EStatus.NOT_AUTHENTICATED),
                       ("plain-nmt-stop", p.E2EStatus.NOT_AUTHENTICATED)]
        # After a refused frame the steady commands pause long enough for a telemetry frame to show
        # the coils if they moved (a board without the echo), and short enough to stay inside the
        # command timeout with the margin to spare (0.05 s with the defaults).
        pause_s = max(c.command_period_s, min(1.5 * c.telemetry_period_s,
                                              c.command_timeout_s - c.command_period_s - c.margin_s))
        results = []
        for kind, status in probes:
            # A probe judged while this host held the check's commands up past the command timeout
            # (the board then rightly went to its safe state) is sent again, as the timeout step is.
            def attempt():
                lead_s = time.monotonic()
                f.command_for(PROBE_LEAD_S, steady)
                expected_steady = [s for s in f.sent if s.kind == "command"][-1].expected_am2
                sleep_until(f.sent[-1].t_s + 0.5 * c.command_period_s)
                probe = f.probe(kind, wrong)
                sleep_until(probe.t_s + pause_s)
                f.command_for(PROBE_LEAD_S, steady)
                end = time.monotonic()
                self.probe_windows.append((probe.t_s, end))
                result, problems = self._judge_probe(kind, status, probe, end, expected_steady)
                if kind == "plain-nmt-stop" and f.state_at(time.monotonic()) != p.NMT_OPERATIONAL:
                    self.start_operational("NMT start after an obeyed plain NMT stop")
                return result, problems, self.commands_held_up(lead_s, end) if problems else None

            results.append(self.judged_unless_held_up(attempt))
        f.command_for(PROBE_LEAD_S, steady)
        self.measured["refusals"] = results

    def commands_held_up(self, from_s: float, to_s: float) -> str | None:
        """What says this host held the check's genuine commands up within [from_s, to_s]: two of
        them further apart than the command timeout, or what `held_up` finds; None: nothing."""
        c = self.contract
        sent = [s.t_s for s in self.flight.sent if s.kind == "command" and from_s <= s.t_s <= to_s]
        gap = max((b - a for a, b in zip(sent, sent[1:])), default=0.0)
        if gap > c.command_timeout_s:
            return f"the check sent no command for {ms(gap)}"
        return self.held_up(from_s, to_s)

    def _judge_probe(self, kind: str, status: p.E2EStatus, probe: Sent, end_s: float,
                     steady: np.ndarray) -> tuple[dict, list[str]]:
        """The probe's measurements and its problems (not yet the check's)."""
        c, f = self.contract, self.flight
        what = PROBE_WORDS[kind]
        emcys = f.frames(p.EMCY, probe.t_s, end_s)
        match = next((h for h in emcys if h.signals["ErrorCode"] == p.EMCY_E2E_CHECK_FAILED
                      and h.signals["E2eStatus"] == status
                      and (probe.counter is None or h.signals["RejectedCounter"] == probe.counter)), None)
        moved = []
        for h in f.frames(p.TLM_SETPOINT, probe.t_s, end_s):
            if np.max(np.abs(echoed_am2(h) - steady)) > 0.5e-4:
                moved.append(f"set-point echoed {fmt(echoed_am2(h))}")
                break
        for h in f.frames(p.TLM_DIPOLE, probe.t_s, end_s):
            if np.max(np.abs(applied_am2(h) - steady)) > c.dipole_tolerance_am2:
                moved.append(f"telemetry applied {fmt(applied_am2(h))}")
                break
        if kind == "plain-nmt-stop":
            states = {int(h.signals["NmtState"]) for h in f.frames(p.HEARTBEAT, probe.t_s, end_s)}
            if states - {p.NMT_OPERATIONAL}:
                moved.append(f"heartbeat said {', '.join(state_name(s) for s in sorted(states))}")
        result = {"probe": kind, "expected_emcy": f"0x{p.EMCY_E2E_CHECK_FAILED:04X} {status.name}",
                  "emcy_after_s": _after(match, probe), "moved": moved,
                  "emcys": [emcy_words(h) for h in emcys]}
        problems = []
        if moved or match is None:
            said = (f"; EMCYs heard: {', '.join(result['emcys'])}" if emcys and match is None else "")
            problems.append(f"{what}: " + " and ".join(
                (["not refused: " + ", ".join(moved) + f" (the steady dipole {fmt(steady)}, the frame's "
                  f"{fmt([-0.75 * c.max_dipole_am2, 0.75 * c.max_dipole_am2, -0.75 * c.max_dipole_am2])})"] if moved else [])
                + ([f"no EMCY 0x{p.EMCY_E2E_CHECK_FAILED:04X} with E2eStatus {status.name} ({int(status)})"
                    + ("" if probe.counter is None else f" and RejectedCounter {probe.counter}") + said]
                   if match is None else [])))
        return result, problems

    def command_timeout(self) -> None:
        """Stop commanding: the timeout's EMCY, the coils off, the safe state's echo; commands
        again: the error reset. An attempt that fails while the board went silent or the check
        stalled (bench/contract_check/host_stalls.py) is repeated, at most HELD_UP_RETRIES times,
        and recorded; the last attempt is judged."""
        def attempt():
            problems, result, window = self._timeout_attempt()
            return result, problems, self.held_up(*window) if problems else None

        self.measured["command_timeout"] = self.judged_unless_held_up(attempt)

    def judged_unless_held_up(self, attempt) -> dict:
        """Run a timed step's `attempt()` -> (its measurements, its problems, what says this host
        held it up or None) again while it fails held up, at most HELD_UP_RETRIES times; the last
        attempt's problems are the check's, the attempts before it are kept in its measurements'
        repeated_attempts. Returns the last attempt's measurements."""
        repeated = []
        for n in range(HELD_UP_RETRIES + 1):
            result, problems, held_up = attempt()
            if held_up is None or n == HELD_UP_RETRIES:
                break
            repeated.append({"problems": problems, "held_up": held_up})
        if repeated:
            result["repeated_attempts"] = repeated
        for text in problems:
            self.problem(text if held_up is None else f"{text} ({held_up} in each of {len(repeated) + 1} "
                                                      f"attempts: this host may be too busy to judge the board)")
        return result

    def _timeout_attempt(self) -> tuple[list[str], dict, tuple[float, float]]:
        """One attempt: its problems, its measurements and its window (from the last command)."""
        c, f = self.contract, self.flight
        problems = []
        last = [s for s in f.sent if s.kind == "command"][-1]
        bound = c.command_timeout_s + c.margin_s
        listen_s = bound + c.telemetry_period_s + c.settle_s + 0.1
        sleep_until(last.t_s + listen_s)
        self.timeout_windows.append((last.t_s, last.t_s + listen_s))
        emcy = next((h for h in f.frames(p.EMCY, last.t_s, last.t_s + listen_s)
                     if h.signals["ErrorCode"] == p.EMCY_COMMAND_TIMEOUT), None)
        off = next((h for h in f.frames(p.TLM_DIPOLE, last.t_s, last.t_s + listen_s)
                    if h.signals["SafeState"] and np.max(np.abs(applied_am2(h))) <= c.dipole_tolerance_am2), None)
        echo = next((h for h in f.frames(p.TLM_SETPOINT, last.t_s, last.t_s + listen_s)
                     if h.signals["SafeState"] and not h.signals["CommandApplied"]
                     and np.max(np.abs(echoed_am2(h))) <= 0.5e-4), None)
        result = {"emcy_after_s": _after(emcy, last), "coils_off_telemetry_after_s": _after(off, last),
                  "safe_state_echo_after_s": _after(echo, last), "bound_s": round(bound, 4)}
        if emcy is None:
            problems.append(f"command timeout: no EMCY 0x{p.EMCY_COMMAND_TIMEOUT:04X} within {ms(listen_s)} of the "
                            f"last command (contract: safe state after {ms(c.command_timeout_s)} without a valid "
                            f"command)")
        elif not c.command_timeout_s - 0.002 <= emcy.t_s - last.t_s <= bound:
            problems.append(f"command timeout: EMCY 0x{p.EMCY_COMMAND_TIMEOUT:04X} {ms(emcy.t_s - last.t_s)} after the "
                            f"last command, the contract's {ms(c.command_timeout_s)} (+ {ms(c.margin_s)})")
        if off is None:
            held = [applied_am2(h) for h in f.frames(p.TLM_DIPOLE, last.t_s + bound, last.t_s + listen_s)]
            problems.append(f"command timeout: no safe state: the telemetry never said coils off within "
                            f"{ms(listen_s)} of the last command" + (f" (applied {fmt(held[-1])} A m^2)" if held else ""))
        elif off.t_s - last.t_s > bound + c.telemetry_period_s + c.settle_s:
            problems.append(f"command timeout: the telemetry said coils off {ms(off.t_s - last.t_s)} after the last "
                            f"command (timeout {ms(c.command_timeout_s)} + margin + one telemetry period)")
        if c.setpoint_echo and (echo is None or echo.t_s - last.t_s > bound):
            problems.append(f"command timeout: no set-point echo of the safe state (MTQ_TLM_SETPOINT SafeState 1, "
                            f"CommandApplied 0, set-point 0) within {ms(bound)}" if echo is None else
                            f"command timeout: set-point echo of the safe state {ms(echo.t_s - last.t_s)} after the "
                            f"last command, over {ms(bound)}")
        # Commands again: the error is gone, and the board says so (CiA 301 error reset).
        first = f.command(STEADY(c.max_dipole_am2))
        f.command_for(2 * HOLD_S, STEADY(c.max_dipole_am2))
        reset = next((h for h in f.frames(p.EMCY, first.t_s) if h.signals["ErrorCode"] == p.EMCY_NO_ERROR), None)
        result["error_reset_emcy_after_s"] = _after(reset, first)
        if reset is None and emcy is not None:
            problems.append("command timeout: no error-reset EMCY (0x0000) when commands came back (CiA 301: a "
                            "cleared error is announced)")
        return problems, result, (last.t_s, last.t_s + listen_s)

    def nmt_states(self) -> None:
        c, f = self.contract, self.flight
        steady = STEADY(c.max_dipole_am2)
        for command, state, what in ((p.NMT_ENTER_PRE_OPERATIONAL, p.NMT_PRE_OPERATIONAL, "NMT enter pre-operational"),
                                     (p.NMT_STOP, p.NMT_STOPPED, "NMT stop")):
            f.command_for(HOLD_S, steady)
            sent, beat = self.nmt(command, state, 3 * c.heartbeat_period_s)
            bound = c.heartbeat_period_s + c.margin_s
            entry = {"heartbeat_after_s": _after(beat, sent)}
            self.measured.setdefault("nmt", {}).setdefault(what, []).append(entry)
            if beat is None:
                self.problem(f"{what}: no heartbeat saying {state_name(state)} within {ms(3 * c.heartbeat_period_s)} "
                             f"(it said {state_name(f.state_at(time.monotonic()))})")
            elif beat.t_s - sent.t_s > bound:
                self.problem(f"{what}: {state_name(state)} heartbeat {ms(beat.t_s - sent.t_s)} after the command, "
                             f"over one heartbeat period + margin ({ms(bound)})")
            # Not operational: commands are not processed, nothing but heartbeats (and, pre-operational,
            # EMCY) is sent. A frame the board would refuse when operational must not be answered when stopped.
            quiet_from = sent.t_s + c.margin_s
            f.command_for(2 * c.heartbeat_period_s, steady, judged=False)
            if state == p.NMT_STOPPED:
                f.probe("bad-crc", steady)
            sleep_until(time.monotonic() + c.heartbeat_period_s)
            self.echo_free.append((quiet_from, time.monotonic()))
            sent_frames = f.frames(PROTECTED + ((p.EMCY,) if state == p.NMT_STOPPED else ()), quiet_from)
            entry["frames_while_not_operational"] = len(sent_frames)
            if sent_frames:
                names = sorted({h.name for h in sent_frames})
                self.problem(f"{what}: {len(sent_frames)} frame(s) ({', '.join(names)}) while {state_name(state)} "
                             f"(CiA 301: " + ("only heartbeats when stopped)" if state == p.NMT_STOPPED
                                              else "no PDOs when pre-operational)"))
            if beat is None:
                continue
            self.start_operational(f"NMT start after {what.removeprefix('NMT ')}")

    def reset_node(self, at_start: bool = False) -> bool:
        c, f = self.contract, self.flight
        sent, boot = self.nmt(p.NMT_RESET_NODE, p.NMT_BOOT_UP, 3 * c.heartbeat_period_s)
        bound = c.heartbeat_period_s + c.margin_s
        pre = f.wait_for(p.HEARTBEAT, boot.t_s if boot else sent.t_s, 3 * c.heartbeat_period_s,
                         lambda h: h.signals["NmtState"] == p.NMT_PRE_OPERATIONAL)
        self.measured.setdefault("nmt", {})["NMT reset node"] = {"boot_up_after_s": _after(boot, sent),
                                                                 "pre_operational_after_s": _after(pre, sent)}
        if boot is None:
            self.problem(f"NMT reset node: no boot-up message (heartbeat state 0) within {ms(3 * c.heartbeat_period_s)}")
        elif boot.t_s - sent.t_s > bound:
            self.problem(f"NMT reset node: boot-up {ms(boot.t_s - sent.t_s)} after the command, over {ms(bound)}")
        if pre is None:
            self.problem("NMT reset node: no pre-operational heartbeat after it")
            return False
        if not at_start:
            sleep_until(time.monotonic() + c.heartbeat_period_s)
        return True

    def nmt(self, command: int, state: int, within_s: float) -> tuple[Sent, Heard | None]:
        """Send an NMT command; the first heartbeat saying `state` within within_s, or None. A frame
        the board refused as stale that this host may have delivered late (late_arrivals) is not the
        board's fault: it is sent again, at most LATE_NMT_RETRIES times, and noted."""
        f = self.flight
        for _ in range(LATE_NMT_RETRIES + 1):
            sent = f.nmt(command)
            beat = f.wait_for(p.HEARTBEAT, sent.t_s, within_s, lambda h: h.signals["NmtState"] == state)
            if beat is not None or not self._arrived_stale(sent):
                break
            self.late.append(sent)
        return sent, beat

    def _arrived_stale(self, sent: Sent) -> bool:
        f = self.flight
        if self.contract.profile != "secoc":
            return False                 # no freshness window on e2e
        frames = f.frames()
        index = next(i for i, s in enumerate(f.sent) if s is sent)
        return may_have_arrived_stale(index, f.sent, frames, self.contract.freshness_max_age_s)


STEADY = lambda m: [0.4 * m, -0.3 * m, 0.2 * m]    # noqa: E731 - the steady dipole for a limit m

PROBE_WORDS = {
    "bad-crc": "bad CRC (a command whose E2E CRC is wrong, its MAC authentic on secoc)",
    "repeated-counter": "repeated alive counter (the last command's counter again, otherwise valid)",
    "bad-mac": "bad MAC (an authenticated command whose CMAC is wrong by one bit)",
    "old-freshness": "old freshness (an authentic command whose freshness value is ten windows old)",
    "plain-command": "plain MTQ_CMD on secoc (valid E2E, no MAC)",
    "plain-nmt-stop": "plain NMT stop on secoc (identifier 0, no MAC)",
}


def _after(h: Heard | None, sent: Sent) -> float | None:
    return None if h is None else round(h.t_s - sent.t_s, 5)

