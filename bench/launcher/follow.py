"""Following a run until the plant finishes: the progress bar from the plant's signed steps, and
every look that can end the run early (a node that died or hung, a remote node that left, steps
that stopped advancing, a diverged plant)."""
from __future__ import annotations

import collections
import time
from pathlib import Path

from bench.bus import keys
from bench.bus.presence import PresenceWatcher
from bench.bus.schemas import MalformedMessage, StepDone, decode
from bench.launcher.children import Child, _check_children
from bench.launcher.endings import Diverged, NodeFailed
from bench.launcher.liveliness import TokenLoss, _check_liveliness, _check_remote
from bench.launcher.stats import StatsCollector
from bench.plant.divergence import EXIT_DIVERGED, read_divergence
from bench.runtime.ownership import process_state
from bench.runtime.progress_watchdog import ProgressWatchdog
from bench.scenario import LivelinessConfig

FOLLOW_PERIOD_S = 0.1     # how often the launcher checks its children and moves the progress bar


def _follow_run(session, run_id: str, children: list[Child], n_steps: int, show_progress: bool,
                liveliness: LivelinessConfig, run_dir: Path, reports: StatsCollector,
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
