"""Each fault against the board and the bus model, on simulated time and, for a few, in real time.

The driver commands the scripted profile every 20 ms; the board sends heartbeat every 100 ms and
telemetry every 50 ms and times out after 100 ms without a valid command. Each fault starts 1 s
after commanding starts. Each test runs on simulated time (`SimulatedCanBench`: the lock-step
loop's driver, bus model and board in this process, no host in the run); the tests marked
`both_clocks` also run as their real-time twin (`CanBench`: bus model and board as separate
processes on the Zenoh transport, the driver here on the wall clock), with the same checks and
bounds. Every test asserts:
- the driver detects the fault within a bound stated in the test, measured from the injector's
  log to the driver's event (one clock: bus time, or the host's monotonic clock across processes);
- every frame a node sent is on the wire or in the drop capture, and every frame on the wire
  reached the nodes that listen for it;
- no command outside what the driver commanded was ever applied (except where E2E cannot know:
  corruption before protection, stated in that test);
- the board goes to its safe state when the commands stop at the end.
"""
from __future__ import annotations

import itertools
import os
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

from bench.bus.can import host_lateness
from bench.bus.can import protocol as p
from bench.bus.can.config import SecurityConfig
from bench.runtime.can_bench import CanBench, CanRunResult, write_scenario
from bench.runtime.can_bench_simulated import SimulatedCanBench
from bench.bus.can.sim_window import sim_ns

HEARTBEAT_PERIOD_S = 0.1
TELEMETRY_PERIOD_S = 0.05
COMMAND_PERIOD_S = 0.02
COMMAND_TIMEOUT_S = 0.1
FAULT_START_S = 1.0
DRIVE_S = 2.0
SILENCE_S = 0.4          # commands stop: the board must go safe within this
STARVED_RETRIES = 2
# Events a node's measured lateness explains (host_caused): deadlines of the board's periodic
# frames, and an applied dipole compared with a newer command because the bus model delivered the
# board's telemetry late (seen in UML under load: bus model 1.3 s late, telemetry 0.26 s old).
HOST_EXPLAINED_KINDS = ("telemetry_timeout", "heartbeat_timeout", "heartbeat_resumed", "telemetry_lost",
                        "actuator_mismatch")
HOST_WINDOW_NS = 500_000_000
_runs = itertools.count()

SIMULATED, WALL = "simulated", "wall"
simulated = pytest.mark.parametrize("clock", [SIMULATED])
# The real-time twins: what the processes and the transport add (every frame across processes, a
# timeout over the wall clock, a flood through the transport's queues, freshness across processes).
both_clocks = pytest.mark.parametrize("clock", [SIMULATED, WALL])

# A hang bound above CanBench's own (two 60 s start-ups, two 10 s exits) and the re-runs of a
# starved run; a run takes 5-10 s.
pytestmark = pytest.mark.timeout(600)


# The E2E layer's own fault handling (MTQ_CMD, CRC and counter verdicts) is what these runs
# measure: the e2e profile, chosen explicitly. The default (secoc) profile's refusal of replays and
# spoofers is the last test here, and every built-in scenario's default in test_can_spoofing_defaults.
E2E_ONLY = {"security": {"profile": "e2e"}}
ZENOH = {"transport": "zenoh", **E2E_ONLY}
SOCKETCAN = {"transport": "socketcan", "flight_channel": "vcan0", "board_channel": "vcan1", **E2E_ONLY}


