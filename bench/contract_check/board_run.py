"""`bench contract check board`, the command: the scenario (the contract) and the SecOC key, the
board's bus (a Zenoh hub the check opens for the bench's board, or the user's python-can channel),
the board's process if the check starts it, the check (bench/contract_check/board_check.py), and the
verdict.

It prints one line on a pass, or FAIL and each problem, and writes the verdict with the contract's
numbers and the measured ones to <run_dir>/contract_check.json; every frame sent and heard goes to
<run_dir>/can.log (candump format), the board's output (if the check started it) to
<run_dir>/logs/outside.log.
"""
from __future__ import annotations

import json
import shlex
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import can
import msgspec
import numpy as np

from bench.bus import data_auth, keys
from bench.bus.private_files import read_private_key
from bench.bus.can import run_key, secoc
from bench.bus.can.config import BusSpec
from bench.bus.can.transport import TransportUnavailable, open_bus
from bench.bus.schemas import SCHEMA_VERSION
from bench.bus.session import SessionOptions, free_loopback_port, loopback_endpoint, open_session
from bench.contract_check.board_check import BoardCheck
from bench.contract_check.board_flight import BoardContract, FlightSide, ms
from bench.contract_check.check import OUTSIDE_LOG, Verdict
from bench.contract_check.host_stalls import StallWatch, board_records
from bench.runtime.priority import set_realtime_priority
from bench.runtime.process import terminate
from bench.scenario import Scenario, ScenarioError, load_scenario, parse_scenario

STARTUP_TIMEOUT_S = 60.0      # until the board's first heartbeat (a node's start on a loaded host)
DEFAULT_MARGIN_S = 0.03       # beyond a period or a timeout, for the board's reaction and the bus
EXIT_TIMEOUT_S = 10.0
CAPTURE_NAME = "can.log"
VERDICT_NAME = "contract_check.json"
# The default contract: the bench's board with its set-point echo, which lock-step needs.
DEFAULT_SCENARIO = {"name": "board_contract", "run": {"seed": 1}, "can": {"board": {"setpoint_echo": True}}}


def board_scenario(path: str | None) -> Scenario:
    scenario = load_scenario(path) if path else parse_scenario(DEFAULT_SCENARIO, "board check")
    if scenario.can is None:
        raise ScenarioError(f"contract check board: scenario {scenario.name!r} has no [can] section (the board's "
                            f"contract)")
    return scenario


def read_secoc_key(path: Path) -> str:
    """The 16-byte SecOC key as 32 hex digits from a file only its owner can read (secoc.key)."""
    return read_private_key(path, secoc.KEY_BYTES, f"--key-file {str(path)!r}", "AES-128").hex()


def cmd_check_board(args) -> int:
    """`bench contract check board` (bench/contract_check/cli.py)."""
    try:
        scenario = board_scenario(args.scenario)
        if args.key_file:
            scenario = msgspec.structs.replace(scenario, can=run_key.can_with_key(
                scenario.can, read_secoc_key(Path(args.key_file))))
        outside_bus = args.interface is not None and args.interface != "zenoh"
        if args.channel and not outside_bus:     # the bench's board, started from {scenario}, on that channel too
            scenario = msgspec.structs.replace(scenario, can=msgspec.structs.replace(scenario.can,
                                                                                      board_channel=args.channel))
        if args.no_fd and scenario.can.security.authenticated:
            raise ValueError("--no-fd: the secoc profile's authenticated frames are CAN FD (a classic-only board "
                             "needs [can.security] profile = \"e2e\" in --scenario)")
        if outside_bus and run_key.needs_key(scenario):
            raise ValueError("the secoc profile needs the board's key: --key-file FILE (32 hex digits, mode 0600), or "
                             "[can.security] key_hex in --scenario")
        if not 0 < args.margin <= 10:
            raise ValueError(f"--margin must be in (0, 10] s, got {args.margin}")
        startup_s = args.startup_timeout if args.startup_timeout is not None else STARTUP_TIMEOUT_S
        if not 1 <= startup_s <= 3600:
            raise ValueError(f"--startup-timeout must be 1-3600 s, got {startup_s}")
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S")
        run_id = keys.check_run_id(args.run_id or f"contract-board-{stamp}")
        run_dir = Path(args.runs_dir) / run_id
        if run_dir.exists():
            raise ValueError(f"run directory {run_dir} exists: choose another --run-id")
        spec = (BusSpec(interface=args.interface, channel=args.channel or "", bitrate=args.bitrate, fd=not args.no_fd)
                if outside_bus else None)
        verdict = run_board_check(scenario, run_id, run_dir, args.command, spec, args.channel, args.port,
                                  args.margin, args.dipole_tolerance, args.real_time_only, startup_s)
    except (ScenarioError, ValueError, msgspec.ValidationError) as exc:
        print(f"bench contract check: error: {exc}", file=sys.stderr)
        return 2
    except (can.CanError, OSError, TransportUnavailable, NotImplementedError) as exc:
        print(f"bench contract check: error: the board's bus: {exc}", file=sys.stderr)
        return 2
    print(verdict.text("board"))
    return 0 if verdict.passed else 1


