"""Fault-injection campaigns for the attitude loop: every bus fault x every attitude law x seeds.

A spec (TOML, `kind = "attitude_faults"`) names missions, laws and faults:

    name = "attitude_faults"
    kind = "attitude_faults"
    seeds = 10
    onset_jitter_s = 20.0                  # per seed, the same for every law and fault
    [missions.detumble]
    base_scenario = "attitude_quick"       # built-in name or TOML path
    quantity = "rate"                      # deviation from the clean run: body rate [deg/s] or
    tolerance = 0.05                       #   "pointing" error [deg]; within tolerance = no effect
    patch = { attitude = { duration_s = 600.0 } }
    [laws.bdot_rate_damping]
    mission = "detumble"                   # the mission this law flies
    label = "B-dot + rate damping"
    patch = { attitude_control = { law = "bdot_then_rate_damping" } }
    [faults.drop]                          # a bench.bus.can.faults.FaultSpec; start_s in mission seconds
    name = "drop"
    start_s = 120.0
    duration_s = 10.0

A case is one law (on its mission) x one fault x one seed. It runs the mission twice in process
(`bench.sim.simulate_attitude_in_process`): clean, and with the fault acting through the real
board, driver, bus model and injector co-simulated on the loop's clock
(`bench.studies.fault_bus.BusCoSimulation`). The clean run of a (law, seed) is computed once per
worker process and reused (it is deterministic). The row reports the effect against the clean
run: detumble time, final pointing error and the worst after the onset, time to recover, dipole
effort, whether the fault was detected, how fast (simulated seconds), with what and by which
monitor (the board's checks reported by EMCY, the flight-side driver's own, or the FDIR actuator
monitor's, which the in-process loop runs when [attitude_control.fdir] is on), how long the coils
were off inside the fault's window, whether the board was operational again after it and how long
its NMT start took after a reboot, and the effect class (`EFFECTS`).
"""
from __future__ import annotations

import importlib
import logging
import math
from typing import Annotated, Callable

import msgspec
import numpy as np

from bench.bus.can.faults import FaultSpec
from bench.scenario import ScenarioError, load_scenario, parse_scenario, scenario_to_toml_dict

KIND = "attitude_faults"
CELL_COLUMNS = ("mission", "law", "fault")
IN_PROCESS_LOOP = "bench.sim:simulate_attitude_in_process"       # above this layer: by name
ATTITUDE_METRICS = "bench.report.attitude_metrics:attitude_metrics"
RUNNER = "bench.studies.fault_campaign:fault_case"
# Mission effect, mildest first (the report colours by it): no deviation beyond tolerance from the
# clean run; deviated then back within tolerance for good; never back but the mission still met
# its goal; the goal missed where the clean run met it.
EFFECTS = ("none", "recovered", "degraded", "lost")


class MissionSpec(msgspec.Struct, forbid_unknown_fields=True):
    base_scenario: str
    quantity: str = "pointing"          # "pointing" (error to the target, deg) or "rate" (deg/s)
    tolerance: Annotated[float, msgspec.Meta(gt=0)] = 0.25
    # Mission goal: detumbled by the end (rate), or the final pointing error at most this (deg).
    goal_final_error_deg: float | None = None
    patch: dict = {}


class LawSpec(msgspec.Struct, forbid_unknown_fields=True):
    mission: str
    label: str = ""
    patch: dict = {}


class FaultCampaignSpec(msgspec.Struct, forbid_unknown_fields=True):
    name: str
    kind: str
    missions: dict[str, MissionSpec]
    laws: dict[str, LawSpec]
    faults: dict[str, FaultSpec]
    description: str = ""
    seeds: Annotated[int, msgspec.Meta(ge=1)] = 10
    first_seed: Annotated[int, msgspec.Meta(ge=0)] = 1
    onset_jitter_s: Annotated[float, msgspec.Meta(ge=0)] = 0.0
    steps: Annotated[int, msgspec.Meta(ge=1)] | None = None       # overrides every mission's length
    case_timeout_s: Annotated[float, msgspec.Meta(gt=0)] = 900.0
    mode: str = RUNNER


