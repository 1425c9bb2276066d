"""One time base per run: the run's simulated time, onto which every monotonic stamp is mapped.

Processes stamp what they do on the host's monotonic clock (message headers, the bus model's
frames and fault windows, the injector's log); the plant stamps each step's sensing on the same
clock and knows the step's simulated time. Those (monotonic, simulated) pairs map any other stamp
of the run onto simulated time, so a fault window, a frame and a plot axis line up with the steps.
Between steps the map is linear. Outside the loop it is linear at the nominal rate in real time
(`time_factor` simulated seconds per wall second) and held at the first or last step in lock-step,
where no simulated time passes while the loop is not running.

CAN captures (can.log) carry wall-clock (epoch) timestamps as candump writes them; the bus model
records the wall-minus-monotonic offset it stamped them with (busmodel.json `wall_offset_s`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RunClock:
    step_mono_ns: np.ndarray      # the plant's sensing stamp of each step that has one
    step_sim_s: np.ndarray        # that step's simulated time
    sim_s_per_wall_s: float | None  # real time: the time factor; lock-step: None (held outside the loop)

    @classmethod
    def from_run(cls, trajectory: dict, scenario) -> "RunClock | None":
        """The map of a run, or None when the plant recorded no sensing stamps."""
        sensed = trajectory.get("stamp_sensed_ns")
        times = trajectory.get("att_time_s", trajectory.get("t_s"))
        if sensed is None or times is None:
            return None
        sensed = np.asarray(sensed, dtype=np.int64)
        times = np.asarray(times, dtype=float)[: sensed.size]
        ok = sensed[: times.size] > 0
        if not ok.any():
            return None
        realtime = scenario is not None and scenario.run.mode == "real-time"
        return cls(sensed[: times.size][ok], times[ok], float(scenario.run.time_factor) if realtime else None)

    def sim_s(self, mono_ns) -> np.ndarray | float:
        """Simulated seconds of monotonic stamps (scalar or array)."""
        rate = None if self.sim_s_per_wall_s is None else self.sim_s_per_wall_s / 1e9
        return _through(mono_ns, self.step_mono_ns.astype(float), self.step_sim_s, rate)

    def monotonic_ns(self, sim_s) -> np.ndarray | float:
        """Monotonic ns of simulated seconds (scalar or array), the inverse of `sim_s`; outside the
        loop in lock-step, where no simulated time passes, the first or last step's stamp."""
        ns_per_s = None if self.sim_s_per_wall_s is None else 1e9 / self.sim_s_per_wall_s
        return _through(sim_s, self.step_sim_s, self.step_mono_ns.astype(float), ns_per_s)

    @property
    def end_sim_s(self) -> float:
        return float(self.step_sim_s[-1])

    @property
    def start_sim_s(self) -> float:
        return float(self.step_sim_s[0])


def _through(t, x: np.ndarray, y: np.ndarray, slope: float | None) -> np.ndarray | float:
    """y at t, linear between the points (x, y); beyond the first and the last, at `slope` from
    them (real time), or held at their y (slope None: lock-step)."""
    t = np.asarray(t, dtype=float)
    out = np.interp(t, x, y)
    if slope is not None:
        out = np.where(t < x[0], y[0] + (t - x[0]) * slope, out)
        out = np.where(t > x[-1], y[-1] + (t - x[-1]) * slope, out)
    return float(out) if out.ndim == 0 else out


def wall_to_mono_ns(wall_s, wall_offset_s: float) -> np.ndarray:
    """Monotonic ns of wall-clock (epoch) seconds, given wall = monotonic + wall_offset_s."""
    return (np.asarray(wall_s, dtype=float) - wall_offset_s) * 1e9