def run_fault(tmp_path, *faults: dict, drive_s: float = DRIVE_S, transport: dict = ZENOH,
              clock: str = WALL) -> CanRunResult:
    """One bench run with these faults, on simulated time or the wall clock (then on `transport`).
    A real-time run the host starved so badly that a fault never acted (the injector affected no
    frame, and the driver or the board counted host overruns) proves nothing about the bus: it is
    run again, at most STARVED_RETRIES times, and said so."""
    for attempt in range(STARVED_RETRIES + 1):
        result = _run_once(tmp_path / (f"retry{attempt}" if attempt else "."), faults, drive_s, transport, clock)
        _report_host_overruns(tmp_path, result)
        if not (faults and starved(result)):
            return result
        print(f"{tmp_path.name}: the host starved the run (host overruns: driver "
              f"{sum(e.kind == 'host_overrun' for e in result.events)}, board {result.board.get('host_overruns', 0)}; "
              f"no fault acted): run again")
    return result


def _run_once(tmp_path, faults, drive_s, transport, clock) -> CanRunResult:
    tmp_path.mkdir(parents=True, exist_ok=True)
    scenario = write_scenario(tmp_path / "scenario", {**transport, "faults": list(faults)})
    bench_class = SimulatedCanBench if clock == SIMULATED else CanBench
    bench = bench_class(scenario, tmp_path / "run", f"canfault-{os.getpid()}-{next(_runs)}")
    try:
        bench.start()
        bench.drive(drive_s)
        bench.drive(SILENCE_S, commanding=False)
    except BaseException:
        bench.close()
        raise
    return bench.stop()


def affected(r: CanRunResult) -> int:
    """Frames the faults acted on. A count-limited fault ("count": 5, "every": 10) acts on fewer
    when a starved host sent fewer commands in the fault's window; what it did act on must then be
    caught, each one."""
    n = sum(f["affected"] for f in r.report.get("faults", []))
    assert n > 0, "no fault acted in this run"
    return n


def injected_frames_on_the_wire(r: CanRunResult) -> int:
    """The faults' frames less the injector's own frames a collision destroyed ("collided"). A
    frame injected with a command's identifier can start together with the driver's next command
    (a starved driver sends late, into the copy's slot): equal identifiers, different data, a bit
    error (ISO 11898-1). The driver's controller retransmits its command; the injector, which has no
    controller, gives up, and its frame never reaches the board."""
    return affected(r) - len(r.injected(action="collided"))


def first_injection_on_the_wire_ns(r: CanRunResult) -> int | None:
    """When the first injected frame that did not collide was injected."""
    collided = {i["data"] for i in r.injected(action="collided")}
    times = [i["t_ns"] for i in r.injected() if i["data"] not in collided]
    return min(times) if times else None


def diagnosis(r: CanRunResult) -> str:
    """What a failed check needs to be understood from its message alone (the UML guest's files
    are gone when the host reads its output)."""
    lateness = host_lateness.host_late_records(r.events, r.board, r.report)
    longest = {node: max((x.late_s for x in lateness if x.node == node), default=0.0)
               for node in ("driver", "board", "bus_model")}
    board = {k: r.board.get(k) for k in ("received", "accepted", "rejected", "ignored", "bad_frames", "lost_commands")}
    return (f"board {board}; wire {dict(r.wire)}; dropped {dict(r.dropped)}; driver sent {r.driver_sent}; "
            f"injections {Counter(i['action'] for i in r.injections)}; faults {r.report.get('faults')}; "
            f"bus model send failures {r.report.get('send_failures')}; longest host lateness s {longest}; "
            f"events {Counter(e.kind for e in r.events)}; waited for the board at the end "
            f"{'gave up' if r.board_drain_s is None else f'{r.board_drain_s:.2f} s'}")


def starved(r: CanRunResult) -> bool:
    host = (any(e.kind == "host_overrun" for e in r.events) or r.board.get("host_overruns", 0) > 0
            or r.report.get("host_overruns", 0) > 0)
    return host and all(f["affected"] == 0 for f in r.report.get("faults", []))


