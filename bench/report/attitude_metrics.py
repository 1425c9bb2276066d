"""Metrics of an attitude run, from the arrays the attitude plant writes (trajectory.npz).

- pointing error (deg) to the scenario's target at every step; final, max after settling, settling
  time (the error stays inside the band from then on);
- body rate (deg/s); time to detumble (the rate stays below the threshold from then on);
- dipole per axis against the limit, and the share of steps the law commanded at the limit;
- applied against commanded dipole (after the board's quantisation), refused board reports;
- the field's strength along the orbit;
- sense-to-actuation latency percentiles from the stamps.
"""
from __future__ import annotations

import numpy as np

from bench.gnc import quaternion as qt
from bench.plant.mtq_acceptance import board_dipole_without_bus
from bench.scenario import Scenario

DETUMBLE_THRESHOLD_DPS = 0.1
SETTLING_BAND_DEG = 2.0


def pointing_error_deg(trajectory: dict, scenario: Scenario) -> np.ndarray | None:
    """Angle between the body and the target frame per step; None for laws without a target."""
    from bench.config.controller import TARGET_FREE_LAWS

    if scenario.attitude_control.law in TARGET_FREE_LAWS:
        return None
    from bench.controller.attitude_laws import attitude_target   # the flight side's target

    target = attitude_target(scenario)
    return np.rad2deg([qt.angle_between_rad(target(t).q_wxyz, q)
                       for t, q in zip(trajectory["att_time_s"], trajectory["att_q_wxyz"])])


def continuous_rotation_angle_deg(trajectory: dict, scenario: Scenario) -> np.ndarray:
    """Rotation angle of the error quaternion on [0, 720) deg, kept continuous (no sign choice):
    a slew that starts at 200 deg goes the short way if this rises to 360, the long way if it
    falls through 180."""
    from bench.controller.attitude_laws import attitude_target

    target = attitude_target(scenario)
    angles, previous = [], None
    for t, q in zip(trajectory["att_time_s"], trajectory["att_q_wxyz"]):
        q_e = qt.multiply(qt.conjugate(target(t).q_wxyz), q)
        if previous is not None and q_e @ previous < 0:
            q_e = -q_e                       # same attitude; keep the path continuous on S^3
        previous = q_e
        angles.append(np.rad2deg(2 * np.arctan2(np.linalg.norm(q_e[1:]), q_e[0])) % 720.0)
    return np.array(angles)


def first_time_staying_below(times: np.ndarray, values: np.ndarray, threshold: float) -> float | None:
    above = np.nonzero(values >= threshold)[0]
    if len(above) == 0:
        return float(times[0])
    last = above[-1]
    return float(times[last + 1]) if last + 1 < len(times) else None


def _percentiles_ms(start: np.ndarray, end: np.ndarray) -> dict:
    ok = (start >= 0) & (end >= 0)
    if not ok.any():
        return {"samples": 0}
    ms = (end[ok] - start[ok]) / 1e6
    return {"samples": int(ok.sum()), "p50_ms": float(np.percentile(ms, 50)), "p90_ms": float(np.percentile(ms, 90)),
            "p99_ms": float(np.percentile(ms, 99)), "max_ms": float(ms.max())}


