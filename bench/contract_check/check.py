"""`bench contract check controller|estimator`: run the bench's other nodes against an outside
controller or estimator and judge what it published.

The run is an ordinary `bench run` with `[run] external = [NODE]` (the launcher starts no such
node and waits for one to join under that name). The outside node is started by the
check from `--command` (with {connect}, {run_id}, {scenario}, {run_dir} filled in) or by the user,
who is told where to connect. The verdict comes afterwards from the run's recording: the recorder
keeps every sample under `bench/<run_id>/**`, valid or not, with its arrival time on the recorder's
clock, so the check needs nothing from the outside node but what it put on the bus:

- authenticity: every message carries a valid MAC under the run's data key (bench/bus/data_auth.py;
  the recorder puts the others on `unauthentic/<topic>`, and the plant never saw them);
- keys: every topic is one of the contract's (bench.contract.table);
- schemas: everything on the controller's topics decodes as its message (bench.bus.schemas), of
  this run and schema version;
- sequence numbers: one command per estimate, `header.seq` = the estimate's, none skipped, none
  repeated, in order; the header carried (same sim_time_s, upstream stamps unchanged);
- deadlines, on the recorder's clock (the outside node's own stamps are its claims): lock-step, a
  command later than the plant's command timeout broke the loop; the budget is reported. Real
  time, a step the plant integrated on a held command is a miss, unless the plant refused that
  step's command (a refusal is named as such, never as a deadline miss).

And what the bench did with them, and what the node did with the bench's:
- the plant's refusals (out of envelope, stale, future, non-finite: command_acceptance.json) fail
  the check, by reason and count;
- a key the controller signed outside its role's row of the key table (recorder_counts.json's
  publishers: the sender in each tag) fails, whatever the key;
- a command without its own stages' stamps (`controller_received`, `commanded`) fails;
- a node that does not stop within STOP_GRACE_S of the launcher's leaving fails;
- the check sends forged and replayed estimates itself (bench/contract_check/probe.py) and fails a
  controller whose commands answer them.
"""
from __future__ import annotations

import contextlib
import io
import json
import re
import shlex
import subprocess
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import numpy as np
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader

from bench.bus import keys
from bench.bus.schemas import (SCHEMA_VERSION, MalformedMessage, Message, RangeBearing, RelativePosition,
                                ThrustCommand, TranslationEstimate, TruthState, decode)
from bench.bus.session import free_loopback_port, loopback_endpoint
from bench.contract.fields import THRUST_STATUS_PATTERN, THRUST_STATUSES
from bench.contract_check.probe import FORGED_SEQ_BASE, InputProbe
from bench.contract.table import RENDEZVOUS, publications_of, topic_of
from bench.launcher import run_bench
from bench.recorder import MALFORMED_PREFIX, RECORDING_FILE, UNAUTHENTIC_PREFIX
from bench.scenario import Scenario, ScenarioError, load_scenario, parse_scenario

STOP_GRACE_S = 5.0        # how long an outside node has to stop once the launcher has left
MAX_LISTED = 5            # per kind of problem, the first few are named
OUTSIDE_LOG = "outside.log"


@dataclass
class Verdict:
    problems: list[str] = field(default_factory=list)
    summary: str = ""

    @property
    def passed(self) -> bool:
        return not self.problems

    def text(self, node: str) -> str:
        if self.passed:
            return f"contract check {node}: pass ({self.summary})"
        lines = [f"contract check {node}: FAIL ({len(self.problems)} problem{'s' * (len(self.problems) > 1)}; {self.summary})"]
        return "\n".join(lines + [f"  - {p}" for p in self.problems])


@dataclass(frozen=True)
class CheckedRole:
    """A node the check can judge: what it reads and answers, what it answers with, the stamps it
    carries on and adds. One output per input sample, with the input's seq."""

    node: str
    input_topic: str
    input_type: type
    output_topic: str
    output_type: type
    upstream_stages: tuple[str, ...]
    own_stages: tuple[str, ...]
    inputs: str           # the inputs and the output in words, for the verdict
    output: str


CHECKED_NODES = ("controller", "estimator")
DEFAULT_SCENARIO = {"controller": "rendezvous_lqr", "estimator": "rendezvous_smoother"}