def _report_host_overruns(tmp_path, r: CanRunResult) -> None:
    """For benchmarks/can_uml_load.py: each run's host overruns, apart from its bus events."""
    out = os.environ.get("BENCH_CAN_REPORT_DIR")
    if not out:
        return
    import json
    host = host_caused(r)
    record = {"test": tmp_path.name, "host_overruns": sum(e.kind == "host_overrun" for e in r.events),
              "board_host_overruns": r.board.get("host_overruns", 0),
              "bus_model_host_overruns": r.report.get("host_overruns", 0),
              "host_caused": [f"{e.kind} {e.detail}" for e in host],
              "bus_events_before_silence": [e.kind for e in before_silence(r)]}
    with open(Path(out) / "host_overruns.jsonl", "a") as f:
        f.write(json.dumps(record) + "\n")


def latency_s(result: CanRunResult, kind: str, since_ns: int, detail: str = "", host_excused: bool = True) -> float:
    """Seconds from since_ns to the driver's first `kind` event, less the time the host held the
    driver's own loop up in between (its host_overrun events: how late each command period
    started), unless host_excused is False. A detection bound is a property of the bus and the
    nodes; on a starved host (UML's one CPU under a loaded 2-core machine: loop 74 ms late
    measured) the wall clock adds what the driver or the board measured of their own lateness
    (host_late_s), no more."""
    assert since_ns is not None, f"nothing to measure {kind} from: the fault never acted; events: {result.kinds()}"
    event = result.first_event(kind, after_ns=since_ns, detail=detail)
    assert event is not None, f"no {kind} {detail} detected; events: {result.kinds()}"
    latency = (event.detected_ns - since_ns) / 1e9
    if host_excused:
        latency -= host_late_s(result, since_ns, event.detected_ns)
    return latency


def host_late_s(r: CanRunResult, from_ns: int, to_ns: int) -> float:
    """How long the host held up the driver, the board or the bus model between from_ns and to_ns
    (bench.bus.can.host_lateness)."""
    return host_lateness.host_late_s(host_lateness.host_late_records(r.events, r.board, r.report), from_ns, to_ns)


def window_start_ns(result: CanRunResult, start_s: float = FAULT_START_S) -> int:
    return result.report["faults_t0_ns"] + round(start_s * 1e9)


def check_accounting(r: CanRunResult) -> None:
    # The injector's frames that went on the wire: those a collision destroyed never did.
    names = {a: Counter(p.Protocol().name_of(i["frame_id"]) for i in r.injected(action=a)) for a in ("injected", "collided")}
    injected = names["injected"] - names["collided"]
    assert r.driver_sent == r.wire[p.CMD] - injected[p.CMD] + r.dropped[p.CMD], "commands unaccounted for"
    for name in p.BOARD_FRAMES:
        assert r.board["sent"].get(name, 0) == r.wire[name] - injected[name] + r.dropped[name], name
    assert r.board["received"].get(p.CMD, 0) == r.wire[p.CMD], f"a command on the wire did not reach the board: {diagnosis(r)}"
    to_driver = Counter({n: r.wire[n] for n in p.BOARD_FRAMES}) + Counter({p.CMD: injected[p.CMD], "error_frame": r.wire["error_frame"]})
    assert +r.driver_received == +to_driver, "a frame on the wire did not reach the driver"


def check_only_commanded_applied(r: CanRunResult) -> None:
    commanded = {tuple(round(x, 4) for x in d) for d in r.commanded}
    applied = {tuple(round(x, 4) for x in a["dipole_am2"]) for a in r.board["applied"]}
    assert applied <= commanded, f"applied but never commanded: {applied - commanded}"


def check_safe_when_commands_stop(r: CanRunResult) -> None:
    assert latency_s(r, "board_command_timeout", r.last_command_ns) <= COMMAND_TIMEOUT_S + 2 * TELEMETRY_PERIOD_S + 0.1
    # The plant hears it too: the last applied dipole the board published is zero, in safe state.
    last = r.mtq_applied[-1]
    assert last.safe_state and last.dipole_am2 == [0.0, 0.0, 0.0]
    assert len(r.mtq_applied) >= len(r.board["applied"])