def attitude_metrics(trajectory: dict, scenario: Scenario) -> dict:
    from bench.controller.attitude_laws import dipole_limit_am2
    times = trajectory["att_time_s"]
    rate_dps = np.rad2deg(np.linalg.norm(trajectory["att_omega_radps"], axis=1))
    applied = trajectory["att_dipole_applied_am2"]
    commanded = trajectory["att_dipole_commanded_am2"]
    limit = dipole_limit_am2(scenario)
    has_command = np.all(np.isfinite(commanded), axis=1)
    expected = np.array([board_dipole_without_bus(c, scenario.can) if ok else np.zeros(3)
                         for c, ok in zip(commanded, has_command)]).reshape(-1, 3)
    field_nt = np.linalg.norm(trajectory["att_field_inertial_t"], axis=1) * 1e9
    metrics = {
        "kind": "attitude",
        "steps": int(len(times)),
        "duration_s": float(times[-1] - times[0]) if len(times) else 0.0,
        "law": scenario.attitude_control.law,
        "initial_rate_dps": float(rate_dps[0]),
        "final_rate_dps": float(rate_dps[-1]),
        "time_to_detumble_s": first_time_staying_below(times, rate_dps, DETUMBLE_THRESHOLD_DPS),
        # B-dot settles near twice the orbit rate (it follows the field), ~0.13 deg/s at 500 km:
        # the rate may dip below the threshold long before it stays there.
        "first_below_detumble_threshold_s": float(times[np.argmax(rate_dps < DETUMBLE_THRESHOLD_DPS)])
        if np.any(rate_dps < DETUMBLE_THRESHOLD_DPS) else None,
        "min_rate_dps": float(rate_dps.min()),
        "detumble_threshold_dps": DETUMBLE_THRESHOLD_DPS,
        "dipole_limit_am2": limit,
        "max_abs_dipole_applied_am2": np.abs(applied).max(axis=0).tolist(),
        "saturation_fraction": float(np.mean(np.any(np.abs(commanded[has_command]) >= limit * (1 - 1e-9), axis=1)))
        if has_command.any() else 0.0,
        "max_applied_minus_commanded_am2": float(np.abs(applied[has_command] - expected[has_command]).max())
        if has_command.any() else 0.0,
        "steps_without_command": int((~has_command).sum()),
        "refused_board_reports": int(trajectory.get("plant_refused_reports", 0)),
        "field_nt": {"min": float(field_nt.min()), "max": float(field_nt.max())},
    }
    error = pointing_error_deg(trajectory, scenario)
    if error is not None:
        settle = first_time_staying_below(times, error, SETTLING_BAND_DEG)
        metrics.update({
            "initial_pointing_error_deg": float(error[0]),
            "final_pointing_error_deg": float(error[-1]),
            "max_pointing_error_deg": float(error.max()),
            "settling_band_deg": SETTLING_BAND_DEG,
            "settling_time_s": settle,
            "max_error_after_settling_deg": float(error[times >= settle].max()) if settle is not None else None,
        })
    if "stamp_sensed_ns" in trajectory:
        metrics["latency"] = {
            "sense_to_can_sent": _percentiles_ms(trajectory["stamp_sensed_ns"], trajectory["stamp_can_sent_ns"]),
            "sense_to_board": _percentiles_ms(trajectory["stamp_sensed_ns"], trajectory["stamp_board_received_ns"]),
            "sense_to_plant": _percentiles_ms(trajectory["stamp_sensed_ns"], trajectory["stamp_plant_received_ns"]),
        }
    return metrics


def is_detumble(law: str) -> bool:
    """A law whose job is to detumble (B-dot and its kin), for which time to detumble means something."""
    return "detumble" in law or "bdot" in law


def summary_rows(metrics: dict) -> list[tuple[str, str]]:
    def fmt(value, unit, digits=3):
        return "-" if value is None else f"{value:.{digits}g} {unit}"

    rows = [("law", metrics["law"]),
            ("body rate initial / final", f"{metrics['initial_rate_dps']:.3g} / {metrics['final_rate_dps']:.3g} deg/s")]
    if is_detumble(metrics["law"]):     # not for slews and holds: they do not detumble
        rows.append((f"time to detumble (< {metrics['detumble_threshold_dps']} deg/s)",
                     fmt(metrics["time_to_detumble_s"], "s")))
    if "final_pointing_error_deg" in metrics:
        rows += [("pointing error initial / final", f"{metrics['initial_pointing_error_deg']:.3g} / "
                                                     f"{metrics['final_pointing_error_deg']:.3g} deg"),
                 (f"settling time (< {metrics['settling_band_deg']} deg)", fmt(metrics["settling_time_s"], "s"))]
    rows += [("saturation fraction", f"{metrics['saturation_fraction']:.1%}"),
             ("max |applied - commanded|", f"{metrics['max_applied_minus_commanded_am2']:.2g} A m^2"),
             ("refused board reports", str(metrics["refused_board_reports"]))]
    latency = metrics.get("latency", {}).get("sense_to_board", {})
    if latency.get("samples"):
        rows.append(("sense -> board p50 / p99", f"{latency['p50_ms']:.2f} / {latency['p99_ms']:.2f} ms"))
    return rows