def role_for(node: str, scenario: Scenario) -> CheckedRole:
    if node == "controller":
        return CheckedRole("controller", keys.ESTIMATE_TRANSLATION, TranslationEstimate, keys.COMMAND_THRUST,
                           ThrustCommand, ("sensed", "estimator_received", "estimated"),
                           ("controller_received", "commanded"), "estimates", "command")
    if node == "estimator":
        # What the scenario's estimator reads: the truth in truth mode, else its sensor.
        if scenario.estimator.mode == "truth":
            topic, kind = keys.TRUTH, TruthState
        elif scenario.estimator.translation.sensor == "range_bearing":
            topic, kind = keys.SENSE_RANGE_BEARING, RangeBearing
        else:
            topic, kind = keys.SENSE_RELPOS, RelativePosition
        return CheckedRole("estimator", topic, kind, keys.ESTIMATE_TRANSLATION, TranslationEstimate, ("sensed",),
                           ("estimator_received", "estimated"), "samples", "estimate")
    raise ValueError(f"contract check: no check for {node!r} (one of {', '.join(CHECKED_NODES)})")


def check_scenario(scenario: Scenario, steps: int, mode: str | None, command_timeout_s: float,
                   startup_timeout_s: float | None = None, node: str = "controller") -> Scenario:
    """The scenario the check runs: the node external, short, a short command timeout."""
    if scenario.kind != "rendezvous" or scenario.can is not None:
        raise ScenarioError(f"contract check {node}: scenario {scenario.name!r} is not the rendezvous loop "
                            f"without [can]")
    run = msgspec.structs.replace(scenario.run, steps=steps, external=[node],
                                  command_timeout_s=command_timeout_s, mode=mode or scenario.run.mode)
    if startup_timeout_s is not None:
        run = msgspec.structs.replace(run, liveliness=msgspec.structs.replace(
            run.liveliness, startup_timeout_s=startup_timeout_s))
    return parse_scenario(msgspec.to_builtins(msgspec.structs.replace(scenario, run=run)), "contract check")


# --- the run ----------------------------------------------------------------------------------
class Outside:
    """The outside node's process, started once the launcher has written scenario.json (its hub is
    listening by then) and stopped at the end if it has not stopped by itself."""

    def __init__(self, command: str, hub: str, run_id: str, run_dir: Path):
        self.argv = [a.format(connect=hub, run_id=run_id, scenario=str(run_dir / "scenario.json"), run_dir=str(run_dir))
                     for a in shlex.split(command)]
        self.run_dir = run_dir
        self.process: subprocess.Popen | None = None
        self.error: str | None = None
        self._thread = threading.Thread(target=self._start, name="outside-start", daemon=True)
        self._stop = threading.Event()
        self._thread.start()

    def _start(self) -> None:
        scenario_file = self.run_dir / "scenario.json"
        while not scenario_file.is_file():
            if self._stop.wait(0.02):
                return
        try:
            log = open(self.run_dir / "logs" / OUTSIDE_LOG, "w")
            self.process = subprocess.Popen(self.argv, stdout=log, stderr=subprocess.STDOUT)
        except OSError as exc:
            self.error = f"could not start the outside node ({' '.join(self.argv)}): {exc}"

    def stop(self, grace_s: float = STOP_GRACE_S) -> int | None:
        """Its exit code; None if it never started; KILLED if it did not stop within grace_s."""
        self._stop.set()
        self._thread.join()        # a process started after this look would be left running
        if self.process is None:
            return None
        try:
            return self.process.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            self.process.kill()            # only the process this check started, by its handle
            self.process.wait(timeout=5.0)
            return KILLED


KILLED = "killed"


class ProbeStarter:
    """The input probe, started once the hub listens (scenario.json is written after it)."""

    def __init__(self, hub: str, run_id: str, run_dir: Path, topic: str):
        self.probe: InputProbe | None = None
        self._stop = threading.Event()

        def start() -> None:
            while not (run_dir / "scenario.json").is_file():
                if self._stop.wait(0.02):
                    return
            self.probe = InputProbe(hub, run_id, topic)

        self._thread = threading.Thread(target=start, name="probe-start", daemon=True)
        self._thread.start()

    def close(self) -> InputProbe | None:
        self._stop.set()
        # No timeout: a probe still opening its session (seconds on a loaded host) would otherwise be
        # left open, and Zenoh's threads calling into Python while the interpreter exits abort the
        # process ("FATAL: exception not rethrown", exit -6).
        self._thread.join()
        if self.probe is not None:
            self.probe.close()
        return self.probe


