"""Process entry points of the actuator bus: node "mtq" (the board) and node "canbus" (bus model).

Each opens its CAN buses on the scenario's transport and writes what a test or a report needs
into <run_dir>/can/ when it stops: the board its counts and every command it applied, the bus
model its report, the injector's log and the candump capture.

In lock-step with the bus on simulated time (bench/bus/can/sim_window.py) there is no "mtq"
process: "canbus" runs the board with the bus model on the simulated clock
(bench/bus/can/lockstep_bus.py).
reads:  canstep/flight (CanWindow: the driver's frames of step k)
writes: canstep/bus    (CanWindow: the frames the driver heard during step k),
        actuator/mtq   (MtqApplied with `step` = k: the coils' output averaged over the step)
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import can

from bench.bus import keys
from bench.bus.can import protocol as p
from bench.bus.can.board import AppliedCommand, MagnetorquerBoard, applied_record
from bench.bus.can.coils import CoilHardware
from bench.bus.can.busmodel import BOARD, CHANNEL_BUS, FLIGHT, BusModel
from bench.bus.can.realtime_bridge import RealTimeBridge
from bench.bus.can.config import CanConfig
from bench.bus.can.injector import FaultInjector
from bench.bus.can.live_faults import LiveFaults, follow_live_hardware_faults
from bench.bus.can.lockstep_bus import LockStepBus, StepCoils
from bench.bus.can.sim_window import SIM_ZERO_NS, CanWindow, bus_on_simulated_time, fault_clock_scale
from bench.bus.can.transport import open_bus
from bench.bus.schemas import MtqApplied, header
from bench.bus.spill import SpilledJson, write_json_with_list

PEER_WAIT_S = 10.0
CAPTURE_NAME = "can.log"             # in the run directory: what a sniffer on the bus would see
ACCOUNTING_NAME = "dropped.log"      # in can/: frames dropped, and originals of altered frames
REPORT_NAME = "busmodel.json"
INJECTIONS_NAME = "injections.jsonl"
BOARD_NAME = "board.json"


def can_dir(run_dir: Path) -> Path:
    path = Path(run_dir) / "can"
    path.mkdir(parents=True, exist_ok=True)
    return path


def open_node_bus(ctx, config: CanConfig, role: str) -> can.BusABC:
    """The CAN bus of this node's `role` (CanConfig.bus_spec: "driver", "board", "busmodel_flight",
    "busmodel_board"); over Zenoh it shares the node's own session (one per process)."""
    return open_bus(config.bus_spec(role), run_id=ctx.run_id, session=ctx.session)


def _wait_for_bus_peer(bus: can.BusABC, what: str, ctx) -> None:
    # Zenoh delivers only to buses it already knows: wait for the other end before sending.
    if hasattr(bus, "wait_for_peers") and not bus.wait_for_peers(1, PEER_WAIT_S):
        ctx.log.warning("no peer on the %s CAN channel after %.0f s; sending anyway", what, PEER_WAIT_S)


def _can_config(ctx) -> CanConfig | None:
    config = getattr(ctx.scenario, "can", None)
    if config is None:
        ctx.log.error("scenario %r has no [can] section", ctx.scenario.name)
    return config


# --- node "mtq" ---------------------------------------------------------------------------------
def run_board(ctx) -> int:
    config = _can_config(ctx)
    if config is None:
        return 2
    bus = open_node_bus(ctx, config, "board")
    # One record per applied command (100 a second at a 10 ms command period): on disk as they
    # come, copied into board.json at the end (bench/bus/spill.py), so the board's memory stays flat.
    applied = SpilledJson(can_dir(ctx.run_dir))

    def publish(received_ns: int | None, counter: int, target_dipole_am2: list[float] | None = None) -> None:
        stamps = {"applied": time.monotonic_ns()}
        if received_ns is not None:
            stamps["board_received"] = received_ns
        message = MtqApplied(
            header=header(ctx.run_id, ctx.published[keys.ACTUATOR_MTQ], 0.0, **stamps),
            dipole_am2=board.output_dipole_am2.tolist(), coil_current_a=board.state.coil_current_a.tolist(),
            safe_state=board.state.safe_state, actuation_paused=board.state.actuation_paused, alive_counter=counter,
            target_dipole_am2=target_dipole_am2)
        ctx.publish(keys.ACTUATOR_MTQ, message)

    def on_applied(command: AppliedCommand) -> None:
        applied.append(applied_record(command))
        publish(command.received_ns, command.alive_counter, command.dipole_am2.tolist())

    def on_coils_changed(state) -> None:
        publish(None, state.last_command_counter)

    # The board's own hardware faults, armed with the first command it accepts (fault times in
    # simulated seconds, on its wall clock by the run's time factor).
    hardware = CoilHardware(config.faults, config.board.max_dipole_am2, fault_clock_scale(ctx.scenario))
    board = MagnetorquerBoard(bus, config.board, config.protocol(), on_applied=on_applied,
                              on_coils_changed=on_coils_changed, security=config.security, hardware=hardware)
    follow_live_hardware_faults(ctx, hardware)    # live hardware faults, from canbus (bench/bus/can/live_faults.py)
    try:
        _wait_for_bus_peer(bus, config.board_channel, ctx)
        ctx.declare_ready([])   # the plant starts the loop once every node is ready
        board.run(ctx.stop)
    finally:
        ctx.leave_realtime_priority()   # the files at normal priority: they must not hold up another run's bus
        summary = write_board_summary(ctx.run_dir, board, applied, ctx.realtime_priority)
        ctx.log.info("board: sent %s, accepted %d, rejected %s", summary["sent"], board.accepted, summary["rejected"])
        applied.close()
        bus.shutdown()
    return 0