def check_all(r: CanRunResult, only_commanded: bool = True) -> None:
    check_accounting(r)
    if only_commanded:
        check_only_commanded_applied(r)
    check_safe_when_commands_stop(r)


def host_caused(r: CanRunResult) -> list:
    """Events of the host, not the bus: the driver's own command thread late (host_overrun), a
    board timeout the driver attributes to its own command gap, and the board's error reset
    after it. Reported apart (benchmarks/can_uml_load.py counts them), never a bus fault."""
    # A board timeout the driver puts down to its own command gap, or any board timeout while a
    # node measured itself late around it: the driver's command thread was not scheduled ("cause
    # driver stopped commanding": it stops for good only at the end of the run), or the bus
    # model held the commands back ("cause bus": seen with the bus model 1.3 s late in UML).
    timeouts = [e for e in r.events if e.kind == "board_command_timeout" and (
        e.detail.startswith("cause host_overrun")
        or host_late_s(r, e.detected_ns - HOST_WINDOW_NS, e.detected_ns + HOST_WINDOW_NS) > 0)]
    resets = [e for e in r.events if e.kind == "board_error_reset"] if timeouts else []
    # A board frame missing its deadline while a node measured itself late (within
    # HOST_WINDOW_NS): its process was not scheduled, or the bus model's, the bus lost nothing.
    late_frames = [e for e in r.events if e.kind in HOST_EXPLAINED_KINDS
                   and host_late_s(r, e.detected_ns - HOST_WINDOW_NS, e.detected_ns + HOST_WINDOW_NS) > 0]
    return [e for e in r.events if e.kind == "host_overrun"] + timeouts + resets + late_frames


def before_silence(r: CanRunResult) -> list:
    """Events detected while commanding, host overruns and what they caused excepted."""
    host = {id(e) for e in host_caused(r)}
    return [e for e in r.events if e.detected_ns <= r.last_command_ns and id(e) not in host]


def check_twin(r: CanRunResult, tmp_path, *faults: dict) -> None:
    """A real-time run detects every kind of event its simulated-time twin detects; anything else
    it detects, the host caused (host_caused: a node measured itself late around it)."""
    twin = run_fault(tmp_path / "simulated-twin", *faults, clock=SIMULATED)
    expected = {e.kind for e in twin.events}
    assert expected <= {e.kind for e in r.events}, f"simulated twin: {twin.kinds()}; {diagnosis(r)}"
    host = {id(e) for e in host_caused(r)}
    unexplained = [e for e in r.events if e.kind not in expected and id(e) not in host]
    assert unexplained == [], f"simulated twin: {twin.kinds()}; {diagnosis(r)}"


# ------------------------------------------------------------------------------------------------
@both_clocks
def test_no_fault_no_event_and_every_frame_delivered(tmp_path, clock):
    r = run_fault(tmp_path, clock=clock)
    assert before_silence(r) == [], "false alarm on a clean bus"
    assert r.board["accepted"] == r.driver_sent and r.board["rejected"] == {}
    check_all(r)
    # Any CAN tool reads the capture: cantools decodes every frame with the DBC.
    with open(r.run_dir / "can.log") as capture:
        decoded = subprocess.run([sys.executable, "-m", "cantools", "decode", str(p.DBC_PATH)], stdin=capture,
                                 capture_output=True, text=True, timeout=60)
    assert decoded.returncode == 0, decoded.stderr
    assert decoded.stdout.count("MTQ_CMD(") == r.wire[p.CMD]
    assert "MTQ_TLM_DIPOLE(" in decoded.stdout and "Unknown frame" not in decoded.stdout
    if clock == WALL:
        check_twin(r, tmp_path)