def applied_is_commanded_or_zero(trajectory: dict, can, commanded=None) -> np.ndarray:
    """Per step: True when the dipole the plant applied is zero or what the board makes of a dipole
    the law commanded in this run (so no frame altered on the bus moved the coils). `commanded`:
    every dipole the controller published (the recording's command/dipole); the plant's own log
    misses commands that reached it after their step in real time."""
    commanded = trajectory["att_dipole_commanded_am2"] if commanded is None else np.asarray(commanded, float)
    expected = {tuple(board_dipole_without_bus(c, can)) for c in commanded if np.all(np.isfinite(c))}
    return np.array([not np.any(a) or tuple(a) in expected for a in trajectory["att_dipole_applied_am2"]])


def whole_steps(trajectory: dict, can) -> np.ndarray:
    """Per step, whether the plant applied what the board makes of the dipole commanded in that
    step (or, in real time, in the step before: the latest report is held over a step, so a
    command that changed mid-step shows the previous value)."""
    commanded, applied = trajectory["att_dipole_commanded_am2"], trajectory["att_dipole_applied_am2"]

    def as_board_applies(c, a) -> bool:
        return bool(np.all(np.isfinite(c)) and np.array_equal(board_dipole_without_bus(c, can), a))

    whole = np.array([as_board_applies(c, a) for c, a in zip(commanded, applied)])
    previous = np.array([False] + [as_board_applies(c, a) for c, a in zip(commanded[:-1], applied[1:])])
    return whole | previous


def loop_recovery_s(trajectory: dict, can, after_sim_s: float, excused: np.ndarray | None = None) -> float | None:
    """Simulated time after `after_sim_s` until the loop is whole (`whole_steps`) at every later
    step; None if never. excused: steps not to count against the loop (for example those a
    real-time run's host held up: bench.bus.can.host_lateness)."""
    times = trajectory["att_time_s"]
    whole = whole_steps(trajectory, can)
    if excused is not None:
        whole |= np.asarray(excused, bool)
    later = times >= after_sim_s
    broken = np.nonzero(later & ~whole)[0]
    if len(broken) == 0:
        return 0.0
    last = broken[-1]
    return float(times[last + 1] - after_sim_s) if last + 1 < len(times) else None


def fault_effect(clean: dict, faulted: dict, scenario: Scenario, fault_end_sim_s: float) -> dict:
    """The mission effect of a fault: the excess of the pointing error (or of the body rate, for
    laws without a target) over the clean run of the same scenario, step by step, and how long
    after the fault the loop applied what it commanded again."""
    n = min(len(clean["att_time_s"]), len(faulted["att_time_s"]))
    clean_c = {k: v[:n] for k, v in clean.items() if isinstance(v, np.ndarray) and v.ndim and len(v) >= n}
    faulted_c = {k: v[:n] for k, v in faulted.items() if isinstance(v, np.ndarray) and v.ndim and len(v) >= n}
    error_f, error_c = pointing_error_deg(faulted_c, scenario), pointing_error_deg(clean_c, scenario)
    if error_f is None:
        quantity = "body rate [deg/s]"
        error_f = np.rad2deg(np.linalg.norm(faulted_c["att_omega_radps"], axis=1))
        error_c = np.rad2deg(np.linalg.norm(clean_c["att_omega_radps"], axis=1))
    else:
        quantity = "pointing error [deg]"
    excess = error_f - error_c
    return {"quantity": quantity, "max_excess": float(excess.max()), "final_excess": float(excess[-1]),
            "loop_recovery_s": loop_recovery_s(faulted, scenario.can, fault_end_sim_s)}