def write_board_summary(run_dir: Path, board: MagnetorquerBoard, applied, realtime_priority: int = 0) -> dict:
    """<run_dir>/can/board.json: the board's counts and every command it applied (`applied_record`);
    `applied`: a list of those records or a SpilledJson of them (copied to the file as it is read).
    Returns the counts (without the applied records)."""
    summary = {"sent": dict(board.sent), "received": dict(board.received), "accepted": board.accepted,
               "rejected": dict(board.rejected), "bad_frames": dict(board.protocol.bad.counts),
               "ignored": dict(board.ignored), "lost_commands": board.lost_commands, "nmt_state": board.nmt_state,
               "sdo_writes_refused": board.sdo.refused_writes, **board.host_lateness.report(),
               "realtime_priority": realtime_priority,
               # Power lost, booted, operational again (board_power_loss), on the board's clock (ns).
               "power_log": [{"event": e["event"], "t_ns": round(e["t_s"] * 1e9)} for e in board.power_log],
               "hardware_faults": board.hardware.summary()}
    write_json_with_list(can_dir(run_dir) / BOARD_NAME, summary, "applied", applied)
    return summary


# --- node "canbus" ------------------------------------------------------------------------------
class Capture:
    """candump .log files (python-can Logger): the wire in one, drops and altered originals in the other."""

    def __init__(self, bus_path: Path, accounting_path: Path):
        self.bus = can.Logger(str(bus_path))
        self.accounting = can.Logger(str(accounting_path))

    def __call__(self, msg: can.Message) -> None:
        (self.bus if msg.channel == CHANNEL_BUS else self.accounting).on_message_received(msg)

    def stop(self) -> None:
        self.bus.stop()
        self.accounting.stop()


def run_bus_model(ctx) -> int:
    config = _can_config(ctx)
    if config is None:
        return 2
    if bus_on_simulated_time(ctx.scenario):
        return run_lockstep_bus(ctx, config)
    out = can_dir(ctx.run_dir)
    buses = {FLIGHT: open_node_bus(ctx, config, "busmodel_flight"),
             BOARD: open_node_bus(ctx, config, "busmodel_board")}
    capture = Capture(Path(ctx.run_dir) / CAPTURE_NAME, out / ACCOUNTING_NAME) if config.capture else None
    protocol = p.Protocol(config.node_id, config.security.profile)   # no key: the injector is no insider
    t0_ns = time.monotonic_ns()
    wall_offset_s = time.time() - t0_ns / 1e9
    injector = FaultInjector(config.faults, protocol, seed=ctx.scenario.run.seed,
                             wall_s_per_sim_s=fault_clock_scale(ctx.scenario), max_dipole_am2=config.board.max_dipole_am2)
    model = BusModel(injector, protocol, t0_ns, bitrate_bps=config.bitrate_bps, tx_queue_frames=config.tx_queue_frames,
                     capture=capture, to_wall_s=lambda t_ns: t_ns / 1e9 + wall_offset_s)
    bridge = RealTimeBridge(model, buses)
    # Faults that arrive while the run runs (`bench inject`, the live view): bench/bus/can/live_faults.py.
    live = LiveFaults(ctx, lambda: injector, time.monotonic_ns, ctx.allow_live_faults, out)
    ctx.declare_ready([])   # the launcher and tests start the other CAN nodes after this
    try:
        bridge.run(ctx.stop)
    finally:
        live.close()
        # Results first: whatever happens while the buses close, the run's record is on disk.
        # At normal priority: writing the capture must not hold up another run's bus.
        ctx.leave_realtime_priority()
        report = model.report()
        report.update(bridge.report())
        report["t0_ns"] = t0_ns
        report["wall_offset_s"] = wall_offset_s   # can.log's wall timestamps = monotonic + this
        report["realtime_priority"] = ctx.realtime_priority
        write_bus_results(ctx.run_dir, capture, report, injector)
        _log_bus_load(ctx, report)
        for bus in buses.values():
            bus.shutdown()
    return 0