@both_clocks
def test_dropped_commands_put_the_board_in_safe_state(tmp_path, clock):
    drop = {"name": "drop", "start_s": FAULT_START_S, "count": 10}
    r = run_fault(tmp_path, drop, clock=clock)
    first_drop = r.first_injection_ns("dropped")
    # 10 commands (200 ms) missing: the board times out after 100 ms, says so in its next frames.
    assert latency_s(r, "board_command_timeout", first_drop) <= 3 * COMMAND_TIMEOUT_S
    assert r.dropped[p.CMD] == 10
    check_all(r)
    if clock == WALL:
        check_twin(r, tmp_path, drop)


@simulated
def test_a_delayed_command_arriving_late_is_rejected(tmp_path, clock):
    r = run_fault(tmp_path, {"name": "delay", "start_s": FAULT_START_S, "count": 1, "params": {"delay_s": 0.2}},
                  clock=clock)
    # Stale by 10 counter steps when it arrives: out of sequence.
    assert latency_s(r, "command_rejected", r.first_injection_ns("delayed"), "WRONG_SEQUENCE") <= 0.2 + 0.1
    check_all(r)


@simulated
def test_duplicated_commands_are_rejected_as_repeated(tmp_path, clock):
    r = run_fault(tmp_path, {"name": "duplicate", "start_s": FAULT_START_S, "count": 5, "every": 10}, clock=clock)
    assert r.board["rejected"] == {"REPEATED": injected_frames_on_the_wire(r)}, diagnosis(r)
    assert latency_s(r, "command_rejected", first_injection_on_the_wire_ns(r), "REPEATED") <= 5 * COMMAND_PERIOD_S
    assert r.kinds()["spoofed_command"] == injected_frames_on_the_wire(r)   # the copy was not sent by this driver
    check_all(r)


@simulated
def test_replayed_commands_are_seen_as_foreign(tmp_path, clock):
    r = run_fault(tmp_path, {"name": "replay", "start_s": FAULT_START_S, "count": 3, "every": 10,
                             "params": {"after_s": 0.3}}, clock=clock)
    assert len(r.injected(p.CMD)) == affected(r)
    assert latency_s(r, "spoofed_command", first_injection_on_the_wire_ns(r)) <= 5 * COMMAND_PERIOD_S
    assert r.kinds()["spoofed_command"] == injected_frames_on_the_wire(r), diagnosis(r)
    check_all(r)   # a replayed command is an old genuine one: never a value nobody commanded


@simulated
def test_corrupted_commands_fail_the_crc_and_are_never_applied(tmp_path, clock):
    r = run_fault(tmp_path, {"name": "corrupt", "start_s": FAULT_START_S, "count": 5, "every": 10,
                             "params": {"bits": 3}}, clock=clock)
    assert r.board["rejected"] == {"WRONG_CRC": affected(r)}, diagnosis(r)
    assert latency_s(r, "command_rejected", r.first_injection_ns("replaced"), "WRONG_CRC") <= 5 * COMMAND_PERIOD_S
    check_all(r)


@simulated
def test_corruption_before_protection_is_applied_but_caught_by_plausibility(tmp_path, clock):
    # A valid CRC over wrong data (seed 1 flips the sign bit of DipoleX): E2E cannot see it, the
    # board applies it, and the driver notices the applied dipole is not what it commanded.
    r = run_fault(tmp_path, {"name": "corrupt", "start_s": FAULT_START_S, "duration_s": 0.5,
                             "params": {"bits": 3, "recompute_crc": True, "seed": 1}}, clock=clock)
    assert r.board["rejected"] == {}
    bound_s = 0.06 + 0.15 + 2 * TELEMETRY_PERIOD_S + 0.1   # settle + mismatch time + telemetry
    assert latency_s(r, "actuator_mismatch", r.first_injection_ns("replaced")) <= bound_s
    check_all(r, only_commanded=False)