def run_board_check(scenario: Scenario, run_id: str, run_dir: Path, command: str | None, spec: BusSpec | None,
                    channel: str | None, port: int | None, margin_s: float = DEFAULT_MARGIN_S,
                    tolerance_am2: float | None = None, real_time_only: bool = False,
                    startup_timeout_s: float = STARTUP_TIMEOUT_S, bus_session=None) -> Verdict:
    """Check the board; `spec` None: the bench's zenoh interface on a hub the check opens (`port`),
    else the board's own bus (bus_session: a Zenoh session of the caller's for a `zenoh` spec)."""
    config = scenario.can
    if run_key.needs_key(scenario):            # the bench's board started by the check: a key for this run
        scenario = run_key.with_run_key(scenario)
        config = scenario.can
    contract = BoardContract.of(config, margin_s, tolerance_am2, real_time_only)
    (run_dir / "logs").mkdir(parents=True)
    scenario_path = run_dir / "scenario.json"
    run_key.write_private(scenario_path, msgspec.json.format(msgspec.json.encode(scenario)))
    # The data topics' key, as the launcher writes it: the bench's board signs what it publishes.
    run_key.write_private(run_dir / data_auth.KEY_FILE, (data_auth.new_key().hex() + "\n").encode())
    # The flight side stands for flight software on its own processor, as the bench's driver does.
    priority = config.realtime_priority
    if priority and not set_realtime_priority(priority, inherited=True):
        priority = 0
    session = hub = None
    board_channel = channel or config.board_channel
    if spec is None:
        hub = loopback_endpoint(port or free_loopback_port())
        session = open_session(SessionOptions(listen=(hub,)))
        spec = BusSpec(interface="zenoh", channel=board_channel)
    process = None
    flight = None
    stalls = StallWatch()
    try:
        bus = open_bus(spec, run_id=run_id, session=session or bus_session)
        if priority:
            set_realtime_priority(priority)    # what this thread starts from now on runs at normal priority
        flight = FlightSide(bus, contract, config.security.key if contract.profile == "secoc" else None,
                            run_dir / CAPTURE_NAME, priority)
        where = (f"connect to {hub}, run id {run_id}, scenario {scenario_path}, channel {board_channel}"
                 if hub else f"{spec.interface} channel {spec.channel}")
        t_started_s = time.monotonic()
        # A board on the user's own channel without --command may be running already (no boot-up to see).
        check = BoardCheck(flight, contract, started_by_check=bool(command) or hub is not None,
                           log_path=str(run_dir / "logs" / OUTSIDE_LOG), stalls=stalls)
        if command:
            argv = [a.format(connect=hub or "", run_id=run_id, scenario=str(scenario_path), run_dir=str(run_dir),
                             channel=board_channel) for a in shlex.split(command)]
            with open(run_dir / "logs" / OUTSIDE_LOG, "w") as log:
                try:
                    process = check.process = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT)
                except OSError as exc:
                    check.problem(f"could not start the board ({' '.join(argv)}): {exc}")
        else:
            print(f"bench: waiting for the board: {where}", file=sys.stderr)
        finished = not check.problems and check.run(startup_timeout_s, t_started_s)
        if (process is not None and process.poll() is not None
                and not any("the board's command exited" in problem for problem in check.problems)):
            check.problem(f"the board's command exited with code {process.returncode} during the check "
                          f"(its output: {run_dir / 'logs' / OUTSIDE_LOG})")
        terminate(process, EXIT_TIMEOUT_S)        # the bench's board writes how late its host held it
        if finished:
            check.throughout(board_records(run_dir))
    finally:
        stalls.close()
        if flight is not None:
            flight.close()
            bus.shutdown()
        terminate(process, EXIT_TIMEOUT_S)
        if session is not None:
            session.close()
        if priority:
            set_realtime_priority(0)
    verdict = Verdict(check.problems, summary(check, contract, spec, flight))
    write_board_verdict(run_dir, verdict, contract, check.measured)
    return verdict


