"""`bench run`'s run: the hub session, the run directory and its files, the nodes started and
followed to the end, stopped in order, and what the run leaves (run_bench)."""
from __future__ import annotations

import dataclasses
import signal
import sys
import time
from pathlib import Path

import msgspec

from bench.bus import data_auth, keys
from bench.bus.can import run_key
from bench.bus.certs import read_secoc_key
from bench.bus.deployment import LAUNCHER
from bench.bus.presence import PresenceQuery, PresenceResponder
from bench.bus.session import open_session
from bench.contract.document import CONTRACT_FILE, write_contract
from bench.launcher.children import Child, ProcessGroup, _check_children, _kill_children, _spawn, _stop_children
from bench.launcher.endings import EXIT_FAILED, Diverged, NodeFailed, RunEnding, RunInterrupted
from bench.launcher.finish import _finish, _import_report_meanwhile
from bench.launcher.follow import _follow_run
from bench.launcher.liveliness import _stop_remote, _wait_alive
from bench.launcher.parts import (BOARD_SIDE_NODES, EXTERNAL_HOST, LIVE_NODE, board_is_external, external_parts,
                                  nodes_for, with_driver_on_the_board_bus)
from bench.launcher.placement import Placement, local_placement
from bench.launcher.run_dir import RunDirClaim
from bench.launcher.signals import SignalGuard
from bench.launcher.stats import StatsCollector
from bench.plant.divergence import EXIT_DIVERGED
from bench.runtime import zygote as node_zygote
from bench.runtime.ownership import child_environment
from bench.runtime.progress_watchdog import ProgressWatchdog
from bench.scenario import Scenario


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