def parse_spec(data: dict, source: str = "<spec>") -> FaultCampaignSpec:
    from bench.studies.campaign import CampaignError

    try:
        spec = msgspec.convert(data, FaultCampaignSpec)
    except (msgspec.ValidationError, ValueError) as exc:
        raise CampaignError(f"{source}: {exc}") from None
    if spec.kind != KIND:
        raise CampaignError(f"{source}: kind: {spec.kind!r} is not {KIND!r}")
    for axis in ("missions", "laws", "faults"):
        if not getattr(spec, axis):
            raise CampaignError(f"{source}: {axis}: needs at least one entry")
        for name in getattr(spec, axis):
            if not name.strip() or "/" in name:
                raise CampaignError(f"{source}: {axis}.{name!r}: a name must be non-empty and without '/'")
    for name, mission in spec.missions.items():
        if mission.quantity not in ("pointing", "rate"):
            raise CampaignError(f"{source}: missions.{name}.quantity: {mission.quantity!r} is not 'pointing' or 'rate'")
    for name, law in spec.laws.items():
        if law.mission not in spec.missions:
            raise CampaignError(f"{source}: laws.{name}.mission: {law.mission!r} is not one of the missions "
                                f"({', '.join(spec.missions)})")
    for name, fault in spec.faults.items():
        if fault.duration_s is None and fault.count == 0:
            raise CampaignError(f"{source}: faults.{name}: give duration_s or count (a campaign's fault must end)")
    return spec


def _stream(seed: int, label: str) -> np.random.Generator:
    from bench.studies.campaign import _stream as stream

    return stream(seed, label)


def expand(spec: FaultCampaignSpec) -> list:
    """Every case (law x fault x seed), validated, in a fixed order (seeds innermost)."""
    from bench.studies.campaign import Case, CampaignError, _merge, scenario_name

    bases = {name: mission_base(spec, name) for name in spec.missions}
    cases = []
    for law_name, law in spec.laws.items():
        for fault_name, fault in spec.faults.items():
            for seed in range(spec.first_seed, spec.first_seed + spec.seeds):
                # Drawn per seed only: every law and fault of a seed meets its fault at the same time.
                jitter_s = spec.onset_jitter_s * float(_stream(seed, "fault_onset").uniform(-1.0, 1.0))
                fault_data = msgspec.to_builtins(fault)
                fault_data["start_s"] = max(0.0, fault.start_s + jitter_s)
                case_id = f"{law_name}/{fault_name}/seed{seed}"
                scenario = _merge(bases[law.mission], law.patch)
                scenario = _merge(scenario, {
                    "name": scenario_name(spec.name, [law_name, fault_name, f"s{seed}"]), "run": {"seed": seed},
                    "description": f"campaign {spec.name}, case {case_id}"})
                scenario["can"] = {**scenario["can"], "faults": [fault_data]}
                try:
                    parsed = parse_scenario(scenario, f"case {case_id}")
                except ScenarioError as exc:
                    raise CampaignError(str(exc)) from None
                if fault_data["start_s"] >= parsed.attitude.duration_s:
                    raise CampaignError(f"case {case_id}: the fault starts at {fault_data['start_s']:g} s, after the "
                                        f"mission's {parsed.attitude.duration_s:g} s")
                scenario = scenario_to_toml_dict(parsed)
                # The case runner needs the mission's scoring: carried in the scenario's description.
                mission = spec.missions[law.mission]
                scenario["description"] += (f"; quantity={mission.quantity} tolerance={mission.tolerance:g}"
                                            f" goal={mission.goal_final_error_deg}")
                cell = {"mission": law.mission, "law": law.label or law_name, "fault": fault_name}
                cases.append(Case(case_id, len(cases), cell, seed, scenario, spec.mode, spec.case_timeout_s))
    return cases


