"""The actuator bus as separate processes without the rest of the loop: bus model, board, driver.

Part of the product, not test scaffolding: the CAN fault tests (tests/test_can_faults.py) and the
bus-model benchmark (benchmarks/bench_can_busmodel.py) use it, and so can anyone who wants to
exercise a driver against the board and the bus model alone.

`CanBench` opens the hub Zenoh session (through bench.bus.session), starts `bench node canbus`
and `bench node mtq` as their own OS processes (`bench.runtime.process.start_node`, as the
launcher does) on a scenario, and runs the flight-side driver in
the calling process on the scripted dipole profile. When it stops it collects what each process
wrote (board.json, busmodel.json, injections.jsonl, the captures) into a `CanRunResult` that
accounts for every frame.
"""
from __future__ import annotations

import json
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import can
import msgspec

from bench.bus import keys
from bench.bus.can import protocol as p
from bench.bus.can import run_key
from bench.bus.can.config import CanConfig
from bench.bus.can.driver import CommandLoop, FaultEvent, MagnetorquerDriver
from bench.bus.can.nodes import ACCOUNTING_NAME, BOARD_NAME, CAPTURE_NAME, INJECTIONS_NAME, REPORT_NAME
from bench.bus.can.transport import open_can_bus
from bench.bus.schemas import MtqApplied, decode
from bench.bus.presence import PresenceQuery
from bench.bus.session import SessionOptions, free_loopback_port, loopback_endpoint, open_session
from bench.runtime.process import start_node, terminate
from bench.scenario import load_scenario

# Bounds a hang at start-up, not a speed check: a node's start on UML's one CPU under a loaded host
# has taken over 30 s (when `bench node` still imported every command).
STARTUP_TIMEOUT_S = 60.0
EXIT_TIMEOUT_S = 10.0
# How long stop() waits for the board to act on the last command sent: a host-starved bus model
# holds frames back and delivers them late (0.8-1.3 s in UML under load), and a board behind a
# flood works through thousands of queued frames first (5 s was not enough with both cores busy).
# A hang bound: the wait normally ends within milliseconds.
DRAIN_TIMEOUT_S = 20.0
# After the run's silence has lasted the board's command timeout and a little more, how much longer
# to listen for the board's report of its safe state (the command-timeout EMCY): a board process the
# host held up sends it late (seen in UML on a loaded host: not within the 0.45 s window). A hang
# bound: whether it came in time is judged on the event's time and the lateness the nodes measured.
SAFE_STATE_WAIT_S = 10.0


def first_event(events: list[FaultEvent], kind: str, after_ns: int = 0, detail: str = "") -> FaultEvent | None:
    """The first driver event of `kind` detected at or after after_ns whose detail contains `detail`."""
    return next((e for e in events if e.kind == kind and e.detected_ns >= after_ns and detail in e.detail), None)


@dataclass
class CanRunResult:
    board: dict
    report: dict
    injections: list[dict]
    wire: Counter                        # frames on the bus, by name
    dropped: Counter                     # frames dropped by the injector or the bus, by name
    events: list[FaultEvent]
    driver_sent: int
    driver_received: Counter
    commanded: list[list[float]]         # every dipole the driver commanded
    sent: list[tuple[int, int]]          # (alive counter, monotonic ns it went to the bus) per command
    mtq_applied: list[MtqApplied]        # the board's actuator/mtq messages, in arrival order
    run_dir: Path
    command_start_ns: int = 0
    last_command_ns: int = 0
    board_drain_s: float | None = None   # how long the bench waited for the board at the end; None: gave up

    def injected(self, frame: str | None = None, action: str = "injected") -> list[dict]:
        ids = None if frame is None else {p.Protocol().frame_ids[frame]}
        return [r for r in self.injections if r["action"] == action and (ids is None or r["frame_id"] in ids)]

    def first_injection_ns(self, action: str | None = None) -> int | None:
        times = [r["t_ns"] for r in self.injections if action is None or r["action"] == action]
        return min(times) if times else None

    def first_event(self, kind: str, after_ns: int = 0, detail: str = "") -> FaultEvent | None:
        return first_event(self.events, kind, after_ns, detail)

    def kinds(self) -> Counter:
        return Counter(e.kind for e in self.events)

    def command_latencies_ns(self) -> list[int]:
        """Driver send to board applied, per command, pairing both in order by alive counter."""
        applied = iter(self.board["applied"])
        latencies = []
        for counter, sent_ns in self.sent:
            for entry in applied:
                if entry["counter"] == counter:
                    latencies.append(entry["applied_ns"] - sent_ns)
                    break
        return latencies