def run_check(scenario: Scenario, run_id: str, runs_dir: Path, command: str | None, port: int | None = None,
              allowed_misses: int = 0, node: str = "controller") -> Verdict:
    role = role_for(node, scenario)
    port = port or free_loopback_port()
    run_dir = Path(runs_dir) / run_id
    outside = Outside(command, loopback_endpoint(port), run_id, run_dir) if command else None
    starter = ProbeStarter(loopback_endpoint(port), run_id, run_dir, role.input_topic)
    launcher_err = _Tee(sys.stderr)     # the user still sees where to connect; the check reads the reason
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(launcher_err):
            code, run_dir = run_bench(scenario, run_id, Path(runs_dir), port, show_progress=command is None,
                                      write_report=False)
    finally:
        probe = starter.close()
        outside_code = outside.stop() if outside else None
    verdict = judge(run_dir, scenario, code, allowed_misses, probe, _launcher_error(launcher_err.getvalue()), role)
    if outside is not None and outside.error:
        verdict.problems.insert(0, outside.error)
    elif outside_code == KILLED:
        verdict.problems.append(f"stop not obeyed: the outside node was still running {STOP_GRACE_S:g} s after the "
                                f"launcher left (it must stop when `presence/launcher` no longer answers; it was killed)")
    elif outside is not None and outside_code not in (0, None):
        verdict.problems.append(f"the outside node exited with code {outside_code} "
                                f"(its output: {run_dir / 'logs' / OUTSIDE_LOG})")
    return verdict


class _Tee(io.StringIO):
    """Kept, and passed on to the terminal."""

    def __init__(self, terminal):
        super().__init__()
        self.terminal = terminal

    def write(self, text: str) -> int:
        self.terminal.write(text)
        return super().write(text)


def _launcher_error(stderr: str) -> str:
    """The launcher's own reason for ending the run early (its `bench: error:` line), if any."""
    lines = [line.removeprefix("bench: error: ") for line in stderr.splitlines() if line.startswith("bench: error: ")]
    return lines[-1] if lines else ""


# --- the verdict ------------------------------------------------------------------------------
@dataclass
class Sample:
    topic: str
    payload: bytes
    received_ns: int      # the recorder's wall clock at arrival


def read_samples(path: Path, unauthentic: dict[str, int] | None = None) -> list[Sample]:
    """Every sample of the recording, valid or not, in arrival order (malformed ones under their
    topic); those that failed the data-topic MAC are only counted per topic into `unauthentic`."""
    samples = []
    unauthentic = {} if unauthentic is None else unauthentic
    with open(path, "rb") as f:
        try:
            for _schema, channel, message in NonSeekingReader(f).iter_messages(log_time_order=False):
                if channel.topic.startswith(UNAUTHENTIC_PREFIX):
                    topic = channel.topic.removeprefix(UNAUTHENTIC_PREFIX)
                    unauthentic[topic] = unauthentic.get(topic, 0) + 1
                    continue
                topic = channel.topic.removeprefix(MALFORMED_PREFIX)
                samples.append(Sample(topic, bytes(message.data), int(message.publish_time)))
        except (McapError, EOFError, ValueError):
            pass       # a recording cut short: what was written is judged
    return samples


