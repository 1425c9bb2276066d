"""`bench run`, `bench node` and `bench scenarios`: starting the loop as separate processes.

The launcher opens the hub session every node connects to, starts each node as its own OS process
(`bench node NAME ...`), waits until all are alive, follows the plant's progress, and shuts
everything down on success, on Ctrl-C or SIGTERM, and when a node dies, hangs or the plant's state
diverges, or its steps stop advancing (bench/runtime/progress_watchdog.py: the stage that stopped is
named). Then it writes metrics.json and the report, marked partial with the reason when the run
did not finish. The nodes die with it even when it is killed (bench/runtime/ownership.py); a second
Ctrl-C kills them at once and exits within a bounded time.

Exit codes: 0 done, 1 a process failed or hung or the run stalled, 2 bad input (nothing started),
3 the plant's state diverged, 130 interrupted (SIGINT), 143 terminated (SIGTERM).
"""
from __future__ import annotations

import collections
import dataclasses
import fcntl
import os
import secrets
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import msgspec
import zenoh

from bench.bus import acl, data_auth, keys
from bench.bus.can import run_key
from bench.bus.can.sim_window import bus_on_simulated_time
from bench.bus.presence import PresenceQuery, PresenceResponder, PresenceWatcher
from bench.bus.schemas import ProcessStats, StepDone, decode, MalformedMessage
from bench.bus.certs import CertificateError, identity_files, read_secoc_key, write_deployment_certs
from bench.bus.deployment import LAUNCHER, Deployment, DeploymentError, load_deployment
from bench.bus.session import SessionConfigError, SessionOptions, free_loopback_port, loopback_endpoint, open_session
from bench.contract.document import CONTRACT_FILE, write_contract
from bench.controller.config import PLANNED_LAWS
from bench.plant.divergence import EXIT_DIVERGED, read_divergence
from bench.runtime.node import NODES
from bench.runtime.ownership import CpuProgress, child_environment, kill_group, process_state
from bench.runtime import zygote as node_zygote
from bench.runtime.reports import REPORT_KEY_ENV, is_signed_by, new_report_key
from bench.runtime.process import start_node
from bench.runtime.progress_watchdog import ProgressWatchdog
from bench.scenario import EXTERNAL_PARTS, LivelinessConfig, Scenario, ScenarioError, builtin_names, load_scenario, parse_scenario

EXIT_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143
STARTUP_TIMEOUT_S = 120.0
STARTUP_IDLE_S = 5.0      # a starting node whose CPU time did not advance this long is stuck
SHUTDOWN_GRACE_S = 5.0
FOLLOW_PERIOD_S = 0.1     # how often the launcher checks its children and moves the progress bar
# After a second Ctrl-C (or SIGTERM) the launcher kills every node and exits within this, even if
# a Zenoh call it is in never returns.
HARD_EXIT_S = 2.5
LOCK_FILE = ".lock"


class NodeFailed(RuntimeError):
    pass


class Diverged(RuntimeError):
    pass