@dataclass
class CanBench:
    scenario_path: Path
    run_dir: Path
    run_id: str
    procs: dict = field(default_factory=dict)
    events: list = field(default_factory=list)
    commanded: list = field(default_factory=list)
    sent: list = field(default_factory=list)          # (alive counter, monotonic ns) per command
    command_start_ns: int = 0                         # monotonic ns of the first command, and the last
    last_command_ns: int = 0
    _applied_before_last_command: int = 0             # len(mtq_applied) when the last command left
    board_drain_s: float | None = None                # how long stop() waited for the board; None: gave up

    def __post_init__(self):
        self.scenario = load_scenario(self.scenario_path)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        if run_key.needs_key(self.scenario):
            # As the launcher does: a key for this run, handed to the nodes in their scenario.json (0600).
            self.scenario = run_key.with_run_key(self.scenario)
            self.scenario_path = self.run_dir / "scenario.json"
            run_key.write_private(self.scenario_path, msgspec.json.format(msgspec.json.encode(self.scenario)))
        self.config: CanConfig = self.scenario.can
        self.hub = loopback_endpoint(free_loopback_port())
        self.session = open_session(SessionOptions(listen=(self.hub,)))
        self.mtq_applied: list[MtqApplied] = []   # what the board published for the plant
        self._mtq_applied_seen_s: list[float] = []  # when each arrived here (monotonic)

        def on_applied(sample) -> None:
            message = decode(sample.payload.to_bytes(), MtqApplied)
            self._mtq_applied_seen_s.append(time.monotonic())    # first: mtq_applied[i] has its time
            self.mtq_applied.append(message)

        self._subscriber = self.session.declare_subscriber(keys.key(self.run_id, keys.ACTUATOR_MTQ), on_applied)

    # --- processes ------------------------------------------------------------------------
    def _spawn(self, name: str) -> None:
        self.procs[name] = start_node(name, self.run_id, self.scenario_path, self.hub, self.run_dir,
                                      self.run_dir / f"{name}.log")

    def _wait_ready(self, name: str) -> None:
        # No bus.key in this run directory: the nodes answer presence queries unsigned.
        query = PresenceQuery(self.session, self.run_id, None)
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while time.monotonic() < deadline:
            answer = query.ask(name).get(name)
            if answer is not None and answer.ready:
                return
            self._check_alive()
            time.sleep(0.05)
        raise TimeoutError(f"node {name} not ready after {STARTUP_TIMEOUT_S} s (see {self.run_dir}/{name}.log)")

    def _check_alive(self) -> None:
        for name, proc in self.procs.items():
            if proc.poll() is not None:
                raise RuntimeError(f"node {name} exited with {proc.returncode}: "
                                   f"{(self.run_dir / f'{name}.log').read_text()[-2000:]}")

    def start(self) -> "CanBench":
        self._spawn("canbus")
        self._wait_ready("canbus")
        # The driver listens before the board exists: every frame the board sends is counted.
        self.bus = open_can_bus(self.config.transport, self.config.flight_channel, run_id=self.run_id,
                                session_options=SessionOptions(connect=(self.hub,)))
        if hasattr(self.bus, "wait_for_peers"):
            self.bus.wait_for_peers(1, STARTUP_TIMEOUT_S)
        self.driver = MagnetorquerDriver.from_config(self.bus, self.config)
        self._spawn("mtq")
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not self.driver.health().alive:   # the board's first heartbeat
            self.driver.poll(timeout_s=0.05)
            self._check_alive()
            if time.monotonic() > deadline:
                raise TimeoutError(f"no heartbeat from the board after {STARTUP_TIMEOUT_S} s")
        self.driver.events.clear()
        self.driver.event_counts.clear()
        self.loop = CommandLoop(self.driver, self.config.driver.command_period_s, dipole_at=self.config.dipole_at,
                                on_command=self._on_command, on_events=self.events.extend)
        return self

    # --- the flight side ------------------------------------------------------------------
    def drive(self, duration_s: float, commanding: bool = True) -> None:
        """Command the scripted profile every command period (or stay silent) and poll."""
        self.loop.run(duration_s=duration_s, commanding=commanding)

    def _on_command(self, counter: int, dipole_am2: list[float], sent_ns: int) -> None:
        if not self.sent:
            self.command_start_ns = sent_ns
        self.last_command_ns = sent_ns
        self._applied_before_last_command = len(self.mtq_applied)
        self.commanded.append(dipole_am2)
        self.sent.append((counter, sent_ns))

    # --- stopping and collecting ----------------------------------------------------------
    def stop(self) -> CanRunResult:
        """Board first (so its last frames reach the bus model), then the bus model; the board
        only once it has the last command, so no frame on the wire is lost to the shutdown."""
        try:
            applied_s = self._await_last_command_at_board()
            if applied_s is not None:
                # A backlog can bring the last command to the board late (seen in UML: 0.37 s
                # and 0.66 s after the run's silence began): give the board, after it, the
                # silence in which its command timeout (the safe state the run checks) is seen.
                board = self.config.board
                quiet_until_s = applied_s + board.command_timeout_s + 3 * board.telemetry_period_s + 0.2
                quiet_left_s = quiet_until_s - time.monotonic()
                if quiet_left_s > 0:
                    self.drive(quiet_left_s, commanding=False)
                self._await_safe_state_report(quiet_until_s + SAFE_STATE_WAIT_S)
            events = list(self.events)   # what happens while the nodes shut down is not the run's
            self._terminate("mtq")
            self.drive(0.2, commanding=False)
            self._terminate("canbus")
            self.driver.poll(timeout_s=0.05)   # frames still queued for us, for the accounting
            self.events[:] = events
            return self._collect()
        finally:
            self.close()

    def _await_safe_state_report(self, until_s: float) -> None:
        """Listen (silent) until the driver heard the board's command timeout after the last
        command, or until `until_s` (monotonic s)."""
        while (first_event(self.events, "board_command_timeout", self.last_command_ns) is None
               and time.monotonic() < until_s):
            self.drive(0.05, commanding=False)

    def _await_last_command_at_board(self) -> float | None:
        """Poll (silent) until the board applied the last command sent, at most DRAIN_TIMEOUT_S:
        a bus model the host held up delivers its backlog late, and a board stopped before
        that would leave commands on the wire it never received. A last command a fault
        rejected is never applied: that costs the timeout, no more. Returns when (monotonic s)
        the board's report of applying it arrived here; None if it never did."""
        if not self.sent:
            return None
        last_counter = self.sent[-1][0]
        started = time.monotonic()
        while time.monotonic() < started + DRAIN_TIMEOUT_S:
            first = self._applied_before_last_command
            for i, message in enumerate(self.mtq_applied[first:], start=first):
                if message.alive_counter == last_counter:
                    self.board_drain_s = time.monotonic() - started
                    return self._mtq_applied_seen_s[i]
            self.driver.poll(timeout_s=0.05)
        return None

    def _terminate(self, name: str) -> None:
        if terminate(self.procs.get(name), EXIT_TIMEOUT_S):
            with open(self.run_dir / f"{name}.log", "a") as log:
                log.write(f"\n[can_bench] no exit {EXIT_TIMEOUT_S} s after SIGTERM: killed\n")

    def close(self) -> None:
        for name in list(self.procs):
            proc = self.procs[name]
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        if getattr(self, "bus", None) is not None:
            self.bus.shutdown()
            self.bus = None
        self.session.close()

    def _collect(self) -> CanRunResult:
        can_dir = self.run_dir / "can"
        for name, path in (("mtq", can_dir / BOARD_NAME), ("canbus", can_dir / REPORT_NAME)):
            if not path.is_file():
                log = (self.run_dir / f"{name}.log").read_text(errors="replace")[-3000:]
                raise RuntimeError(f"node {name} left no {path.name} (exit {self.procs[name].returncode}):\n{log}")
        return read_run(self.run_dir, self.config, self.driver, events=list(self.events),
                        commanded=list(self.commanded), sent=list(self.sent), mtq_applied=list(self.mtq_applied),
                        command_start_ns=self.command_start_ns, last_command_ns=self.last_command_ns,
                        board_drain_s=self.board_drain_s)