def judge(run_dir: Path, scenario: Scenario, exit_code: int, allowed_misses: int = 0,
          probe: InputProbe | None = None, launcher_error: str = "", role: "CheckedRole | None" = None) -> Verdict:
    role = role or role_for("controller", scenario)
    verdict = Verdict()
    problems = verdict.problems
    run_id = run_dir.name
    if exit_code != 0:
        why = f" ({launcher_error})" if launcher_error else _plant_error(run_dir)
        problems.append(f"the run did not finish: exit code {exit_code}{why}")
    recording = run_dir / RECORDING_FILE
    if not recording.is_file():
        problems.append(f"no recording ({recording}): nothing to judge")
        verdict.summary = "no recording"
        return verdict
    unauthentic: dict[str, int] = {}
    samples = read_samples(recording, unauthentic)
    if probe is not None:    # what the check sent itself is no fault of the node's
        left = unauthentic.pop(probe.topic, 0) - probe.sent_forged - probe.sent_replayed
        if left > 0:
            unauthentic[probe.topic] = left
    for topic, n in sorted(unauthentic.items()):
        problems.append(f"not authenticated: {n} message(s) on {topic} without a valid, fresh MAC under the run's key "
                        f"(runs/<id>/bus.key; docs/contract.md, \"Signing\"); the bench's nodes dropped them")

    # Keys: the contract's, and the node's own row of the key table.
    unknown: dict[str, int] = {}
    for s in samples:
        if topic_of(s.topic) is None:
            unknown[s.topic] = unknown.get(s.topic, 0) + 1
    own_keys = [t.topic.replace("<process>", role.node) for t in publications_of(role.node, RENDEZVOUS)]
    for topic, n in sorted(unknown.items()):
        problems.append(f"wrong key: {n} message(s) on {keys.key(run_id, topic)}, which is not a key of the contract "
                        f"(the {role.node} publishes on {', '.join(own_keys)})")
    for topic, n in sorted(_signed_by(run_dir, role.node).items()):
        if topic not in own_keys and topic not in unknown:
            problems.append(f"foreign key: {n} message(s) signed by the {role.node} on {keys.key(run_id, topic)}, a key "
                            f"outside its role (it publishes on {', '.join(own_keys)} only)")

    # Schemas of what the node publishes.
    outputs: list[tuple[Message, int]] = []
    own = {t.topic: t.messages[0] for t in publications_of(role.node, RENDEZVOUS)}
    invalid: dict[str, list[str]] = {}
    for s in samples:
        entry = topic_of(s.topic)
        kind = own.get(entry.topic) if entry is not None else _claimed_type(s.payload, own)
        if kind is None or (entry is not None and entry.topic.endswith("<process>")
                            and s.topic != f"{keys.STATUS_STATS}/{role.node}"):
            continue
        try:
            message = decode(s.payload, kind)
        except MalformedMessage as exc:
            invalid.setdefault(s.topic, []).append(str(exc))
            continue
        if message.header.run_id != run_id:
            invalid.setdefault(s.topic, []).append(f"{kind.__name__}: header.run_id {message.header.run_id!r}, "
                                                   f"expected {run_id!r}")
        elif isinstance(message, role.output_type) and s.topic == role.output_topic:
            outputs.append((message, s.received_ns))
    for topic, errors in sorted(invalid.items()):
        problems.append(f"schema-invalid: {len(errors)} message(s) on {topic}; first: {errors[0]}")

    # Sequence numbers and headers, against the inputs the node was given.
    inputs: dict[int, tuple[Message, int]] = {}
    for s in samples:
        if s.topic == role.input_topic:
            try:
                m = decode(s.payload, role.input_type)
            except MalformedMessage:
                continue
            inputs.setdefault(m.header.seq, (m, s.received_ns))
    seqs = [m.header.seq for m, _ in outputs]
    # What the node did with the bench's inputs: the probe's forged and replayed ones (judged here,
    # not as sequence problems).
    if probe is not None:
        forged = [k for k in seqs if k >= FORGED_SEQ_BASE]
        if forged:
            problems.append(f"acted on forged {role.inputs}: {len(forged)} {role.output}(s) answer {role.inputs} the check "
                            f"sent with a wrong tag (seq {forged[0]}...): check every input's tag under the run's key")
        seqs = [k for k in seqs if k < FORGED_SEQ_BASE]
        extra = seqs.count(probe.replayed_seq) - 1 if probe.replayed_seq is not None else 0
        if extra > 0:
            problems.append(f"acted on replayed {role.inputs}: {extra} extra {role.output}(s) for seq {probe.replayed_seq}, "
                            f"whose input the check replayed with its old counter: take a sender's counter only upwards")
            seqs = [k for i, k in enumerate(seqs) if k != probe.replayed_seq or i == seqs.index(k)]
    _sequence_problems(seqs, sorted(inputs), problems, role)
    carried = []
    for output, _ in outputs:
        given = inputs.get(output.header.seq)
        if given is None:
            continue
        h, ih = output.header, given[0].header
        if h.sim_time_s != ih.sim_time_s:
            carried.append(f"seq {h.seq}: sim_time_s {h.sim_time_s!r}, the input's is {ih.sim_time_s!r}")
        lost = [st for st in role.upstream_stages if st in ih.stamps_ns and h.stamps_ns.get(st) != ih.stamps_ns[st]]
        if lost:
            carried.append(f"seq {h.seq}: stamps {', '.join(lost)} not carried from the input")
    if carried:
        problems.append(f"header not carried from the input in {len(carried)} {role.output}(s): "
                        + "; ".join(carried[:MAX_LISTED]))
    if role.output_type is ThrustCommand:
        odd = sorted({m.status for m, _ in outputs if not _allowed_status(m.status)})
        if odd:
            problems.append(f"status: {', '.join(map(repr, odd[:MAX_LISTED]))} is not one of the contract's values "
                            f"({', '.join(THRUST_STATUSES)}, or the tube MPC's 'in-plane X, out-of-plane Y')")
    unstamped = [m.header.seq for m, _ in outputs if any(st not in m.header.stamps_ns for st in role.own_stages)]
    if unstamped:
        problems.append(f"stamps: {len(unstamped)} {role.output}(s) without the stamps {' and '.join(role.own_stages)} "
                        f"(CLOCK_MONOTONIC ns; first seq {unstamped[0]})")

    # What the bench did with the commands: the plant's output stage.
    refused = dict(_thrust_acceptance(run_dir).get("rejected") or {}) if role.node == "controller" else {}
    late_refused = 0
    if scenario.run.mode == "real-time":
        # In real time a command that comes after its step was integrated is refused as stale: that
        # is lateness (the step it was for counts as missed, below), not a command the plant refuses.
        late_refused = refused.pop("stale", 0)
    if refused:
        acceptance = _thrust_acceptance(run_dir)
        envelope = (f"; each |thrust_n[i]| at most {acceptance['max_abs']:g} {acceptance.get('unit', 'N')}"
                    if "out_of_envelope" in refused and "max_abs" in acceptance else "")
        problems.append("refused by the plant: " + ", ".join(f"{reason} {n}" for reason, n in sorted(refused.items()))
                        + f" command(s) (command_acceptance.json{envelope})")

    # Deadlines, on the recorder's clock.
    first_arrival: dict[int, int] = {}
    for output, received_ns in outputs:
        k = output.header.seq
        if k in inputs and received_ns >= inputs[k][1]:     # an answer to input k, not a guess ahead
            first_arrival.setdefault(k, received_ns)
    response_s = np.array([(first_arrival[k] - inputs[k][1]) / 1e9 for k in sorted(first_arrival) if k in inputs])
    run = scenario.run
    budget_s = scenario.controller.deadline.budget_s
    late = int(np.sum(response_s > run.command_timeout_s)) if response_s.size else 0
    if run.mode == "lock-step" and late:
        problems.append(f"deadline: {late} {role.output}(s) came after the plant's command timeout of "
                        f"{run.command_timeout_s:g} s")
    if run.mode == "real-time":
        missed = _plant_missed_steps(run_dir)
        if missed is not None:
            # A step whose command the plant refused ran on the held command too: named above as a
            # refusal, not here as lateness.
            missed = max(0, missed - sum(refused.values()))
        if late_refused:
            timing_note = f"; {late_refused} command(s) came after their step and were not applied"
        else:
            timing_note = ""
        if missed is not None and missed > allowed_misses:
            problems.append(f"deadline: {missed} real-time step(s) integrated on a held command (the command for step k "
                            f"must arrive before step k+1 starts; {allowed_misses} allowed{timing_note})")
    over = int(np.sum(response_s > budget_s)) if response_s.size else 0
    timing = (f"response at the recorder p50 {np.median(response_s) * 1e3:.2f} ms, worst {response_s.max() * 1e3:.2f} ms"
              + (f", {over} over the {budget_s * 1e3:g} ms budget" if role.node == "controller" else "")
              if response_s.size else "no responses")
    probed = (f"; {probe.sent_forged} forged and {probe.sent_replayed} replayed {role.inputs} sent by the check"
              if probe is not None else "")
    verdict.summary = (f"{scenario.name}, {run.mode}, {len(inputs)} {role.inputs}, {len(outputs)} valid {role.output}s"
                       f"{f' seq {min(seqs)}-{max(seqs)}' if seqs else ''} on {role.output_topic}; {timing}{probed}")
    return verdict