def write_bus_results(run_dir: Path, capture: Capture | None, report: dict, injector: FaultInjector) -> None:
    """<run_dir>/can/: the bus model's report and the injector's log; closes the capture."""
    out = can_dir(run_dir)
    if capture is not None:
        capture.stop()
    (out / REPORT_NAME).write_text(json.dumps(report, indent=1))
    with open(out / INJECTIONS_NAME, "w") as f:
        for text in injector.records.raw():    # the JSON of each InjectionRecord, as it was spilled
            f.write(text + "\n")


def _log_bus_load(ctx, report: dict) -> None:
    if "bus_load_pct" in report:
        ctx.log.info("bus load %.1f %%, frames %s, dropped %s", report["bus_load_pct"], report["frames"], report["dropped"])


def run_lockstep_bus(ctx, config: CanConfig) -> int:
    """The bus and the board on simulated time: one CanWindow in, one out, and the step's coils."""
    capture = Capture(Path(ctx.run_dir) / CAPTURE_NAME, can_dir(ctx.run_dir) / ACCOUNTING_NAME) if config.capture else None
    bus = LockStepBus(config, seed=ctx.scenario.run.seed, capture=capture)
    windows = ctx.subscribe_queue(keys.CAN_STEP_FLIGHT, CanWindow)
    live = LiveFaults(ctx, lambda: getattr(bus, "injector", None), lambda: bus.t_ns, ctx.allow_live_faults,
                      can_dir(ctx.run_dir))   # bench/bus/can/live_faults.py
    # Not actuator/mtq: its reader, the plant, subscribes before it waits for this token, and
    # the driver boots the board through canstep/* before the plant is up.
    ctx.declare_ready([keys.CAN_STEP_BUS])
    try:
        for window in ctx.until_stopped(windows):
            received_ns = time.monotonic_ns()
            try:
                heard, coils = bus.advance(window.start_ns, window.end_ns, window.frames)
            except ValueError as exc:   # out of order or outside its step: refused, counted, never applied
                ctx.malformed[keys.CAN_STEP_FLIGHT] += 1
                ctx.log.error("lock-step CAN window of step %d refused: %s", window.step, exc)
                continue
            ctx.publish(keys.CAN_STEP_BUS, CanWindow(header(ctx.run_id, window.header.seq, window.header.sim_time_s),
                                                     window.step, window.start_ns, window.end_ns, heard))
            if window.step < 0:
                continue        # the board's boot, before step 0
            ctx.publish(keys.ACTUATOR_MTQ, step_applied(
                bus, coils, header(ctx.run_id, window.step, window.header.sim_time_s, board_received=received_ns,
                                   applied=time.monotonic_ns()), window.step))
    finally:
        live.close()
        if bus.t_ns is not None:
            # Bus time throughout: can.log stamps are t_ns / 1e9 (wall_offset_s 0), events t_ns.
            report = bus.report() | {"clock": "simulated", "sim_zero_ns": SIM_ZERO_NS, "wall_offset_s": 0.0}
            write_bus_results(ctx.run_dir, capture, report, bus.injector)
            write_board_summary(ctx.run_dir, bus.board, bus.applied)
        elif capture is not None:
            capture.stop()
    return 0


def step_applied(bus: LockStepBus, coils: StepCoils, message_header, step: int) -> MtqApplied:
    """What the plant integrates over lock-step step `step`: the coils' output averaged over it."""
    counter = coils.applied_counter if coils.applied_counter is not None else bus.board.state.last_command_counter
    return MtqApplied(message_header, dipole_am2=coils.dipole_am2.tolist(),
                      coil_current_a=coils.coil_current_a.tolist(), safe_state=coils.safe_state,
                      actuation_paused=coils.actuation_paused, alive_counter=counter, step=step,
                      command_applied=coils.applied_counter is not None)


def run(ctx) -> int:
    """Entry point named in bench.runtime.node.NODES for both nodes; the node's name picks one."""
    return {"mtq": run_board, "canbus": run_bus_model}[ctx.name](ctx)