def read_run(run_dir: Path, config: CanConfig, driver: MagnetorquerDriver, **flight_side) -> CanRunResult:
    """A run's CanRunResult: what the board and the bus model wrote into <run_dir>/can/
    (bench.bus.can.nodes), the capture, the driver's counts, and the flight side's own record
    (`flight_side`: the remaining CanRunResult fields)."""
    can_dir = run_dir / "can"
    protocol = p.Protocol(config.node_id)

    def names(path: Path, channel: str | None = None) -> Counter:
        if not path.is_file():
            return Counter()
        return Counter(p.frame_kind(protocol, m) for m in can.LogReader(str(path))
                       if channel is None or m.channel == channel)

    injections = [json.loads(line) for line in (can_dir / INJECTIONS_NAME).read_text().splitlines() if line]
    return CanRunResult(
        board=json.loads((can_dir / BOARD_NAME).read_text()),
        report=json.loads((can_dir / REPORT_NAME).read_text()),
        injections=injections,
        wire=names(run_dir / CAPTURE_NAME),
        dropped=names(can_dir / ACCOUNTING_NAME, channel="dropped"),
        driver_sent=driver.sent_frames,
        driver_received=Counter(driver.received),
        run_dir=run_dir,
        **flight_side,
    )


def write_scenario(path: Path, can_section: dict, name: str = "can-faults", seed: int = 1) -> Path:
    """A scenario file (JSON, which load_scenario reads like TOML) with only a [can] section."""
    path = path.with_suffix(".json")
    path.write_text(json.dumps({"name": name, "run": {"seed": seed}, "can": can_section}, indent=1))
    return path
