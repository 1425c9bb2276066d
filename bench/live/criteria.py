"""The scenario's criteria as they stand, while the run runs (the live view's `live/criteria`).

A criterion bounds a figure of metrics.json (bench/criteria.py), most of which exist only once the
run is over. What can be followed as the run goes is computed here from the same sources the
report uses, on the messages the live view receives, under the same names, and judged with the
same `bench.criteria.judge`:

| metrics.json figure                               | live, from                                            |
|---------------------------------------------------|-------------------------------------------------------|
| final_rate_dps, final_pointing_error_deg          | the newest truth/attitude (what it would be if the run ended now) |
| max_pointing_error_deg, initial_*                 | every truth/attitude so far                           |
| time_to_detumble_s                                | the first time the rate stayed below 0.1 deg/s so far |
| final_position_error_m, final_velocity_error_mps  | the newest truth (rendezvous)                         |
| can_bus.driver.events.KIND, worst_latency_s.KIND  | event/can (the driver's and FDIR's detections so far) |

Anything else (constraints over the whole run, the board's health at the end, its power
recoveries, latencies) is "judged at the end". A criterion's state is "holds now" or "does not
hold now": a final figure can still change, a running maximum only grow.
"""
from __future__ import annotations

import math

import numpy as np

from bench.criteria import judge
from bench.gnc import quaternion as qt

DETUMBLE_THRESHOLD_DPS = 0.1      # bench.report.attitude_metrics.DETUMBLE_THRESHOLD_DPS
HOLDS, FAILS, AT_END = "holds now", "does not hold now", "judged at the end"


class LiveMetrics:
    """The figures of metrics.json that the run's messages give as it runs (module docstring)."""

    def __init__(self, scenario):
        self.scenario = scenario
        self.metrics: dict = {}
        self._target = None
        if scenario.kind == "attitude":
            from bench.config.controller import TARGET_FREE_LAWS

            if scenario.attitude_control.law not in TARGET_FREE_LAWS:
                from bench.controller.attitude_laws import attitude_target   # the flight side's target

                self._target = attitude_target(scenario)
        self._below_since_s: float | None = None
        self.events: dict[str, int] = {}
        self.worst_latency_s: dict[str, float] = {}

    def target_q(self, t_s: float) -> np.ndarray | None:
        return None if self._target is None else np.asarray(self._target(t_s).q_wxyz, float)

    def pointing_error_deg(self, t_s: float, q_wxyz) -> float | None:
        target = self.target_q(t_s)
        return None if target is None else math.degrees(qt.angle_between_rad(target, np.asarray(q_wxyz, float)))

    def on_attitude_truth(self, t_s: float, q_wxyz, omega_radps) -> dict:
        """A truth/attitude sample; returns the step's figures (rate, pointing error)."""
        m = self.metrics
        rate_dps = math.degrees(float(np.linalg.norm(omega_radps)))
        m.setdefault("initial_rate_dps", rate_dps)
        m["final_rate_dps"] = rate_dps
        m["min_rate_dps"] = min(m.get("min_rate_dps", rate_dps), rate_dps)
        if rate_dps >= DETUMBLE_THRESHOLD_DPS:
            self._below_since_s = None
        elif self._below_since_s is None:
            self._below_since_s = t_s
        m["time_to_detumble_s"] = self._below_since_s
        error = self.pointing_error_deg(t_s, q_wxyz)
        if error is not None:
            m.setdefault("initial_pointing_error_deg", error)
            m["final_pointing_error_deg"] = error
            m["max_pointing_error_deg"] = max(m.get("max_pointing_error_deg", error), error)
        return {"rate_dps": rate_dps, "pointing_error_deg": error}

    def on_translation_truth(self, state_m_mps) -> None:
        state = np.asarray(state_m_mps, float)
        self.metrics["final_position_error_m"] = float(np.linalg.norm(state[:3]))
        self.metrics["final_velocity_error_mps"] = float(np.linalg.norm(state[3:6]))

    def on_bus_event(self, kind: str, latency_s: float) -> None:
        self.events[kind] = self.events.get(kind, 0) + 1
        self.worst_latency_s[kind] = max(self.worst_latency_s.get(kind, 0.0), float(latency_s))
        driver = self.metrics.setdefault("can_bus", {}).setdefault("driver", {})
        driver["events"] = dict(self.events)
        driver["worst_latency_s"] = dict(self.worst_latency_s)

    def judged(self) -> list[dict]:
        """Each criterion of the scenario with its value now and its state (HOLDS, FAILS, AT_END)."""
        out = []
        metrics = self.metrics
        if self.scenario.kind == "attitude" and self.scenario.can is not None:
            # An event kind not seen yet has happened 0 times so far (the end's metrics say the same).
            driver = metrics.setdefault("can_bus", {}).setdefault("driver", {})
            driver.setdefault("events", {})
        for criterion in self.scenario.criteria:
            result = judge(criterion, _with_zero_counts(metrics, criterion.metric))
            live = result["value"] != "not measured"
            result["state"] = (HOLDS if result["passed"] else FAILS) if live else AT_END
            result["live"] = live
            if not live:
                result["value"] = None
            elif isinstance(result["value"], float) and not math.isfinite(result["value"]):
                result["value"] = None
            out.append(result)
        return out


def _with_zero_counts(metrics: dict, path: str) -> dict:
    """An event count the run has not raised yet is 0 so far (not 'not measured')."""
    parts = path.split(".")
    if parts[:3] == ["can_bus", "driver", "events"] and len(parts) == 4:
        events = metrics.get("can_bus", {}).get("driver", {}).get("events")
        if isinstance(events, dict) and parts[3] not in events:
            return {**metrics, "can_bus": {**metrics["can_bus"], "driver": {
                **metrics["can_bus"]["driver"], "events": {**events, parts[3]: 0}}}}
    return metrics