def _claimed_type(payload: bytes, own: dict) -> type | None:
    """On a key that is not the contract's: the controller's message type the payload's "type" tag
    names, so a command sent to a wrong key is judged for its schema too."""
    try:
        tag = json.loads(payload).get("type")
    except (ValueError, AttributeError, UnicodeDecodeError):
        return None
    return next((kind for kind in own.values() if kind.__struct_config__.tag == tag), None)


def _sequence_problems(seqs: list[int], input_seqs: list[int], problems: list[str],
                       role: "CheckedRole | None" = None) -> None:
    output, inputs = (role.output, role.inputs) if role is not None else ("command", "estimates")
    counts: dict[int, int] = {}
    for k in seqs:
        counts[k] = counts.get(k, 0) + 1
    repeated = sorted(k for k, n in counts.items() if n > 1)
    skipped = [k for k in input_seqs if k not in counts]
    unknown = sorted(k for k in counts if k not in set(input_seqs))
    disordered = [b for a, b in zip(seqs, seqs[1:]) if b < a]

    def listed(values) -> str:
        return ", ".join(map(str, values[:MAX_LISTED])) + (" ..." if len(values) > MAX_LISTED else "")

    if skipped:
        problems.append(f"sequence: no {output} with header.seq {listed(skipped)} (skipped: step k's {output} must carry seq k)")
    if repeated:
        problems.append(f"sequence: header.seq {listed(repeated)} repeated (one {output} per step)")
    if unknown:
        problems.append(f"sequence: header.seq {listed(unknown)} answers none of the {inputs} (a step the plant had not sampled)")
    if disordered:
        problems.append(f"sequence: seq went back in {len(disordered)} place(s), first to {disordered[0]}")