@simulated
def test_spoofed_commands_are_rejected_and_reported(tmp_path, clock):
    r = run_fault(tmp_path, {"name": "spoof", "start_s": FAULT_START_S, "count": 3, "every": 10,
                             "params": {"dipole_am2": 0.15}}, clock=clock)
    assert r.board["rejected"] == {"WRONG_CRC": injected_frames_on_the_wire(r)}, diagnosis(r)
    assert latency_s(r, "spoofed_command", first_injection_on_the_wire_ns(r)) <= 5 * COMMAND_PERIOD_S
    assert latency_s(r, "command_rejected", first_injection_on_the_wire_ns(r), "WRONG_CRC") <= 5 * COMMAND_PERIOD_S
    check_all(r)


@simulated
def test_frozen_counter_is_rejected_and_the_board_goes_safe(tmp_path, clock):
    r = run_fault(tmp_path, {"name": "counter_freeze", "start_s": FAULT_START_S, "duration_s": 0.4}, clock=clock)
    start = r.first_injection_ns("replaced")
    assert latency_s(r, "command_rejected", start, "REPEATED") <= 5 * COMMAND_PERIOD_S
    assert latency_s(r, "board_command_timeout", start) <= 3 * COMMAND_TIMEOUT_S
    check_all(r)


@simulated
def test_offset_counter_is_out_of_sequence(tmp_path, clock):
    r = run_fault(tmp_path, {"name": "counter_offset", "start_s": FAULT_START_S, "duration_s": 0.4,
                             "params": {"offset": 5}}, clock=clock)
    assert latency_s(r, "command_rejected", r.first_injection_ns("replaced"), "WRONG_SEQUENCE") <= 5 * COMMAND_PERIOD_S
    check_all(r)


@both_clocks
def test_babbling_node_starves_the_bus_and_the_board_is_lost(tmp_path, clock):
    r = run_fault(tmp_path, {"name": "flood", "start_s": FAULT_START_S, "duration_s": 0.5}, clock=clock)
    assert latency_s(r, "heartbeat_timeout", window_start_ns(r)) <= 3 * HEARTBEAT_PERIOD_S
    report = r.report
    assert report["peak_load_pct"] > 99
    calm, flooded = report["command_latency_us"]["without_flood"], report["command_latency_us"]["with_flood"]
    assert report["dropped"].get("tx_overflow", 0) > 0 or flooded["median"] > 100 * calm["median"]
    check_all(r)


@simulated
def test_board_power_loss_is_detected_and_the_driver_starts_the_board_again(tmp_path, clock):
    """The board without power for 0.6 s: coils off, silent, nobody ACKs the commands; then it
    boots (boot-up heartbeat, pre-operational) and the driver's NMT start makes it operational,
    at the next command period's window (SimulatedCanBench's step)."""
    r = run_fault(tmp_path, {"name": "board_power_loss", "start_s": FAULT_START_S, "duration_s": 0.6}, clock=clock)
    start, back = window_start_ns(r), window_start_ns(r, FAULT_START_S + 0.6)
    assert latency_s(r, "error_passive", start) <= 2 * COMMAND_PERIOD_S      # unacknowledged commands
    assert latency_s(r, "heartbeat_timeout", start) <= 3 * HEARTBEAT_PERIOD_S
    assert latency_s(r, "board_rebooted", back) <= 0.001 and latency_s(r, "heartbeat_resumed", back) <= 0.001
    log = r.board["power_log"]
    assert [e["event"] for e in log] == ["power_lost", "booted", "operational"]
    assert (log[0]["t_ns"], log[1]["t_ns"]) == (start, back)
    assert 0 < log[2]["t_ns"] - back <= round(COMMAND_PERIOD_S * 1e9) + 1_000_000
    # The coils: off over every window inside the power loss, on again after the NMT start.
    t0 = r.report["faults_t0_ns"]
    for m in r.mtq_applied:
        t_ns = sim_ns(m.header.sim_time_s)
        if start <= t_ns and t_ns + round(COMMAND_PERIOD_S * 1e9) <= back:
            assert m.safe_state and m.dipole_am2 == [0.0, 0.0, 0.0]
    assert any(m.command_applied for m in r.mtq_applied if sim_ns(m.header.sim_time_s) > log[2]["t_ns"])
    assert t0 <= start
    check_all(r)


