"""CAN bus load from the candump capture (can.log) and the fault timeline of the run, both on the
run's simulated time (bench.report.timebase).

vcan has no bit timing, so the load is computed the way the bus model charges it: each frame's
bits with stuffing (bench.bus.can.bittiming) at the configured bitrate, summed per 0.1 s of wall
time (the bus is busy in wall time), each window placed at the simulated time it began. A fault
window is the one the injector armed (busmodel.json `faults`: from the driver's first command
frame, `faults_t0_ns`, plus the scenario's `start_s`, for its `duration_s`, both simulated
seconds, on a real-time run's wall clock divided by the time factor: `fault_clock_scale`), or for
a fault limited by a frame count, up to the last frame it affected; a window is clipped to the run.
A bus that ran on simulated time (lock-step, busmodel.json `clock` = "simulated") stamped all of
these in bus time: simulated seconds are `(t_ns - sim_zero_ns) / 1e9`, and can.log's timestamps
are `t_ns / 1e9`.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import can
import numpy as np

from bench.bus.can.bittiming import DEFAULT_BITRATE_BPS, frame_bits
from bench.bus.can.live_faults import live_fault_specs, read_live_faults
from bench.bus.can.host_lateness import held_s, load_host_late_records
from bench.report.document import fmt
from bench.report.timebase import RunClock, wall_to_mono_ns
from bench.report.rundata import RunData

WINDOW_S = 0.1
# A fault injected while the run ran (`bench inject`, the live view; can/live_faults.json): its
# window's name in the report's tables and plots ends so; metrics.json flags it "live".
LIVE_SUFFIX = " (live)"
INJECTIONS_FILE = Path("can") / "injections.jsonl"
BUSMODEL_FILE = Path("can") / "busmodel.json"


@dataclass
class BusLoad:
    window_start_s: np.ndarray      # simulated time at which each 0.1 s (wall) load window began
    load: np.ndarray                # fraction of the bus time busy per window
    frames: int
    bitrate_bps: int
    fault_windows: list[tuple[str, float, float]] = field(default_factory=list)   # (name, start, end) simulated s
    injections: list[tuple[float, str, str]] = field(default_factory=list)        # (simulated s, fault, action)
    on_sim_time: bool = True        # False only for a run without the plant's stamps (then: s since the first frame)

    def to_metrics(self) -> dict:
        actions: dict[str, int] = {}
        for _, fault, action in self.injections:
            actions[f"{fault} {action}"] = actions.get(f"{fault} {action}", 0) + 1
        return {
            "frames": self.frames,
            "bitrate_bps": self.bitrate_bps,
            "mean_load": float(self.load.mean()) if self.load.size else 0.0,
            "peak_load": float(self.load.max()) if self.load.size else 0.0,
            "faults": [{"name": n.removesuffix(LIVE_SUFFIX), "start_sim_s": a, "end_sim_s": b,
                        "live": n.endswith(LIVE_SUFFIX)} for n, a, b in self.fault_windows],
            "injections": actions,
        }


def read_capture(path: Path) -> list[can.Message]:
    return [m for m in can.CanutilsLogReader(str(path)) if not m.is_error_frame]


def bus_load(run: RunData) -> BusLoad | None:
    if run.can_log is None:
        return None
    frames = read_capture(run.can_log)
    can_cfg = getattr(run.scenario, "can", None)
    bitrate = int(getattr(can_cfg, "bitrate_bps", DEFAULT_BITRATE_BPS))
    model = _bus_model_report(run.run_dir)
    clock = _bus_clock(model, RunClock.from_run(run.trajectory, run.scenario))
    result = BusLoad(np.zeros(0), np.zeros(0), len(frames), bitrate, fault_windows_sim_s(run.run_dir, can_cfg, clock),
                     _injections(run.run_dir, clock), on_sim_time=clock is not None and "wall_offset_s" in model)
    if frames:
        wall_s = np.asarray([f.timestamp for f in frames])
        t_s = wall_s - wall_s[0]
        bits = np.asarray([frame_bits(f) for f in frames], dtype=float)
        # Rounded first: candump's microsecond timestamps put 0.3 s at 2.9999... windows otherwise.
        window = np.floor(np.round(t_s / WINDOW_S, 6)).astype(int)
        busy_bits = np.bincount(window, weights=bits, minlength=int(window.max()) + 1)
        window_start_wall_s = wall_s[0] + np.arange(busy_bits.size) * WINDOW_S
        load = busy_bits / (bitrate * WINDOW_S)
        if result.on_sim_time:
            # the windows of the run: before its first step the nodes start, after its last they stop
            start_s = clock.sim_s(wall_to_mono_ns(window_start_wall_s, model["wall_offset_s"]))
            inside = (start_s >= clock.start_sim_s - WINDOW_S * (clock.sim_s_per_wall_s or 1.0)) & (start_s <= clock.end_sim_s)
            result.window_start_s, load = start_s[inside], load[inside]
        else:
            result.window_start_s = window_start_wall_s - wall_s[0]
        result.load = load
    return result


@dataclass(frozen=True)
class _SimulatedBusClock:
    """The map of a bus that ran on simulated time: bus ns -> simulated s (RunClock's interface)."""
    sim_zero_ns: int
    start_sim_s: float
    end_sim_s: float
    sim_s_per_wall_s: float = 1.0

    def sim_s(self, t_ns):
        out = (np.asarray(t_ns, dtype=float) - self.sim_zero_ns) / 1e9
        return float(out) if out.ndim == 0 else out


def _bus_clock(model: dict, run_clock: RunClock | None):
    """How this run's bus stamps map to simulated time: the run's clock, or the bus's own."""
    if model.get("clock") != "simulated" or run_clock is None:
        return run_clock
    return _SimulatedBusClock(int(model["sim_zero_ns"]), run_clock.start_sim_s, run_clock.end_sim_s)


def capture_sim_s(run_dir: Path, clock: RunClock | None, timestamps) -> np.ndarray | None:
    """Simulated seconds of can.log capture timestamps: on a bus that ran on simulated time (lock-step,
    busmodel.json `clock` = "simulated") the stamps are bus time, `(t - sim_zero_ns / 1e9)`; on a bus
    on the wall clock they are wall (epoch) seconds, mapped through the run's clock (`wall_offset_s`).
    Not clipped: the board's boot comes before the first step and its safe state after the last.
    None without the bus model's report or the plant's stamps (nothing to place them by)."""
    model = _bus_model_report(run_dir)
    t = np.asarray(timestamps, dtype=float)
    if model.get("clock") == "simulated" and model.get("sim_zero_ns") is not None:
        return t - int(model["sim_zero_ns"]) / 1e9
    if clock is None or model.get("wall_offset_s") is None:
        return None
    return np.atleast_1d(clock.sim_s(wall_to_mono_ns(t, float(model["wall_offset_s"]))))


def capture_wall_s(run_dir: Path, timestamps) -> np.ndarray:
    """Wall-clock (epoch) seconds of can.log capture timestamps; NaN where the bus ran on simulated
    time (its capture has no wall clock)."""
    t = np.asarray(timestamps, dtype=float)
    return np.full(t.shape, np.nan) if _bus_model_report(run_dir).get("clock") == "simulated" else t


def _bus_model_report(run_dir: Path) -> dict:
    path = Path(run_dir) / BUSMODEL_FILE
    try:
        return json.loads(path.read_text()) if path.is_file() else {}
    except (OSError, ValueError):
        return {}


def fault_windows_sim_s(run_dir: Path, can_cfg, clock: RunClock | None) -> list[tuple[str, float, float]]:
    """Configured faults as (name, start, end) in simulated seconds, clipped to the run, then those
    injected while it ran (can/live_faults.json, numbered after the scenario's by the injector; their
    names end with LIVE_SUFFIX); empty without the bus model's arming time or the plant's stamps
    (nothing to place them by)."""
    scripted = list(getattr(can_cfg, "faults", None) or [])
    faults = scripted + live_fault_specs(run_dir)
    model = _bus_model_report(run_dir)
    clock = _bus_clock(model, clock)
    t0_ns = model.get("faults_t0_ns")
    if not faults or t0_ns is None or clock is None:
        return []
    affected = {i: record for i, record in enumerate(model.get("faults", []))}
    scale = float(model.get("fault_clock_scale", 1.0))    # bus seconds per simulated second
    windows = []
    for i, fault in enumerate(faults):
        armed = affected.get(i) or {}
        start_ns = armed.get("start_ns") or t0_ns + float(fault.start_s) * scale * 1e9
        if fault.duration_s is not None:
            end_ns = armed.get("end_ns") or start_ns + float(fault.duration_s) * scale * 1e9
        elif fault.hardware:   # a hardware fault without an end: to the run's end
            end_ns = float("inf")
        else:   # limited by a count: it ends with the last frame it affected (or where it began)
            end_ns = armed.get("last_ns") or start_ns
        start, end = (min(max(clock.sim_s(t), clock.start_sim_s), clock.end_sim_s) if t != float("inf")
                      else clock.end_sim_s for t in (start_ns, end_ns))
        windows.append((str(fault.name) + (LIVE_SUFFIX if i >= len(scripted) else ""), start, end))
    return windows


DETECTION_KINDS_LEFT_OUT = frozenset({"heartbeat_resumed", "board_error_reset", "error_active", "bus_restarted",
                                      "host_overrun"})   # the bus well again, or the host: bench.studies.fault_bus


def fault_detections(run_dir: Path, windows: list[tuple[str, float, float]], clock: RunClock | None) -> list[dict]:
    """Per fault window (fault_windows_sim_s' order), what the flight side detected first: the first
    alarm of the driver or the FDIR monitor (can/driver.json; not the kinds that say the bus is well
    again) at or after the fault's start and before the next fault's start, on simulated time, as the
    fault campaign's matrix has it: {"detected", "first_detection", "detected_by", "detected_sim_s",
    "detection_latency_s"} (latency from the fault's start, simulated seconds)."""
    from bench.studies.fault_bus import monitor_of

    path = Path(run_dir) / "can" / "driver.json"
    try:
        events = json.loads(path.read_text()).get("events") or [] if path.is_file() else []
    except (OSError, ValueError):
        events = []
    clock = _bus_clock(_bus_model_report(run_dir), clock)
    alarms = []
    if clock is not None:
        alarms = sorted((float(clock.sim_s(e["detected_ns"])), e["kind"]) for e in events
                        if e.get("kind") not in DETECTION_KINDS_LEFT_OUT and e.get("detected_ns") is not None)
    starts = sorted(start for _, start, _ in windows)
    out = []
    for _, start, _ in windows:
        later = [s for s in starts if s > start]
        until = later[0] if later else float("inf")
        first = next(((t, kind) for t, kind in alarms if start <= t < until), None)
        out.append({"detected": first is not None, "first_detection": first[1] if first else None,
                    "detected_by": monitor_of(first[1]) if first else None,
                    "detected_sim_s": first[0] if first else None,
                    "detection_latency_s": first[0] - start if first else None})
    return out


# Faults that hold frames on the bus themselves (a dead board acknowledges nothing, a babbling node
# takes the bus): in their windows the bus model's lateness is partly the fault's.
FAULTS_THAT_DELAY_FRAMES = frozenset({"board_power_loss", "flood"})
HOST_HELD_MARGIN_S = 0.5      # a hold this close before a window changes what the fault meets


def host_held_per_fault_s(run: RunData) -> dict[str, float]:
    """Per fault window, from HOST_HELD_MARGIN_S before it to HOST_HELD_MARGIN_S after: how long the
    host held up the driver, the board or the bus model (their own records, can/; `held_s`: one
    hold that several records noticed counts once), the bus model left out in the windows of
    FAULTS_THAT_DELAY_FRAMES. A hold just before the window counts: a suite run's bus model, held
    0.16 s, delivered commands past the board's timeout 11 ms before the drop fault began, and the
    board, already in its safe state, had no timeout left for the drop to cause."""
    clock = RunClock.from_run(run.trajectory, run.scenario)
    records = load_host_late_records(run.run_dir / "can")
    held = {}
    for name, start, end in fault_windows_sim_s(run.run_dir, run.scenario.can, clock):
        lo_ns, hi_ns = (clock.monotonic_ns(t) for t in (start - HOST_HELD_MARGIN_S, end + HOST_HELD_MARGIN_S))
        held[name] = held_s([r for r in records if not (r.node == "bus_model" and name in FAULTS_THAT_DELAY_FRAMES)],
                            lo_ns, hi_ns)
    return held


def _injections(run_dir: Path, clock: RunClock | None) -> list[tuple[float, str, str]]:
    """What the injector did and when (simulated s), if it logged anything."""
    path = Path(run_dir) / INJECTIONS_FILE
    if not path.is_file() or clock is None:
        return []
    records = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    if not records:
        return []
    clock = _bus_clock(_bus_model_report(run_dir), clock)
    times = clock.sim_s(np.asarray([r["t_ns"] for r in records], dtype=float))
    return [(float(t), r["fault"], r["action"]) for t, r in zip(np.atleast_1d(times), records)]


BUS_OFF_EPISODES_IN_REPORT = 10      # the report's table lists the first ones; metrics.json has every one listed


def bus_off_metrics(run_dir: Path, clock: RunClock | None) -> dict:
    """Each node's bus-off episodes and their recoveries (ISO 11898-1: back after 128 x 11 recessive
    bits) from busmodel.json: per node the episodes, how many recovered, the longest and total time
    off the bus (ms), and the episodes the bus model listed, on simulated time where the run has
    a clock (else the bus model's seconds since its start). Empty: no bus-off, or no report."""
    model = _bus_model_report(run_dir)
    counts = model.get("bus_off") or {}
    if not isinstance(counts, dict) or not counts:
        return {}
    recovered = model.get("bus_off_recovered") or {}
    clock = _bus_clock(model, clock)
    t0_ns = model.get("t0_ns") or 0

    def when_s(t_ns):
        if t_ns is None:
            return None
        return float(clock.sim_s(t_ns)) if clock is not None else (t_ns - t0_ns) / 1e9

    nodes = {node: {"episodes": int(n), "recovered": int(recovered.get(node, 0)),
                    "longest_ms": (model.get("bus_off_longest_ns") or {}).get(node, 0) / 1e6,
                    "total_ms": (model.get("bus_off_time_ns") or {}).get(node, 0) / 1e6}
             for node, n in sorted(counts.items())}
    episodes = [{"node": e["node"], "bus_off_s": when_s(e["bus_off_ns"]), "recovered_s": when_s(e["recovered_ns"]),
                 "off_ms": None if e["recovered_ns"] is None else (e["recovered_ns"] - e["bus_off_ns"]) / 1e6}
                for e in model.get("bus_off_episodes") or []]
    return {"nodes": nodes, "episodes": episodes, "episodes_left_off": int(model.get("bus_off_episodes_left_off", 0)),
            "recovery_bits": model.get("bus_off_recovery_bits"),
            "on_sim_time": clock is not None}


def bus_off_rows(bus_off: dict) -> list[list[str]]:
    """The report's rows for bus-off episodes: one per node, then the first episodes."""
    if not bus_off:
        return []
    rows = []
    for node, n in bus_off["nodes"].items():
        still = n["episodes"] - n["recovered"]
        rows.append([f"bus-off {node}", f"{n['episodes']} times, {n['recovered']} recovered (each after 128 x 11 "
                     f"recessive bits: {bus_off.get('recovery_bits') or 1408} bit times on an idle bus, more on a busy "
                     f"one); longest {fmt(n['longest_ms'])} ms, total {fmt(n['total_ms'])} ms"
                     + ("; still bus-off at the end" if still else "")])
    time_kind = "simulated" if bus_off.get("on_sim_time") else "since the bus model started"
    for e in bus_off["episodes"][:BUS_OFF_EPISODES_IN_REPORT]:
        back = "not recovered by the end" if e["recovered_s"] is None else \
            f"recovered at {fmt(e['recovered_s'], 7)} s ({fmt(e['off_ms'])} ms off the bus)"
        rows.append([f"bus-off {e['node']} at {fmt(e['bus_off_s'], 7)} s ({time_kind})", back])
    left_off = len(bus_off["episodes"]) - BUS_OFF_EPISODES_IN_REPORT + bus_off.get("episodes_left_off", 0)
    if left_off > 0:
        rows.append(["bus-off episodes not listed", fmt(left_off)])
    return rows


def board_power_metrics(run_dir: Path, clock: RunClock | None) -> dict:
    """The board's power losses and its recovery from each (board.json `power_log`), on simulated
    time: when power went, when it came back (the board booted, pre-operational), when the driver's
    NMT start made it operational again, and the recovery (operational minus booted, ms). Empty
    without a power loss."""
    path = Path(run_dir) / "can" / "board.json"
    try:
        log = (json.loads(path.read_text()).get("power_log") or []) if path.is_file() else []
    except (OSError, ValueError):
        return {}
    if not log:
        return {}
    clock = _bus_clock(_bus_model_report(run_dir), clock)

    def when_s(t_ns):
        return float(clock.sim_s(t_ns)) if clock is not None else t_ns / 1e9

    episodes = []
    for entry in log:
        if entry["event"] == "power_lost":
            episodes.append({"lost_s": when_s(entry["t_ns"]), "booted_s": None, "operational_s": None,
                             "recovery_ms": None})
        elif episodes and entry["event"] in ("booted", "operational"):
            episodes[-1][f"{entry['event']}_s"] = when_s(entry["t_ns"])
            if entry["event"] == "operational" and episodes[-1]["booted_s"] is not None:
                episodes[-1]["recovery_ms"] = (episodes[-1]["operational_s"] - episodes[-1]["booted_s"]) * 1e3
    recoveries = [e["recovery_ms"] for e in episodes if e["recovery_ms"] is not None]
    return {"losses": len(episodes), "recovered": len(recoveries),
            "max_recovery_ms": max(recoveries) if recoveries else None, "episodes": episodes,
            "on_sim_time": clock is not None}


def board_power_rows(power: dict) -> list[list[str]]:
    """The report's rows for the board's power losses: each loss, its reboot and its recovery."""
    rows = []
    for e in (power or {}).get("episodes", []):
        back = "power not back by the end" if e["booted_s"] is None else (
            f"booted at {fmt(e['booted_s'], 7)} s, " + ("never operational again" if e["operational_s"] is None else
                                                          f"operational again at {fmt(e['operational_s'], 7)} s "
                                                          f"(NMT start {fmt(e['recovery_ms'])} ms after the boot, "
                                                          f"simulated)"))
        rows.append([f"board power lost at {fmt(e['lost_s'], 7)} s (simulated)", back])
    return rows


def driver_events(path: Path) -> tuple[list[list[str]] | None, dict | None]:
    """What the flight-side driver detected (can/driver.json), per kind: table rows (count, first
    and worst detection latency in ms, the final health) and the metrics."""
    if not path.is_file():
        return None, None
    report = json.loads(path.read_text())
    by_kind: dict[str, list[float]] = {}
    for event in report["events"]:
        by_kind.setdefault(event["kind"], []).append(event["latency_s"])
    rows = [[kind, fmt(len(lat)), fmt(lat[0] * 1e3), fmt(max(lat) * 1e3)] for kind, lat in sorted(by_kind.items())]
    rows.append(["board healthy at the end", "yes" if report["health"]["ok"] else "NO", "", ""])
    metrics = {"events": {k: len(v) for k, v in by_kind.items()},
               "worst_latency_s": {k: max(v) for k, v in by_kind.items()},
               "board_ok_at_end": report["health"]["ok"]}
    return rows, metrics


def can_metrics(run: RunData) -> tuple[BusLoad | None, dict | None, list[list[str]] | None]:
    """The bus's figures for metrics.json (with or without the report): load, faults, injections,
    whether commands are authenticated, and what the driver detected (also as the report's table
    rows)."""
    load = bus_load(run)
    if load is None:
        return None, None, None
    m = load.to_metrics()
    can = getattr(run.scenario, "can", None)
    m["authenticated"] = can.security.authenticated if can is not None else None
    m["bus_off"] = bus_off_metrics(run.run_dir, RunClock.from_run(run.trajectory, run.scenario))
    m["board_power"] = board_power_metrics(run.run_dir, RunClock.from_run(run.trajectory, run.scenario))
    driver_rows, driver_metrics = driver_events(run.run_dir / "can" / "driver.json")
    if driver_metrics is not None:
        m["driver"] = driver_metrics
    # Each fault with what detected it first (scripted or live alike), and the live injections asked for.
    detections = fault_detections(run.run_dir, load.fault_windows, RunClock.from_run(run.trajectory, run.scenario))
    m["faults"] = [{**fault, **found} for fault, found in zip(m["faults"], detections)]
    live = read_live_faults(run.run_dir)
    if live:
        m["live_faults"] = {"allowed": bool(live.get("allowed")), "taken": len(live.get("accepted") or []),
                            "refused": dict(live.get("refused") or {}),
                            "requested_by": sorted({e.get("requested_by", "") for e in live.get("accepted") or []})}
    return load, m, driver_rows