def _plant_error(run_dir: Path) -> str:
    """The plant's last error line, if any (why the loop broke)."""
    try:
        lines = (run_dir / "logs" / "plant.log").read_text(errors="replace").splitlines()
    except OSError:
        return ""
    errors = [line.split(" ERROR ", 1)[1] for line in lines if " ERROR " in line]
    return f" (plant: {errors[-1]})" if errors else ""


def _allowed_status(status: str) -> bool:
    return status in THRUST_STATUSES or re.match(THRUST_STATUS_PATTERN, status) is not None


def _thrust_acceptance(run_dir: Path) -> dict:
    """The plant's output stage's counts for thrust commands (accepted, rejected by reason, max_abs)."""
    try:
        return json.loads((run_dir / "command_acceptance.json").read_text()).get("thrust") or {}
    except (OSError, ValueError, AttributeError):
        return {}


def _signed_by(run_dir: Path, sender: str) -> dict[str, int]:
    """Topic -> messages the recorder took with `sender` in their valid tag (recorder_counts.json)."""
    try:
        return json.loads((run_dir / "recorder_counts.json").read_text()).get("signed_by", {}).get(sender, {})
    except (OSError, ValueError, AttributeError):
        return {}


def _plant_missed_steps(run_dir: Path) -> int | None:
    try:
        with np.load(run_dir / "trajectory.npz") as data:
            return int(data["plant_missed_steps"]) if "plant_missed_steps" in data.files else None
    except (OSError, ValueError, KeyError):
        return None


def load_check_scenario(name: str | None, steps: int, mode: str | None, command_timeout_s: float,
                        startup_timeout_s: float | None = None, node: str = "controller") -> Scenario:
    return check_scenario(load_scenario(name or DEFAULT_SCENARIO[node]), steps, mode, command_timeout_s,
                          startup_timeout_s, node)


def write_verdict(run_dir: Path, verdict: Verdict) -> None:
    (run_dir / "contract_check.json").write_text(json.dumps({"passed": verdict.passed, "problems": verdict.problems,
                                                             "summary": verdict.summary, "schema_version": SCHEMA_VERSION},
                                                            indent=2) + "\n")