@simulated
def test_frozen_telemetry_is_caught_by_plausibility(tmp_path, clock):
    r = run_fault(tmp_path, {"name": "telemetry_freeze", "start_s": FAULT_START_S, "duration_s": 0.8}, clock=clock)
    # The profile changes every 0.3 s; then settle 0.06 s, 0.15 s of mismatch, telemetry 0.05 s.
    assert latency_s(r, "actuator_mismatch", window_start_ns(r)) <= 0.3 + 0.06 + 0.15 + 2 * TELEMETRY_PERIOD_S + 0.1
    check_all(r)


@simulated
@pytest.mark.parametrize("fault, applied_y", [({"name": "coil_open", "params": {"axis": 1}}, 0.0),
                                               ({"name": "coil_stuck", "params": {"axis": 1, "value_am2": 0.05}}, 0.05)])
def test_an_open_or_stuck_coil_is_caught_by_its_current_telemetry(tmp_path, clock, fault, applied_y):
    """The y coil gives `applied_y` whatever is commanded, which its current sensor shows. The
    profile holds -0.1 A m^2 on y: actuator_mismatch within the settle time, the mismatch time
    and two telemetry periods."""
    held = {**ZENOH, "dipole_profile": [{"t_s": 0.0, "dipole_am2": [0.02, -0.1, 0.0]}]}
    r = run_fault(tmp_path, {**fault, "start_s": FAULT_START_S, "duration_s": 0.8}, transport=held, clock=clock)
    assert latency_s(r, "actuator_mismatch", window_start_ns(r)) <= 0.06 + 0.15 + 2 * TELEMETRY_PERIOD_S
    start, end = window_start_ns(r), window_start_ns(r, FAULT_START_S + 0.8)
    # The windows inside the fault (the last one's average runs a frame time past its end: lock-step
    # holds one step length from the step's command on, bench/bus/can/lockstep_bus.py).
    inside = [m for m in r.mtq_applied if start <= sim_ns(m.header.sim_time_s) and
              sim_ns(m.header.sim_time_s) + round(COMMAND_PERIOD_S * 1e9) < end and not m.safe_state]
    assert len(inside) == 39 and all(m.dipole_am2 == [0.02, applied_y, 0.0] for m in inside)
    check_all(r)


@simulated
def test_error_frames_take_the_driver_bus_off_and_back(tmp_path, clock):
    r = run_fault(tmp_path, {"name": "error_frames", "start_s": FAULT_START_S, "count": 32,
                             "params": {"restart_delay_s": 0.2}}, clock=clock)
    start = r.first_injection_ns("destroyed")
    # The order on the wall clock; the bound less what the host held the loop up.
    assert latency_s(r, "error_passive", start, host_excused=False) < latency_s(r, "bus_off", start, host_excused=False)
    assert latency_s(r, "bus_off", start) <= 5 * COMMAND_PERIOD_S
    assert 0.2 <= latency_s(r, "bus_restarted", start, host_excused=False)
    assert latency_s(r, "bus_restarted", start) <= 0.2 + 5 * COMMAND_PERIOD_S
    assert latency_s(r, "board_command_timeout", start) <= 0.2 + 3 * COMMAND_TIMEOUT_S
    assert r.report["bus_off"] == {"flight": 1}
    check_all(r)


