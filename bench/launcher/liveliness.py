"""Whether the run's nodes are alive, from their authenticated presence answers (bench/bus/presence.py):
waiting until every node answers at start, telling a hung or stopped node from a slow one while
the run goes on, and waiting for the nodes on other hosts to leave at its end."""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass

from bench.bus.presence import PresenceQuery, PresenceResponder
from bench.launcher.children import SHUTDOWN_GRACE_S, STARTUP_IDLE_S, Child, _check_children
from bench.launcher.endings import NodeFailed
from bench.plant.divergence import EXIT_DIVERGED
from bench.runtime.ownership import CpuProgress, process_state
from bench.scenario import LivelinessConfig

STARTUP_TIMEOUT_S = 120.0


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