def mission_base(spec: FaultCampaignSpec, name: str) -> dict:
    """Mission `name`'s scenario as a case starts from it: its base scenario, its patch, the spec's
    steps; before the law's patch, the seed and the fault."""
    from bench.studies.campaign import CampaignError, _merge

    mission = spec.missions[name]
    try:
        base = scenario_to_toml_dict(load_scenario(mission.base_scenario))
    except ScenarioError as exc:
        raise CampaignError(f"missions.{name}: {exc}") from None
    if base.get("kind") != "attitude" or "can" not in base:
        raise CampaignError(f"missions.{name}: {mission.base_scenario!r} is not an attitude scenario with a [can] section")
    base = _merge(base, mission.patch)
    if spec.steps is not None:
        base = _merge(base, {"attitude": {"duration_s": spec.steps / _step_rate_hz(base)}})
    return base


def _step_rate_hz(scenario: dict) -> float:
    return float(scenario.get("attitude", {}).get("sensors", {}).get("gyro_rate_hz", 10.0))


def _scoring(description: str) -> tuple[str, float, float | None]:
    fields = dict(part.split("=", 1) for part in description.rsplit(";", 1)[-1].split())
    goal = None if fields["goal"] == "None" else float(fields["goal"])
    return fields["quantity"], float(fields["tolerance"]), goal


# ------------------------------------------------------------------------------------------------
# One case (in a worker)
# ------------------------------------------------------------------------------------------------
_CLEAN_RUNS: dict[str, dict] = {}        # per worker process: scenario JSON without faults -> trajectory
_CLEAN_RUNS_KEPT = 16


def _by_name(target: str) -> Callable:
    module, _, function = target.partition(":")
    return getattr(importlib.import_module(module), function)


def _clean_trajectory(scenario) -> dict:
    import json

    data = scenario_to_toml_dict(scenario)
    data["can"]["faults"] = []
    data["name"], data["description"] = "clean", ""
    key = json.dumps(data, sort_keys=True)
    if key not in _CLEAN_RUNS:
        if len(_CLEAN_RUNS) >= _CLEAN_RUNS_KEPT:
            _CLEAN_RUNS.pop(next(iter(_CLEAN_RUNS)))
        _CLEAN_RUNS[key] = _by_name(IN_PROCESS_LOOP)(parse_scenario(data, "clean run"))
    return _CLEAN_RUNS[key]


def _series(trajectory: dict, scenario, quantity: str) -> np.ndarray:
    """Per step: pointing error to the target [deg], or body rate [deg/s]."""
    if quantity == "rate":
        return np.rad2deg(np.linalg.norm(trajectory["att_omega_radps"], axis=1))
    from bench.gnc import quaternion as qt

    target = np.asarray(scenario.attitude_control.target.q_wxyz, float)
    return np.rad2deg([qt.angle_between_rad(target, q) for q in trajectory["att_q_wxyz"]])


def effect_metrics(time_s: np.ndarray, faulted: np.ndarray, clean: np.ndarray, tolerance: float, onset_s: float,
                   end_s: float) -> dict:
    """Deviation of the faulted run's quantity from the clean run's after the onset: the worst, when
    it is back within tolerance for good (time to recover, from the fault's end, or from its onset
    when the fault outlasts the mission (a coil that does not heal); 0 when it never left; NaN when
    it is not back by the end)."""
    if end_s >= time_s[-1]:
        end_s = onset_s
    deviation = np.abs(faulted - clean)
    after = time_s >= onset_s
    worst = float(deviation[after].max()) if after.any() else 0.0
    outside = np.flatnonzero(after & (deviation > tolerance))
    if outside.size == 0:
        recover_s = 0.0
    elif outside[-1] == len(deviation) - 1:
        recover_s = float("nan")
    else:
        recover_s = max(0.0, float(time_s[outside[-1] + 1]) - end_s)
    return {"max_deviation": worst, "time_to_recover_s": recover_s, "deviated": bool(outside.size)}