def test_garbage_from_a_rogue_node_is_counted_and_never_fatal(tmp_path):
    import can

    from bench.bus.can.transport import open_can_bus
    from bench.bus.session import SessionOptions

    scenario = write_scenario(tmp_path / "scenario", {**ZENOH, "faults": []})
    bench = CanBench(scenario, tmp_path / "run", f"canfault-{os.getpid()}-{next(_runs)}")
    garbage = [can.Message(arbitration_id=0x210, is_extended_id=False, data=b"\x01\x02\x03"),   # short command
               can.Message(arbitration_id=0x123, is_extended_id=False, data=bytes(8)),         # unknown id
               can.Message(arbitration_id=0x210, is_extended_id=True, data=bytes(8)),          # extended id
               can.Message(arbitration_id=0x710, is_extended_id=False, data=b"\xee")]          # no NMT state
    try:
        bench.start()
        rogue = open_can_bus("zenoh", "flight", run_id=bench.run_id, session_options=SessionOptions(connect=(bench.hub,)))
        try:
            rogue.wait_for_peers(2, 10)
            bench.drive(FAULT_START_S)
            for msg in garbage:
                rogue.send(msg)
            bench.drive(DRIVE_S - FAULT_START_S)
            bench.drive(SILENCE_S, commanding=False)
        finally:
            rogue.shutdown()
    except BaseException:
        bench.close()
        raise
    r = bench.stop()
    # The board heard all four through the bus model, counted them, and kept applying commands.
    assert r.board["bad_frames"] == {"wrong_length": 1, "unknown_id": 2, "garbage": 1}
    assert r.board["rejected"] == {"wrong_length": 1}
    assert r.board["accepted"] == r.driver_sent
    assert r.first_event("command_rejected", detail="WRONG_LENGTH") is not None
    check_only_commanded_applied(r)
    check_safe_when_commands_stop(r)


@both_clocks
def test_on_the_secoc_profile_replays_and_a_data_id_aware_spoofer_never_reach_the_coils(tmp_path, clock):
    secoc = {**ZENOH, "security": {"profile": "secoc"}}
    r = run_fault(tmp_path, {"name": "replay", "start_s": FAULT_START_S, "every": 3, "params": {"after_s": 0.6}},
                  {"name": "spoof", "start_s": FAULT_START_S, "every": 3, "params": {"knows_data_id": True}},
                  transport=secoc, clock=clock)
    injected = Counter(i["fault"].split(":")[1] for i in r.injections if i["action"] == "injected")
    assert injected["replay"] >= 2 and injected["spoof"] >= 5
    # Every forgery was rejected by its MAC and every replay as stale, across processes. On a
    # loaded host a genuine command can also arrive later than its freshness bound and be refused
    # as stale (measured: 2 of ~100 at load average 15 on 2 cores); that is the bound doing its
    # job, so such commands are counted apart instead of failing the test: each genuine command is
    # either applied or refused as stale, and nothing older than the bound is ever applied.
    rejected = dict(r.board["rejected"])
    assert rejected.pop("WRONG_MAC") == injected["spoof"]
    stale = rejected.pop("STALE")
    # Likewise the driver's authenticated NMT start: late on a loaded host, it is refused as stale
    # and the driver sends another at the next pre-operational heartbeat (nothing else NMT is sent).
    rejected.pop("NMT_STALE", None)
    assert rejected == {} and stale >= injected["replay"]
    late_genuine = stale - injected["replay"]
    assert r.board["accepted"] + late_genuine == r.driver_sent
    # More than a tenth of them late only when the nodes measured the host holding them up by more
    # than the freshness margin (CI with both cores busy: 14 of ~100): a freshness check that
    # refused fresh commands on a quiet host still fails here.
    margin_s = SecurityConfig().freshness_margin_s
    held_s = host_late_s(r, r.command_start_ns, r.last_command_ns)
    assert late_genuine <= 0.1 * r.driver_sent or held_s >= margin_s, \
        f"{late_genuine} genuine commands refused as stale, host held the nodes up {held_s:.3f} s only: {diagnosis(r)}"
    check_only_commanded_applied(r)
    # nothing older than the board's freshness bound (command period + margin) reached the coils
    assert max(a["age_s"] for a in r.board["applied"]) <= COMMAND_PERIOD_S + margin_s
    check_safe_when_commands_stop(r)