def summary(check: BoardCheck, c: BoardContract, spec: BusSpec, flight: FlightSide) -> str:
    m = check.measured
    hb, echo, timeout = m.get("heartbeat", {}), m.get("echo"), m.get("command_timeout", {})
    parts = [f"{c.profile}, node {c.node_id:#04x} on {spec.interface} {spec.channel}"]
    if "period_median_s" in hb:
        parts.append(f"heartbeat {ms(hb['period_median_s'])} (contract {ms(c.heartbeat_period_s)}), "
                     + " -> ".join(hb["states"]))
    if m.get("commands"):
        worst = max((r.get("max_error_am2", 0.0) for r in m["commands"]), default=0.0)
        parts.append(f"{len(m['commands'])} dipoles applied, telemetry within {worst:g} A m^2 (tolerance "
                     f"{c.dipole_tolerance_am2:g}; quantised to {c.dipole_resolution_am2:g}, saturated at "
                     f"{c.max_dipole_am2:g})")
    if not c.setpoint_echo:
        parts.append("set-point echo not required (--real-time-only: a board for real time only)")
    if isinstance(echo, dict) and "latency_p50_s" in echo:
        parts.append(f"{echo['echoed']}/{echo['commands']} commands echoed with their counter (p50 "
                     f"{ms(echo['latency_p50_s'])}, max {ms(echo['latency_max_s'])})")
    if timeout.get("emcy_after_s") is not None:
        parts.append(f"command timeout: EMCY 0x8250 {ms(timeout['emcy_after_s'])}, coils off in telemetry "
                     f"{ms(timeout.get('coils_off_telemetry_after_s'))} after the last command (contract "
                     f"{ms(c.command_timeout_s)} + {ms(c.margin_s)})")
    refused = [r["probe"] for r in m.get("refusals", []) if r["emcy_after_s"] is not None and not r["moved"]]
    if refused:
        parts.append(f"refused with EMCY 0x8100: {', '.join(refused)}")
    repeated = timeout.get("repeated_attempts", [])
    gaps = m.get("held_up_by_host", [])
    if repeated or gaps:
        parts.append("held up by this host: " + ", ".join(
            ([f"command timeout repeated {len(repeated)}x ({repeated[0]['held_up']})"] if repeated else [])
            + [f"a {g['gap']} gap of {ms(g['gap_s'])} excused (the board's host held it {ms(g['host_held_s'])})"
               if g["host_held_s"] is not None else
               f"a command timeout EMCY after {ms(g['gap_s'])} without a command applied (the board was right)"
               for g in gaps]))
    late = m.get("late_on_arrival", {})
    if late.get("commands") or late.get("nmt"):
        parts.append(f"excused as late on arrival (this host, over the {ms(late['freshness_window_s'])} freshness "
                     f"window): {late['commands']} command(s), {late['nmt']} NMT frame(s)")
    return "; ".join(parts)


def write_board_verdict(run_dir: Path, verdict: Verdict, contract: BoardContract, measured: dict) -> None:
    (run_dir / VERDICT_NAME).write_text(json.dumps(
        {"node": "board", "passed": verdict.passed, "problems": verdict.problems, "summary": verdict.summary,
         "schema_version": SCHEMA_VERSION, "contract": contract.__dict__, "measured": measured},
        indent=2, default=_jsonable) + "\n")


def _jsonable(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    raise TypeError(type(value).__name__)