def fault_case(scenario) -> dict:
    """One row's metrics: the mission with its fault against the same mission without it."""
    from bench.bus.can import protocol as p
    from bench.studies.fault_bus import BENIGN_EVENTS, BusCoSimulation, DetectedEvent, fault_end_s, monitor_of

    logging.getLogger("bench.bus.can").setLevel(logging.ERROR)    # the board's safe-state warnings
    quantity, tolerance, goal = _scoring(scenario.description)
    can_config = scenario.can
    faults = list(can_config.faults)
    if len(faults) != 1:
        raise ValueError(f"a fault campaign case has one fault, this one {len(faults)}")
    data = scenario_to_toml_dict(scenario)
    data["can"]["faults"] = []                      # the in-process loop has no bus: the hook is the bus
    bare = parse_scenario(data, scenario.name)
    hook = BusCoSimulation(can_config, faults, scenario.step_s, seed=scenario.run.seed)
    simulate = _by_name(IN_PROCESS_LOOP)
    faulted = simulate(bare, coil_fault=hook)
    clean = _clean_trajectory(bare)
    metrics = _by_name(ATTITUDE_METRICS)
    m_fault, m_clean = metrics(faulted, bare), metrics(clean, bare)
    time_s = np.asarray(faulted["att_time_s"], float)
    series_f, series_c = _series(faulted, bare, quantity), _series(clean, bare, quantity)
    onset_s, end_s = hook.onset_s, fault_end_s(faults[0], can_config.driver.command_period_s)
    effect = effect_metrics(time_s, series_f, series_c, tolerance, onset_s, end_s)
    dt_s = scenario.step_s
    dipole_f = float(np.linalg.norm(faulted["att_dipole_applied_am2"], axis=1).sum() * dt_s)
    dipole_c = float(np.linalg.norm(clean["att_dipole_applied_am2"], axis=1).sum() * dt_s)
    nan = float("nan")

    def goal_met(m: dict, series: np.ndarray) -> bool:
        if quantity == "rate":
            return m["time_to_detumble_s"] is not None and math.isfinite(m["time_to_detumble_s"])
        return goal is None or float(series[-1]) <= goal

    met_f, met_c = goal_met(m_fault, series_f), goal_met(m_clean, series_c)
    if not effect["deviated"]:
        effect_class = "none"
    elif math.isfinite(effect["time_to_recover_s"]):
        effect_class = "recovered"
    elif met_c and not met_f:
        effect_class = "lost"
    else:
        effect_class = "degraded"
    # Every monitor's events: the bus's (board and driver, co-simulated) and the FDIR monitor's
    # from the faulted run, if it ran one (bench.controller.fdir.event_arrays).
    fdir = [DetectedEvent(f"fdir_{c}", float(t), f"axis {a}") for t, a, c in
            zip(faulted.get("fdir_event_time_s", ()), faulted.get("fdir_event_axis", ()), faulted.get("fdir_event_class", ()))]
    events = sorted(hook.events + fdir, key=lambda e: e.time_s)
    alarms = [e for e in events if e.kind not in BENIGN_EVENTS]
    detection = next((e for e in alarms if e.time_s >= onset_s), None)
    after = time_s >= onset_s
    power = hook.power_log()
    booted = [t for event, t in power if event == "booted"]
    started = [t for event, t in power if event == "operational" and booted and t >= booted[-1]]

    def number(value) -> float:
        return nan if value is None else float(value)

    return {
        "fault_kind": faults[0].name,
        "fault_onset_s": float(onset_s),
        "fault_end_s": float(end_s),
        "effect": effect_class,
        "goal_met": met_f,
        "clean_goal_met": met_c,
        "time_to_detumble_s": number(m_fault.get("time_to_detumble_s")) if quantity == "rate" else nan,
        "clean_time_to_detumble_s": number(m_clean.get("time_to_detumble_s")) if quantity == "rate" else nan,
        "final_pointing_error_deg": float(series_f[-1]) if quantity == "pointing" else nan,
        "clean_final_pointing_error_deg": float(series_c[-1]) if quantity == "pointing" else nan,
        "max_pointing_error_after_onset_deg": float(series_f[after].max()) if quantity == "pointing" and after.any() else nan,
        "clean_max_pointing_error_after_onset_deg": float(series_c[after].max()) if quantity == "pointing" and after.any() else nan,
        "final_rate_dps": float(m_fault["final_rate_dps"]),
        "clean_final_rate_dps": float(m_clean["final_rate_dps"]),
        "max_deviation": effect["max_deviation"],          # in the mission's quantity's unit
        "deviation_tolerance": float(tolerance),
        "time_to_recover_s": effect["time_to_recover_s"],
        "fault_outlasts_mission": bool(end_s >= time_s[-1]),
        "dipole_integral_am2s": dipole_f,
        "clean_dipole_integral_am2s": dipole_c,
        "coils_off_s": hook.coils_off_s(),
        "coils_off_in_fault_s": hook.coils_off_in_fault_ns / 1e9,
        "fault_duration_s": float(end_s - onset_s),
        "board_recovery_ms": (started[0] - booted[-1]) * 1e3 if started else nan,
        "board_operational_after": hook.board.nmt_state == p.NMT_OPERATIONAL if hook._started else True,
        "detected": detection is not None,
        "detection_latency_s": detection.time_s - onset_s if detection is not None else nan,
        "first_detection": detection.kind if detection is not None else "",
        "detected_by": monitor_of(detection.kind) if detection is not None else "",
        "monitors": ",".join(sorted({monitor_of(e.kind) for e in alarms if e.time_s >= onset_s})),
        "detection_kinds": ",".join(sorted({e.kind for e in events if e.time_s >= onset_s})),
        "false_alarms": sum(1 for e in alarms if e.time_s < onset_s),
        "steps": int(len(time_s)),
    }