class RunInterrupted(BaseException):
    """SIGINT or SIGTERM to the launcher (a BaseException, like KeyboardInterrupt)."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum

    @property
    def exit_code(self) -> int:
        return EXIT_INTERRUPTED if self.signum == signal.SIGINT else EXIT_TERMINATED


class RunIdTaken(ValueError):
    """The run id is in use by a live run, or its directory holds an earlier run."""


# ------------------------------------------------------------------------------------------------
# Which processes a scenario needs
# ------------------------------------------------------------------------------------------------
def nodes_for(scenario: Scenario) -> list[str]:
    """In start order (they stop in stop_stages' order). The recorder first and last, so it sees
    everything; the CAN bus and board before the flight side and after it, so the driver never sees
    the board vanish at shutdown."""
    names = ["recorder"] if "recorder" in NODES else []
    if scenario.can is not None:
        # On simulated time the board runs with the bus model, in canbus (bench/bus/can/lockstep_bus.py).
        if not board_is_external(scenario):     # else the driver and the plant are on the board's bus
            names += ["canbus"] if bus_on_simulated_time(scenario) else ["canbus", "mtq"]
    names += ["plant", "estimator", "controller"]
    if scenario.kind == "attitude" and scenario.attitude_control.law in PLANNED_LAWS:
        names.append("planner")    # MILQR plans for the controller's tracker (issue 12)
    return names


EXTERNAL_HOST = "external"   # the "host" of a part provided from outside (docs/contract.md)


def external_parts(scenario: Scenario) -> dict[str, str]:
    """[run] external's Zenoh nodes: node -> EXTERNAL_HOST. They join as nodes on other hosts do
    (not spawned, waited for and watched by their liveliness token), so they reuse the `remote`
    placement. An external board is no Zenoh node (it is on the CAN bus only): not in here, but
    nodes_for starts neither the simulated board nor the bus model for it."""
    external = scenario.run.external
    if len(set(external)) != len(external):
        raise ScenarioError(f"run.external: a part named twice ({', '.join(external)})")
    if "board" in external:
        if scenario.kind != "attitude" or scenario.can is None:
            raise ScenarioError("run.external: \"board\" is the magnetorquer board on the CAN bus: the attitude "
                                "loop with [can] only")
        if scenario.run.mode == "lock-step" and scenario.can.lock_step_clock == "simulated":
            raise ScenarioError("run.external: an external \"board\" runs on its own (wall) clock: in lock-step "
                                "[can] lock_step_clock must be \"auto\" or \"wall\", not \"simulated\" "
                                "(and the board must acknowledge its commands with MTQ_TLM_SETPOINT; a board "
                                "without it runs in real time only: docs/can-bus.md)")
    return {name: EXTERNAL_HOST for name in external if name != "board"}


def board_is_external(scenario: Scenario) -> bool:
    return "board" in scenario.run.external


BOARD_SIDE_NODES = ("mtq", "canbus")    # what an external board replaces: the simulated board and the bus model
WATCHERS = ("recorder", "live")          # they stop last: every other node's last messages are theirs too
LIVE_NODE = "live"                       # `--live`: the Foxglove WebSocket server (bench/live/node.py, docs/live.md)
LIVE_DEFAULT_PORT = 8765                 # Foxglove's default WebSocket port


def with_driver_on_the_board_bus(scenario: Scenario) -> Scenario:
    """An external board has no bus model between it and the driver: unless [can.driver_bus] names
    the driver's own bus, the driver (and the plant, which hears the board's telemetry) open the
    board's bus ([can.board_bus], else the transport on board_channel). Written into the run's
    scenario.json, so an external controller started from it opens the same bus."""
    if not board_is_external(scenario) or scenario.can.driver_bus is not None:
        return scenario
    can_config = msgspec.structs.replace(scenario.can, driver_bus=scenario.can.bus_spec("board"))
    return msgspec.structs.replace(scenario, can=can_config)


# ------------------------------------------------------------------------------------------------
# Processes
# ------------------------------------------------------------------------------------------------
@dataclass
class Child:
    name: str
    process: subprocess.Popen | node_zygote.ForkedProcess    # forked by the zygote: the same methods
    log_path: Path

    def tail(self, lines: int = 8) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""


class ProcessGroup:
    """All nodes of a run in one process group (the first node leads it), killed as one."""

    def __init__(self):
        self.pgid: int | None = None
        self.report_keys: dict[int, bytes] = {}    # pid -> the secret its reports are signed with
        self._next_key: bytes | None = None

    def popen_kwargs(self) -> dict:
        # A group of their own: a terminal's Ctrl-C reaches the launcher only, which stops the
        # nodes in stages (the recorder last) instead of all at once. Each node gets its own
        # report key in its environment (bench/runtime/reports.py), never on its command line.
        self._next_key = new_report_key()
        return {"process_group": self.pgid or 0, "env": child_environment({REPORT_KEY_ENV: self._next_key.hex()})}

    def joined(self, process: subprocess.Popen) -> None:
        if self.pgid is None:
            self.pgid = process.pid
        if self._next_key is not None:
            self.report_keys[process.pid], self._next_key = self._next_key, None

    def kill(self) -> None:
        kill_group(self.pgid)


def _spawn(name: str, run_id: str, scenario_path: Path, hub: str, run_dir: Path, peers: list[str],
           zenoh_config: str | None, group: ProcessGroup | None = None,
           extra_args: list[str] | None = None, zygote: node_zygote.Zygote | None = None) -> Child:
    log_path = run_dir / "logs" / f"{name}.log"
    group = group or ProcessGroup()
    process = start_node(name, run_id, scenario_path, hub, run_dir, log_path, peers, zenoh_config,
                         popen_kwargs=group.popen_kwargs(), extra_args=extra_args, zygote=zygote)
    group.joined(process)
    return Child(name, process, log_path)


def stop_stages(names: list[str]) -> list[list[str]]:
    """The order nodes stop in, each stage's nodes at once: the loop and the flight side, then
    the bus and the board (so the driver never sees the board vanish), then the recorder and the
    live view (so they record and show every other node's last messages)."""
    stages = [[n for n in names if n not in (*BOARD_SIDE_NODES, *WATCHERS)],
              [n for n in names if n in BOARD_SIDE_NODES],
              [n for n in names if n in WATCHERS]]
    return [stage for stage in stages if stage]


def _stop_children(children: list[Child], grace_s: float = SHUTDOWN_GRACE_S) -> None:
    """SIGTERM stage by stage (stop_stages), then SIGKILL whatever is left. A child still working
    after grace_s (its CPU time advancing: a recorder finishing its file on a busy host) is given
    up to three times that; one that idles is killed at grace_s."""
    by_name = {c.name: c for c in children}
    for stage in stop_stages([c.name for c in children]):
        stopping = []
        for child in (by_name[n] for n in stage):
            if child.process.poll() is None:
                try:
                    child.process.send_signal(signal.SIGTERM)
                    stopping.append(child)
                except ProcessLookupError:
                    pass
        for child in stopping:
            _wait_exit_while_working(child.process, grace_s)
    _kill_children(children)


def _wait_exit_while_working(process: subprocess.Popen, grace_s: float) -> None:
    started = time.monotonic()
    progress = CpuProgress(process.pid)
    while True:
        try:
            process.wait(timeout=0.02)    # a forked node's wait returns as soon as the zygote reports its exit
            return
        except subprocess.TimeoutExpired:
            pass
        now = time.monotonic()
        idle_s = progress.idle_s(now)
        if now - started > grace_s and (idle_s > STARTUP_IDLE_S or now - started > 3 * grace_s):
            return


def _kill_children(children: list[Child]) -> None:
    for child in children:
        if child.process.poll() is None:
            try:
                child.process.kill()
                child.process.wait(timeout=5.0)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                pass


def _check_children(children: list[Child], allowed_done: set[str]) -> None:
    # A node that failed (non-zero code) is named before one that exited 0 early: two seen exited
    # by the same poll were named in start order, so a plant that ended after the bus model died
    # was blamed ("process 'plant' exited with code 0").
    exited = [(child, child.process.poll()) for child in children]
    for child, code in sorted(exited, key=lambda item: item[1] == 0):
        if code is None:
            continue
        if code != 0 or child.name not in allowed_done:
            raise NodeFailed(
                f"process '{child.name}' (pid {child.process.pid}) exited with code {code}; "
                f"last lines of {child.log_path}:\n{child.tail()}"
            )


@dataclass
class TokenLoss:
    """A node whose alive token vanished: when, and its CPU time then (to tell hung from slow)."""

    since_s: float
    cpu_ticks: int | None


def _check_liveliness(children: list[Child], lost: dict[str, TokenLoss], liveliness: LivelinessConfig,
                      final: bool = False) -> None:
    """A node silent on the control plane (no authentic presence answer for a lease: `lost`, from
    _follow_run's PresenceWatcher) while its process runs on is hung, if it is stopped (state T:
    SIGSTOP, a debugger) for stopped_grace_s, or if it stays silent for hang_timeout_s.

    A node starved of CPU on a busy machine may miss its lease too; it is still runnable and
    answers again, so it is not called hung before hang_timeout_s. `final`: the run is ending
    anyway (a peer gave up on it): any node still without its token is the cause to name.

    A zombie (state Z) has exited: its exit status, once its parent collects it, says how it
    ended. It is not called hung; only one whose status stays uncollected for another
    hang_timeout_s is named, as such. (Seen on a loaded machine: a plant that had finished its run
    stayed a zombie for over 15 s, its process not yet fully exited, and the run was called failed.)
    """
    now = time.monotonic()
    for name, loss in list(lost.items()):
        child = next((c for c in children if c.name == name), None)
        if child is None or child.process.poll() is not None:
            continue
        state = process_state(child.process.pid)
        if state is None:
            continue
        away_s = now - loss.since_s
        if state.state == "Z":
            if away_s >= 2 * liveliness.hang_timeout_s:
                raise NodeFailed(f"process '{name}' (pid {child.process.pid}) exited, but its exit status was not "
                                 f"collected {away_s:.1f} s after its liveliness lease ran out (state Z)")
            continue
        progress = "no CPU progress" if loss.cpu_ticks == state.cpu_ticks else "CPU time still advancing"
        if state.stopped and (final or away_s >= liveliness.stopped_grace_s):
            raise NodeFailed(
                f"process '{name}' (pid {child.process.pid}) is stopped (state {state.state}, {progress}): its "
                f"liveliness lease ran out {away_s:.1f} s ago (no authenticated presence answer since)"
            )
        if final or away_s >= liveliness.hang_timeout_s:
            raise NodeFailed(
                f"process '{name}' (pid {child.process.pid}) stopped answering on Zenoh: its liveliness lease "
                f"ran out {away_s:.1f} s ago (state {state.state}, {progress}; hung, or cut off from the bus)"
            )


# ------------------------------------------------------------------------------------------------
# bench run
# ------------------------------------------------------------------------------------------------
def _new_run_id(scenario: Scenario) -> str:
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S")
    return f"{scenario.name}-{stamp}-{secrets.token_hex(2)}"


def _apply_overrides(scenario: Scenario, args) -> Scenario:
    run = scenario.run
    if args.mode:
        run = msgspec.structs.replace(run, mode=args.mode)
    if getattr(args, "external", None):
        run = msgspec.structs.replace(run, external=sorted(set(run.external) | set(args.external)))
    if args.steps is not None:
        from bench.scenario import MAX_STEPS

        if not 1 <= args.steps <= MAX_STEPS:
            raise ScenarioError(f"--steps must be 1-{MAX_STEPS}, got {args.steps}")
        run = msgspec.structs.replace(run, steps=args.steps)
    return parse_scenario(msgspec.to_builtins(msgspec.structs.replace(scenario, run=run)), "command line")


@dataclass
class RunEnding:
    code: int
    reason: str | None      # None: the run finished; else why it ended early (first line)


def _follow_run(session, run_id: str, children: list[Child], n_steps: int, show_progress: bool,
                liveliness: LivelinessConfig, run_dir: Path, reports: "StatsCollector",
                remote: dict[str, str] | None = None, interrupted=lambda: None,
                data_key: bytes | None = None, watchdog: ProgressWatchdog | None = None) -> None:
    """Block until the plant finishes; raise NodeFailed if any process dies or hangs first,
    Diverged if the plant stopped on a diverged state.

    The end of the run is the plant process's exit and its code, which nobody on the bus can fake;
    the plant's StepDone messages only move the progress bar and open `reports`' window for the
    stats of remote nodes, and count only when signed by the plant (`reports.genuine_step`).
    remote: node -> host of the nodes on other hosts; their presence answers are all we see of them.
    interrupted: called at every look (SignalGuard.check: a signal whose exception was lost).
    data_key: the run's key, under which every node's presence answers must be signed.
    watchdog: ends a run whose steps stop advancing, naming the stage (_check_progress).
    """
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    # Steps done so far, written by Zenoh's thread and read every FOLLOW_PERIOD_S: the launcher's
    # thread must not wake once per step (in lock-step it would compete with the loop's processes
    # for the cores, once per cycle, for a progress bar).
    steps_done = [0]
    waits: collections.deque = collections.deque(maxlen=16)   # the plant's wait reports, for the watchdog

    def on_step(sample) -> None:
        try:
            message = decode(sample.payload.to_bytes(), StepDone)
        except MalformedMessage:
            return   # garbage on the status topic must not stop the launcher
        if message.header.run_id != run_id or not reports.genuine_step(message):
            return   # not the plant's: counted as forged by `reports`
        if message.waiting:
            waits.append((message.header.seq, message.waiting, message.waited_s, time.monotonic()))
            return   # a wait, not a step
        steps_done[0] = max(steps_done[0], min(message.header.seq + 1, n_steps))
        if message.finished:
            reports.accept()

    subscriber = session.declare_subscriber(keys.key(run_id, keys.STATUS_STEP), on_step)
    lost: dict[str, TokenLoss] = {}
    pids = {c.name: c.process.pid for c in children}
    # Liveliness is an authenticated presence answer (bench/bus/presence.py), not a Zenoh token:
    # a token anyone on the bus can declare would hide a hung node.
    watcher = PresenceWatcher(session, run_id, data_key, set(pids) | set(remote or {}), liveliness.lease_s).start()

    def note_silent() -> None:
        now = time.monotonic()
        for name in watcher.names:
            since = watcher.silent_since(name, now)
            if since is None:
                lost.pop(name, None)    # answering (again): slow, not hung
            elif name not in lost:
                state = process_state(pids[name]) if name in pids else None
                lost[name] = TokenLoss(since, state.cpu_ticks if state else None)
    plant = next(c for c in children if c.name == "plant")
    columns = [TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn()]
    try:
        with Progress(*columns, disable=not show_progress, transient=False) as progress:
            task = progress.add_task("steps", total=n_steps)
            done = 0
            while plant.process.poll() is None:
                try:
                    # The plant may finish between the loop's test and this check (seen on a
                    # loaded machine: a clean run called failed): its exit is judged after the loop.
                    _check_children(children, allowed_done={"plant"})
                except NodeFailed:
                    # A peer that noticed a hung node first may exit before the grace period is
                    # over; the hung one is the cause to name.
                    _check_liveliness(children, lost, liveliness, final=True)
                    raise
                note_silent()
                _check_liveliness(children, lost, liveliness)
                _check_remote(watcher.query, remote or {}, lost)
                _check_progress(watchdog, steps_done[0], waits, children)
                interrupted()
                time.sleep(FOLLOW_PERIOD_S)
                if steps_done[0] != done:
                    done = steps_done[0]
                    progress.update(task, completed=done)
            progress.update(task, completed=steps_done[0])
    finally:
        subscriber.undeclare()
        watcher.stop()
    if plant.process.returncode == EXIT_DIVERGED:
        divergence = read_divergence(run_dir)
        raise Diverged(f"plant {divergence.describe()}" if divergence else "plant state diverged (no divergence.json)")
    if plant.process.returncode != 0:
        _check_progress(watchdog, steps_done[0], waits, children, final=True)
        _check_liveliness(children, lost, liveliness, final=True)
        _check_children([plant], allowed_done=set())


def _check_progress(watchdog: ProgressWatchdog | None, steps_done: int, waits, children: list[Child],
                    final: bool = False) -> None:
    """The progress watchdog's look (bench/runtime/progress_watchdog.py): NodeFailed naming the stage
    if the run's steps stopped advancing for its bound; `final`: the plant exited with an error,
    named by the stage it was waiting for if it gave up waiting."""
    if watchdog is None:
        return
    now = time.monotonic()
    watchdog.step_done(steps_done, now)
    while waits:
        watchdog.plant_waits(*waits.popleft())
    stall = watchdog.gave_up(now) if final else watchdog.look(now)
    if stall is not None:
        states = {c.name: process_state(c.process.pid) for c in children if c.process.poll() is None}
        raise NodeFailed(stall.describe(watchdog.bound, [n for n, s in states.items() if s is not None and s.stopped]))


def _check_remote(presence: PresenceQuery, remote: dict[str, str], lost: dict[str, "TokenLoss"]) -> None:
    """A node on another host that stopped answering presence queries died, hung, or lost its link.

    Asked again, with a longer wait, before it is declared lost: with a router, routes change
    while peers connect to each other directly (seen in the router test of tests/test_deployment.py).
    """
    for name in [n for n in lost if n in remote]:
        if name in presence.ask(name, timeout_s=1.0):
            lost.pop(name)
            continue
        raise NodeFailed(f"process '{name}' on host '{remote[name]}' left the bus (no authenticated liveliness "
                         f"answer for a lease: it died, hung, or its link to this host is down)")


def _stop_remote(presence: PresenceQuery, launcher_presence: PresenceResponder, launcher_token,
                 remote: dict[str, str], grace_s: float = SHUTDOWN_GRACE_S) -> None:
    """Nodes on other hosts stop when the launcher stops answering presence queries (its token's
    delete makes them ask at once: node.py stop_when_gone); wait until they stop answering too."""
    launcher_presence.undeclare()
    launcher_token.undeclare()
    deadline = time.monotonic() + grace_s
    while remote and time.monotonic() < deadline:
        if not set(presence.ask()) & set(remote):
            return
        time.sleep(0.05)


class StatsCollector:
    """The reports the launcher takes from its processes: each one's ProcessStats (a node publishes
    them once, as it stops) and the plant's StepDone (`genuine_step`).

    Anyone on the bus of a plain run can publish either, under any name. A process this launcher
    started signs its reports with the secret handed to it at start (`trust`; bench/runtime/reports.py),
    so a report naming it is taken only with a valid signature under that secret, its stats only
    once (a replay of them is counted as `replayed`, not taken); any other report naming it is
    dropped and counted under its `forged`. Reports naming no process of the run are ignored.

    A process on another host (`remote`, a deployment) was not started here and has no secret: in
    a secure run, access control lets only its certificate publish its stats. They are taken only
    once the plant has reported its last step or the launcher is stopping the nodes (earlier ones
    are kept aside as premature), the first per process (later ones counted as conflicting)."""

    def __init__(self, session, run_id: str, names: set[str], remote: set[str] | frozenset = frozenset()):
        self.run_id = run_id
        self.names = names
        self.remote = set(remote)
        self.report_keys: dict[str, bytes] = {}
        self.stats: dict = {}
        self.forged: dict[str, int] = {}      # process -> reports naming it that it did not sign
        self.accepting = False
        self.premature = 0
        self._premature: dict = {}
        self._lock = threading.Lock()        # Zenoh delivers on several threads
        self._subscriber = session.declare_subscriber(keys.key(run_id, f"{keys.STATUS_STATS}/*"), self._on_stats)

    def trust(self, name: str, key: bytes) -> None:
        """`name` is a process this launcher started with `key`."""
        self.report_keys[name] = key

    def _genuine(self, name: str, message) -> bool:
        """A report naming `name`: signed with its key, or from a remote process (access control's)."""
        if name in self.remote:
            return True
        key = self.report_keys.get(name)
        if key is not None and is_signed_by(message, key):
            return True
        with self._lock:
            self.forged[name] = self.forged.get(name, 0) + 1
        return False

    def genuine_step(self, message: StepDone) -> bool:
        return self._genuine("plant", message)

    def _on_stats(self, sample) -> None:
        try:
            message = decode(sample.payload.to_bytes(), ProcessStats)
        except MalformedMessage:
            return
        if message.header.run_id != self.run_id or message.process not in self.names:
            return
        if not self._genuine(message.process, message):
            return
        entry = {"published": message.published, "malformed": message.malformed}
        if message.unauthentic:
            entry["unauthentic"] = message.unauthentic
        if message.realtime_priority:
            entry["realtime_priority"] = message.realtime_priority
        with self._lock:
            if message.process not in self.remote:
                # Signed by the process itself, which sends its stats once: a second is a replay.
                taken = self.stats.setdefault(message.process, entry)
                if taken is not entry:
                    taken["replayed"] = taken.get("replayed", 0) + 1
                return
            if not self.accepting:
                # Kept aside, the latest per process: a node's own stats are the last it sends, and
                # on a busy host they can overtake the plant's last-step message that opens the window.
                self.premature += 1
                self._premature[message.process] = entry
                return
            if message.process in self.stats:
                taken = self.stats[message.process]
                taken["conflicting"] = taken.get("conflicting", 0) + 1
                return
            self.stats[message.process] = entry

    def accept(self) -> None:
        self.accepting = True

    def wait_for_stats(self, names: set[str], timeout_s: float) -> None:
        """Until every process in `names` has reported its stats (each sends them as it stops), at
        most timeout_s: a node killed before it could send them never will."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                if names <= set(self.stats):
                    return
            time.sleep(0.005)

    def finish(self) -> None:
        """At the end of the run: a remote process whose stats came only before the window takes its
        latest early one, marked as such; the forged reports are counted under each process."""
        with self._lock:
            for process, entry in self._premature.items():
                self.stats.setdefault(process, {**entry, "premature": True})
            for process, count in self.forged.items():
                self.stats.setdefault(process, {})["forged"] = count

    def undeclare(self) -> None:
        self._subscriber.undeclare()


def _wait_alive(presence: PresenceQuery, children: list[Child], timeout_s: float = STARTUP_TIMEOUT_S,
                remote: dict[str, str] | None = None, show: bool = False, interrupted=lambda: None) -> None:
    """Until every node answers presence queries under the run's key (bench/bus/presence.py). Past timeout_s, a node still starting is given up
    to three times that while its CPU time advances (slow on a busy machine), not while it idles.
    show: say on stderr when each node comes up (the terminal is never blank while they start).
    interrupted: called at every look, as in _follow_run."""
    names = {c.name for c in children} | set(remote or {})
    started = time.monotonic()
    progress = {c.name: CpuProgress(c.process.pid) for c in children}
    announced: set[str] = set()
    plant = next((c for c in children if c.name == "plant"), None)
    others = [c for c in children if c is not plant]
    while True:
        # The plant steps only once it has seen every peer, so a plant that ended cleanly ran the
        # whole loop: a short run can end before this query sees every token (seen through a
        # router: 20 steps in 60 ms), or stop on divergence (CI97: at step 4, 36 ms in). The run's
        # end is judged after this, by _follow_run. Another node that failed is named first.
        _check_children(others, allowed_done=set())
        if plant is not None:
            if plant.process.poll() in (0, EXIT_DIVERGED):
                return
            _check_children([plant], allowed_done=set())
        alive = set(presence.ask())
        for name in sorted((alive & names) - announced) if show else ():
            print(f"bench: {name} up after {time.monotonic() - started:.1f} s", file=sys.stderr)
            announced.add(name)
        if names <= alive:
            return
        now = time.monotonic()
        idle_s = {name: p.idle_s(now) for name, p in progress.items()}
        missing = sorted(names - alive)
        if now - started > timeout_s:
            # A remote node (no local process to watch) never counts as still working.
            still_working = all(idle_s.get(n, float("inf")) < STARTUP_IDLE_S for n in missing)
            if not still_working or now - started > 3 * timeout_s:
                refused = {n: presence.refused_by_name[n] for n in missing if presence.refused_by_name.get(n)}
                why = "".join(f"; {n}: {k} presence answer(s) refused, not signed under the run's key (bus.key)"
                              for n, k in refused.items())
                raise NodeFailed(f"processes not alive after {now - started:.0f} s: {', '.join(missing)}{why}")
        interrupted()
        time.sleep(0.05)


class RunDirClaim:
    """runs/<run_id>, created for this run and locked while it lasts (flock: released by the kernel
    when the launcher dies, however it dies). A live id, or a directory holding an earlier run, is
    refused before anything is written or started."""

    def __init__(self, run_dir: Path):
        self.run_dir = run_dir
        run_dir.parent.mkdir(parents=True, exist_ok=True)
        try:
            run_dir.mkdir()
        except FileExistsError:
            raise RunIdTaken(self._taken_message()) from None
        self._lock = open(run_dir / LOCK_FILE, "w")
        fcntl.flock(self._lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        self._lock.write(str(os.getpid()))
        self._lock.flush()

    def _taken_message(self) -> str:
        run_id = self.run_dir.name
        try:
            with open(self.run_dir / LOCK_FILE) as f:
                try:
                    fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    return f"run id {run_id!r} is in use by a running bench (pid {f.read().strip() or '?'}); choose another --run-id"
        except OSError:
            pass
        return f"run id {run_id!r}: {self.run_dir} already holds a run; choose another --run-id or remove it"

    def release(self) -> None:
        self._lock.close()


class SignalGuard:
    """SIGINT and SIGTERM during a run. The first is noted, and the launcher's next look (`check`,
    at most a few tenths of a second away in its waits) raises RunInterrupted there; it stops the
    nodes in order and writes what the run left. A second one kills every node at once and arms a
    hard exit HARD_EXIT_S later.

    The handler itself never raises: Python runs it between any two bytecodes of the main thread,
    and an exception raised there can land inside an import's module-lock bookkeeping (dropped as
    "Exception ignored", CI105) or leave that lock half taken, after which the report's import
    waited forever (CI2 of issue 44: "stopping all processes", "building the report", then no
    exit for 120 s)."""

    def __init__(self, group: ProcessGroup):
        self.group = group
        self.first: int | None = None
        self.delivered = False      # the first signal's RunInterrupted reached the launcher's handler
        self.hurry = False
        self._saved: dict = {}

    def __enter__(self) -> "SignalGuard":
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, signal.SIGTERM):
                self._saved[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for signum, handler in self._saved.items():
            signal.signal(signum, handler)

    def check(self) -> None:
        """Raise the first signal's RunInterrupted, once (the launcher's waits call this at every
        look; the cleanup that follows is not interrupted again)."""
        if self.first is not None and not self.delivered:
            self.delivered = True
            raise RunInterrupted(self.first)

    def _handle(self, signum, _frame) -> None:
        if self.first is None:
            self.first = signum       # raised at the next look (check), never from here
            return
        if not self.hurry:
            self.hurry = True
            self.group.kill()
            code = RunInterrupted(self.first).exit_code
            timer = threading.Timer(HARD_EXIT_S, os._exit, (code,))
            timer.daemon = True
            timer.start()


@dataclass
class Placement:
    """Where this run's sessions are: the hub's session options, what each local node is told,
    and which nodes run on other hosts (node -> host). Local and plain unless asked otherwise."""

    hub: SessionOptions
    hub_endpoint: str
    node_args: list[str]
    remote: dict[str, str]


def local_placement(port: int | None, zenoh_config: str | None, cert_dir: Path | None = None) -> Placement:
    """`bench run` on this host: the hub on loopback; with cert_dir, mutual TLS and access control."""
    protocol = "tls" if cert_dir else "tcp"
    hub = loopback_endpoint(port or free_loopback_port(), protocol)
    identity = identity_files(cert_dir, LAUNCHER) if cert_dir else None
    options = SessionOptions(listen=(hub,), config_file=Path(zenoh_config) if zenoh_config else None, identity=identity)
    return Placement(options, hub, ["--cert-dir", str(cert_dir)] if cert_dir else [], {})


def deployment_placement(deployment: Deployment, deployment_file: Path, names: list[str],
                         zenoh_config: str | None) -> Placement:
    host = deployment.launcher_host
    if deployment.host_of("plant") != host:
        raise DeploymentError(f"the plant runs on {deployment.host_of('plant')!r}: it must be on the launcher's "
                              f"host {host!r} (the launcher follows the plant's progress)")
    deployment.check_certificates(host, names)
    options = dataclasses.replace(deployment.hub_options(), config_file=Path(zenoh_config) if zenoh_config else None)
    remote = {n: deployment.host_of(n) for n in names if deployment.host_of(n) != host}
    return Placement(options, deployment.rendezvous, ["--deployment", str(Path(deployment_file).resolve()), "--host", host],
                     remote)


def make_local_certs(cert_dir: Path) -> Path:
    """A throw-away CA and certificates for one secure local run (`bench run --secure`)."""
    write_deployment_certs(cert_dir, "local", {name: ("127.0.0.1",) for name in acl.identities()})
    return cert_dir


def _data_key(identity) -> bytes:
    """The run's data-topic key: derived from the deployment's secoc.key when the run has a
    certificate directory holding one (so nodes on other hosts derive it too), else new."""
    if identity is not None:
        secoc_hex = read_secoc_key(identity.ca_path.parent)
        if secoc_hex:
            return data_auth.deployment_key(secoc_hex)
    return data_auth.new_key()


def run_bench(scenario: Scenario, run_id: str, runs_dir: Path, port: int | None, show_progress: bool = True,
              zenoh_config: str | None = None, write_report: bool = True,
              placement: Placement | None = None, live_port: int | None = None,
              allow_live_faults: bool = False) -> tuple[int, Path]:
    """Run a scenario as separate processes. Returns (exit code, run directory).

    placement: where the sessions are (default: this host, loopback, plain TCP).
    live_port: also start the live view (node "live": a Foxglove WebSocket server on this loopback
    port, docs/live.md). allow_live_faults: canbus and the board take faults injected while the run
    runs (`bench inject`, the live view's service); refused otherwise.
    """
    external = external_parts(scenario)      # bad input: before anything is opened
    scenario = with_driver_on_the_board_bus(scenario)
    # Marked "external" in metrics.json; not waited for (no Zenoh node): the board on the CAN bus.
    board_side = dict.fromkeys(BOARD_SIDE_NODES, EXTERNAL_HOST) if board_is_external(scenario) else {}
    placement = placement or local_placement(port, zenoh_config)
    if scenario.can is not None:
        from bench.bus.can.preflight import check_run_buses, roles_on_this_host

        # CanBusError (a ValueError): exit 2, nothing started. Only the buses of nodes started here:
        # a deployment's node on another host opens its channel there.
        check_run_buses(scenario.can, roles_on_this_host(scenario.can, {**placement.remote, **external, **board_side}))
    hub = placement.hub_endpoint
    if live_port is not None:
        from bench.live.node import check_live_port

        check_live_port(live_port)     # taken: exit 2, nothing started
    # The zygote before any session of ours (the one `bench run` started first, if it matches): it
    # imports the nodes' packages while the launcher goes on, and is started by fork+exec, never
    # forked from a process running Zenoh's threads.
    zygote = node_zygote.Zygote.for_launcher(child_environment(), show_progress)
    # The session first: a taken port must fail before anything is written or started.
    lease_ms = int(round(scenario.run.liveliness.lease_s * 1000))
    try:
        session = open_session(dataclasses.replace(placement.hub, lease_ms=lease_ms))
    except BaseException:
        if zygote is not None:
            zygote.close()
        raise
    launcher_token = session.liveliness().declare_token(keys.key(run_id, f"{keys.ALIVE}/{LAUNCHER}"))
    remote = {**placement.remote, **external}
    run_dir = runs_dir / run_id
    try:
        claim = RunDirClaim(run_dir)
    except BaseException:
        session.close()
        if zygote is not None:
            zygote.close()
        raise
    (run_dir / "logs").mkdir()
    scenario_path = run_dir / "scenario.json"
    # The CAN bus's SecOC key (the deployment's, else new per run) reaches the nodes only here (0600).
    identity = placement.hub.identity
    scenario = run_key.with_run_key(scenario, identity.ca_path.parent if identity else None)
    run_key.write_private(scenario_path, msgspec.json.format(msgspec.json.encode(scenario)))
    # This run's numbers and meanings for an outside node (hub, lease, step period, envelopes, frames;
    # bench/contract/document.py), before bus.key: a node that has the key finds it there. No secret in it.
    write_contract(run_dir / CONTRACT_FILE, scenario, run_id, hub)
    # The data topics' key (bench/bus/data_auth.py): the deployment's, else new per run; bus.key
    # (0600) beside scenario.json is where this run's nodes, by hand or outside ones too, read it.
    data_key = _data_key(identity)
    run_key.write_private(run_dir / data_auth.KEY_FILE, (data_key.hex() + "\n").encode())
    # The launcher answers presence queries too: nodes on other hosts stop when it no longer does.
    launcher_presence = PresenceResponder(session, run_id, LAUNCHER, data_key)
    launcher_presence.ready = True     # nothing to wait for: its answer means the run is on
    presence = PresenceQuery(session, run_id, data_key)
    children: list[Child] = []
    group = ProcessGroup()
    started = time.monotonic()
    names = nodes_for(scenario) + ([LIVE_NODE] if live_port is not None else [])
    collector = StatsCollector(session, run_id, set(names), set(remote))
    stats = collector.stats
    ending = RunEnding(EXIT_FAILED, "the launcher failed")
    guard = SignalGuard(group)
    with guard:
        try:
            try:
                if show_progress:
                    print(f"bench: run {run_id}: starting {', '.join(n for n in names if n not in remote)}",
                          file=sys.stderr)
                for name in external:
                    print(f"bench: waiting for the external {name}: connect to {hub}, run id {run_id}, "
                          f"scenario {scenario_path}", file=sys.stderr)
                if board_side:
                    spec = scenario.can.driver_bus
                    print(f"bench: the magnetorquer board is external: the driver and the plant open {spec.interface} "
                          f"channel {spec.channel!r}; no simulated board, no bus model", file=sys.stderr)
                loop_peers = [n for n in names if n != "plant"]
                for name in names:
                    if name in remote:
                        continue
                    peers = loop_peers if name == "plant" else []
                    children.append(_spawn(name, run_id, scenario_path, hub, run_dir, peers, zenoh_config, group,
                                           placement.node_args + _live_args(name, live_port, allow_live_faults), zygote))
                    collector.trust(name, group.report_keys[children[-1].process.pid])
                _wait_alive(presence, children, scenario.run.liveliness.startup_timeout_s, remote,
                            show=show_progress, interrupted=guard.check)
                if live_port is not None or allow_live_faults:
                    _announce_live(run_id, live_port, allow_live_faults, data_key, runs_dir)
                if write_report:
                    _import_report_meanwhile()
                _follow_run(session, run_id, children, scenario.n_steps, show_progress, scenario.run.liveliness, run_dir,
                            reports=collector, remote=remote, interrupted=guard.check, data_key=data_key,
                            watchdog=ProgressWatchdog.for_scenario(scenario, time.monotonic()))
                guard.check()
                collector.accept()
                _stop_remote(presence, launcher_presence, launcher_token, remote)
                _stop_children(children)
                collector.wait_for_stats({c.name for c in children}, 0.1)   # the last ones are on their way
                _check_children(children, allowed_done={c.name for c in children})
                ending = RunEnding(0, None)
            except NodeFailed as exc:
                print(f"bench: error: {exc}", file=sys.stderr)
                ending = RunEnding(EXIT_FAILED, str(exc).splitlines()[0].split("; last lines of")[0])
            except Diverged as exc:
                print(f"bench: error: {exc}", file=sys.stderr)
                ending = RunEnding(EXIT_DIVERGED, str(exc))
            except (RunInterrupted, KeyboardInterrupt) as exc:
                guard.delivered = True
                signum = exc.signum if isinstance(exc, RunInterrupted) else signal.SIGINT
                print(f"bench: {signal.Signals(signum).name}: stopping all processes", file=sys.stderr)
                ending = RunEnding(RunInterrupted(signum).exit_code, f"interrupted by {signal.Signals(signum).name}")
            finally:
                collector.accept()
                if guard.hurry:
                    _kill_children(children)
                else:
                    _stop_children(children)
                group.kill()     # anything a node started
                collector.undeclare()
                collector.finish()
            _finish(run_dir, scenario, children, stats, time.monotonic() - started, ending, write_report and not guard.hurry,
                    {**remote, **{n: h for n, h in board_side.items() if n == "mtq"}})
        except RunInterrupted as exc:
            # The first signal came during the cleanup itself: the nodes go at once; only the
            # files may be missing, and `bench report RUN` can build them.
            _kill_children(children)
            group.kill()
            if ending.reason is None:
                ending = RunEnding(exc.exit_code, f"interrupted by {exc}")
        finally:
            session.close()
            claim.release()
            if zygote is not None:
                zygote.close()
    return ending.code, run_dir


def _live_args(name: str, live_port: int | None, allow_live_faults: bool) -> list[str]:
    """`bench node` options of live operation: the live view's port, and live faults for the nodes
    that take them (canbus's injector, the board's hardware)."""
    args = ["--live-port", str(live_port)] if name == LIVE_NODE and live_port is not None else []
    if allow_live_faults and name in (*BOARD_SIDE_NODES, LIVE_NODE):
        args.append("--allow-live-faults")
    return args


def _announce_live(run_id: str, live_port: int | None, allow_live_faults: bool, data_key: bytes, runs_dir: Path) -> None:
    """What to open and how to inject, on the terminal (docs/live.md)."""
    from bench.live.node import live_urls, service_token

    if live_port is not None:
        ws_url, app_url = live_urls(live_port)
        print(f"bench: live view: {ws_url} (Foxglove: Open connection > Foxglove WebSocket, or {app_url}); "
              f"layout docs/foxglove/live_layout.json", file=sys.stderr)
    if allow_live_faults:
        runs = "" if Path(runs_dir) == Path("runs") else f" --runs-dir {runs_dir}"
        how = f"bench: live faults allowed: bench inject {run_id}{runs} KIND [--duration S] [--axis x] ..."
        if live_port is not None:
            how += f", or the live view's service /inject_fault with \"token\": \"{service_token(data_key)}\""
        print(how, file=sys.stderr)
    else:
        print("bench: live faults refused (start the run with --allow-live-faults to inject them)", file=sys.stderr)


def _import_report_meanwhile() -> None:
    """Import the report's modules (matplotlib, ~0.5 s) on a thread while the run goes on, not
    after it, where the user waits for them; the launcher's own thread only follows the run."""
    def load() -> None:
        import bench.report.build  # noqa: F401
        import bench.report.summary  # noqa: F401

    threading.Thread(target=load, name="import-report", daemon=True).start()


def _finish(run_dir: Path, scenario: Scenario, children: list[Child], stats: dict, wall_s: float,
            ending: RunEnding, write_report: bool, remote: dict[str, str] | None = None) -> None:
    """metrics.json, the report and the summary from whatever the run left (bench.report.summary);
    none of them may turn an ending into a crash."""
    from bench.report import summary

    processes = {c.name: {"pid": c.process.pid, "exit_code": c.process.returncode} for c in children}
    for name, host in (remote or {}).items():   # started on their own hosts: no pid of ours
        processes[name] = {"host": host, "pid": None, "exit_code": None}
    try:
        metrics = summary.run_metrics(run_dir, scenario, processes, stats, wall_s, ending.code, ending.reason)
    except Exception as exc:     # noqa: BLE001 - a broken file must not hide how the run ended
        print(f"bench: could not write metrics.json: {exc}", file=sys.stderr)
        return
    html = None
    if write_report:
        print("bench: building the report", file=sys.stderr)
        try:
            from bench.report.build import write_report as build_report

            _, html = build_report(run_dir)
            metrics = summary.read_metrics(run_dir) or metrics
        except Exception as exc:     # noqa: BLE001
            print(f"bench: could not build the report ({exc}); `bench report {run_dir}` retries", file=sys.stderr)
    if ending.reason is None:
        summary.print_summary(metrics, run_dir, summary.command_wall_time_s())
    else:
        for line in unauthentic_drops(stats, run_dir):     # often why a loop with an outside node stalls
            print(f"bench: {line}", file=sys.stderr)
        print(f"bench: partial run ({ending.reason}); metrics: {run_dir / 'metrics.json'}", file=sys.stderr)
    if html is not None:
        print(f"report: {html}")


def unauthentic_drops(stats: dict, run_dir: Path) -> list[str]:
    """What each process dropped for its tag, named by the topic's publishers: "estimate/translation
    from 'estimator' dropped as forged by 'controller': 40 ..." (a node from outside that does not
    sign, or signs with another key, leaves a loop waiting for messages it did send)."""
    from bench.contract.table import topic_of

    lines = []
    for process, entry in sorted(stats.items()):
        for reason, by_topic in sorted((entry.get("unauthentic") or {}).items()):
            for topic, n in sorted(by_topic.items()):
                table = topic_of(topic)
                source = f" from {', '.join(repr(p) for p in table.publishers)}" if table is not None else ""
                lines.append(f"{topic}{source} dropped as {reason} by '{process}': {n} (no valid tag under the run's key, "
                             f"{run_dir / data_auth.KEY_FILE}, or a counter already seen)")
    return lines


def campaign_case(scenario: Scenario) -> dict:
    """One campaign row's metrics from a full multi-process run in a scratch directory
    (`bench campaign`, mode "processes"); a run that does not finish raises, naming the logs."""
    import contextlib
    import io
    import tempfile
    import zlib

    from bench.report.rundata import load_run
    from bench.studies.campaign_metrics import run_metrics

    run_id = keys.check_run_id(f"campaign-{zlib.crc32(scenario.name.encode()):08x}-{os.getpid()}")
    with tempfile.TemporaryDirectory(prefix="bench-campaign-") as runs_dir:
        with contextlib.redirect_stdout(io.StringIO()):           # the run's summary table
            code, run_dir = run_bench(scenario, run_id, Path(runs_dir), None, show_progress=False, write_report=False)
        if code != 0:
            logs = sorted((run_dir / "logs").glob("*.log"))
            tail = " | ".join(f"{p.stem}: {p.read_text().strip().splitlines()[-1:]}" for p in logs if p.stat().st_size)
            raise RuntimeError(f"bench run exited with {code}: {tail}")
        run = load_run(run_dir)
        commands = [m.body for m in run.on(keys.COMMAND_THRUST) if not m.body.get("fallback")]
        return run_metrics(run.trajectory["state_m_mps"], run.trajectory["thrust_n"], scenario.params(),
                           [c["solve_time_s"] for c in commands], [c.get("iterations", 0) for c in commands],
                           [c["ctrl_feasible"] for c in commands])


def cmd_run(args) -> int:
    try:
        scenario = _apply_overrides(load_scenario(args.scenario), args)
        run_id = keys.check_run_id(_new_run_id(scenario) if args.run_id is None else args.run_id)
        if args.port is not None and not 0 < args.port < 65536:
            raise ScenarioError(f"--port must be between 1 and 65535, got {args.port}")
        placement = None
        if args.deployment:
            if args.port is not None:
                raise DeploymentError("--port: the deployment file names the hub's endpoint")
            placement = deployment_placement(load_deployment(args.deployment), Path(args.deployment),
                                             nodes_for(scenario) + ([LIVE_NODE] if args.live is not None else []),
                                             args.zenoh_config)
        elif args.secure:
            # Not in runs/<run_id>: the run claims that directory new (a second run with a live id is refused).
            cert_dir = Path(args.cert_dir) if args.cert_dir else make_local_certs(Path(args.runs_dir) / ".certs" / run_id)
            placement = local_placement(args.port, args.zenoh_config, cert_dir)
        if args.live is not None and not 0 < args.live < 65536:
            raise ScenarioError(f"--live PORT must be between 1 and 65535, got {args.live}")
        code, _ = run_bench(scenario, run_id, Path(args.runs_dir), args.port, not args.no_progress, args.zenoh_config,
                            write_report=not args.no_report, placement=placement, live_port=args.live,
                            allow_live_faults=args.allow_live_faults)
        return code
    except (ScenarioError, SessionConfigError, DeploymentError, CertificateError, ValueError) as exc:
        print(f"bench: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    finally:
        node_zygote.Zygote.close_early()    # started by bench.cli for this run, if run_bench never took it


# ------------------------------------------------------------------------------------------------
# bench scenarios
# ------------------------------------------------------------------------------------------------
def cmd_scenarios(_args) -> int:
    for name in builtin_names():
        print(f"{name:28s} {load_scenario(name).description}")
    return 0


def add_commands(subparsers) -> None:
    run = subparsers.add_parser("run", help="run a scenario: plant, estimator and controller as processes")
    run.add_argument("scenario", nargs="?", help="built-in name or TOML file (default: rendezvous_lqr)")
    run.add_argument("--run-id", help="name of the run (default: scenario name and time)")
    run.add_argument("--runs-dir", default="runs", help="where run directories go (default: runs)")
    run.add_argument("--port", type=int, help="loopback TCP port of the hub session (default: a free one)")
    run.add_argument("--mode", choices=["lock-step", "real-time"], help="override the scenario's run.mode")
    run.add_argument("--steps", type=int, help="override the scenario's run.steps")
    run.add_argument("--zenoh-config", help="JSON5 Zenoh configuration applied under the bench's own settings")
    run.add_argument("--secure", action="store_true",
                     help="mutual TLS and access control on loopback, with certificates made for this run")
    run.add_argument("--cert-dir", help="with --secure: certificates to use (default: new ones in the run directory)")
    run.add_argument("--deployment", help="deployment TOML: which node runs on which host (see docs/security.md)")
    run.add_argument("--external", action="append", choices=list(EXTERNAL_PARTS),
                     help="a part provided from outside: not started, waited for under its name (docs/contract.md)")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    run.add_argument("--no-report", action="store_true", help="skip report.html/report.md (bench report RUN_DIR later)")
    run.add_argument("--live", nargs="?", type=int, const=LIVE_DEFAULT_PORT, metavar="PORT",
                     help=f"watch the run in Foxglove: a WebSocket server on 127.0.0.1:PORT (default {LIVE_DEFAULT_PORT}) "
                          "with the run's topics as they happen (docs/live.md); put it after the scenario")
    run.add_argument("--allow-live-faults", action="store_true",
                     help="take faults injected while the run runs (`bench inject`, the live view's service); "
                          "refused otherwise")
    run.set_defaults(func=cmd_run)

    scenarios = subparsers.add_parser("scenarios", help="list the built-in scenarios")
    scenarios.set_defaults(func=cmd_scenarios)