def schema():
    """The results file's columns (Parquet)."""
    import pyarrow as pa

    fields = [("case_id", pa.string()), ("case_index", pa.int64())] + [(c, pa.string()) for c in CELL_COLUMNS]
    fields += [("seed", pa.int64()), ("status", pa.string()), ("error", pa.string())]
    strings = {"fault_kind", "effect", "first_detection", "detected_by", "monitors", "detection_kinds"}
    booleans = {"goal_met", "clean_goal_met", "detected", "board_operational_after", "fault_outlasts_mission"}
    integers = {"false_alarms", "steps"}
    for column in METRIC_COLUMNS:
        fields.append((column, pa.string() if column in strings else pa.bool_() if column in booleans
                       else pa.int64() if column in integers else pa.float64()))
    fields += [("wall_time_s", pa.float64()), ("scenario_json", pa.string())]
    return pa.schema(fields)


METRIC_COLUMNS = (
    "fault_kind", "fault_onset_s", "fault_end_s", "effect", "goal_met", "clean_goal_met", "time_to_detumble_s",
    "clean_time_to_detumble_s", "final_pointing_error_deg", "clean_final_pointing_error_deg",
    "max_pointing_error_after_onset_deg", "clean_max_pointing_error_after_onset_deg", "final_rate_dps",
    "clean_final_rate_dps", "max_deviation", "deviation_tolerance", "time_to_recover_s", "fault_outlasts_mission", "dipole_integral_am2s",
    "clean_dipole_integral_am2s", "coils_off_s", "coils_off_in_fault_s", "fault_duration_s", "board_recovery_ms",
    "board_operational_after", "detected", "detection_latency_s", "first_detection", "detected_by", "monitors",
    "detection_kinds", "false_alarms", "steps")
