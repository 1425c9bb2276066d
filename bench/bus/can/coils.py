"""The board's hardware under the scenario's hardware faults: its power supply and its three coils.

The board has two outputs, and a hardware fault can set them apart:
- the physical dipole, what the coils put into the field (the plant's torque is m x B of it);
- its telemetry, whose current sensor sits in series with each coil, between the coil driver and
  the coil's wiring.

Per axis, for the coil driver's set-point s (zero in safe state and magnetometer windows):

| fault           | physical dipole | current sensor (telemetry) |
|-----------------|-----------------|----------------------------|
| none            | s               | s                          |
| coil_open       | 0               | 0                          |
| coil_stuck v    | v (clipped)     | v                          |
| coil_reversed   | -s              | s  (wired backwards after the sensor) |
| coil_gain g     | g s             | s  (fewer effective turns: the current is right) |

`board_power_loss` switches the whole board off for its window: no coil current, no frame sent,
none heard (no ACK on the bus either, bench/bus/can/busmodel.py); when power returns the board
boots as after a reset (bench/bus/can/board.py). Where two coil faults act on one axis at once,
the later one in the scenario's list wins.

Fault times are the board's clock: `arm(t0_s)` at the first command frame (the bus model's arming
time where the board shares its process, the board's first accepted command where it runs alone),
`start_s` and `duration_s` scaled by `wall_s_per_sim_s` (FaultSpec.window_ns).
"""
from __future__ import annotations

import math

import numpy as np

from bench.bus.can.faults import FaultSpec

NO_FAULT = ("", 0.0)


class CoilHardware:
    def __init__(self, specs: list[FaultSpec], max_dipole_am2: float = math.inf, wall_s_per_sim_s: float = 1.0):
        # (index in the scenario's list, spec): the injector's labels are "<index>:<name>" too.
        self.faults = [(i, spec) for i, spec in enumerate(specs) if spec.hardware]
        self.max_dipole_am2 = max_dipole_am2
        self.wall_s_per_sim_s = wall_s_per_sim_s
        self.t0_s: float | None = None
        self.windows: list[tuple[int, FaultSpec, float, float]] = []   # (index, spec, start_s, end_s)

    @property
    def active(self) -> bool:
        """Whether any hardware fault is scripted (a board without one skips every check)."""
        return bool(self.faults)

    @property
    def armed(self) -> bool:
        return self.t0_s is not None

    def arm(self, t0_s: float) -> None:
        if self.t0_s is not None:
            return
        self.t0_s = t0_s
        t0_ns = round(t0_s * 1e9)
        for index, spec in self.faults:
            start_ns, end_ns = spec.window_ns(t0_ns, self.wall_s_per_sim_s)
            self.windows.append((index, spec, start_ns / 1e9, math.inf if end_ns is None else end_ns / 1e9))

    def add(self, index: int, spec: FaultSpec) -> None:
        """A hardware fault that arrived while the run runs (live injection, bench/bus/can/live_faults.py),
        `index` its place after the scenario's; windowed at once if armed, else when armed."""
        if not spec.hardware:
            return
        if self.t0_s is not None:
            start_ns, end_ns = spec.window_ns(round(self.t0_s * 1e9), self.wall_s_per_sim_s)
            self.windows.append((index, spec, start_ns / 1e9, math.inf if end_ns is None else end_ns / 1e9))
        self.faults.append((index, spec))

    def _acting(self, now_s: float):
        return [(i, spec) for i, spec, start, end in self.windows if start <= now_s < end]

    def powered(self, now_s: float) -> bool:
        return not any(spec.name == "board_power_loss" for _, spec in self._acting(now_s))

    def axis_faults(self, now_s: float) -> tuple[tuple[str, float], ...]:
        """Per axis, the coil fault acting now as (kind, its value), ("", 0.0) for none."""
        out = [NO_FAULT] * 3
        for _, spec in self._acting(now_s):
            if spec.name == "board_power_loss":
                continue
            value = {"coil_stuck": "value_am2", "coil_gain": "gain"}.get(spec.name)
            out[int(spec.param("axis"))] = (spec.name, float(spec.param(value)) if value else 0.0)
        return tuple(out)

    def state(self, now_s: float) -> tuple:
        """What changes the outputs: compared between two times, it says whether anything did."""
        return (self.powered(now_s), self.axis_faults(now_s)) if self.windows else ()

    def physical_am2(self, setpoint_am2: np.ndarray, now_s: float) -> np.ndarray:
        """The dipole the coils produce for the coil drivers' set-point."""
        if not self.windows:
            return np.asarray(setpoint_am2, float).copy()
        if not self.powered(now_s):
            return np.zeros(3)
        return self._per_axis(setpoint_am2, now_s, sensed=False)

    def sensed_am2(self, setpoint_am2: np.ndarray, now_s: float) -> np.ndarray:
        """The dipole the current sensors measure (current x the coil's nominal gain)."""
        if not self.windows:
            return np.asarray(setpoint_am2, float).copy()
        if not self.powered(now_s):
            return np.zeros(3)
        return self._per_axis(setpoint_am2, now_s, sensed=True)

    def _per_axis(self, setpoint_am2: np.ndarray, now_s: float, sensed: bool) -> np.ndarray:
        out = np.array(setpoint_am2, float)
        for axis, (kind, value) in enumerate(self.axis_faults(now_s)):
            if kind == "coil_open":
                out[axis] = 0.0
            elif kind == "coil_stuck":
                out[axis] = float(np.clip(value, -self.max_dipole_am2, self.max_dipole_am2))
            elif kind == "coil_reversed" and not sensed:
                out[axis] = -out[axis]
            elif kind == "coil_gain" and not sensed:
                out[axis] = value * out[axis]
        return out

    def next_edge_s(self, now_s: float) -> float | None:
        """The next time after now_s at which a hardware fault starts or ends."""
        edges = [t for _, _, start, end in self.windows for t in (start, end) if t > now_s and math.isfinite(t)]
        return min(edges) if edges else None

    def summary(self) -> list[dict]:
        """Each hardware fault's window on the board's clock (ns; end None: to the run's end)."""
        return [{"fault": f"{i}:{spec.name}", "start_ns": round(start * 1e9),
                 "end_ns": None if math.isinf(end) else round(end * 1e9)} for i, spec, start, end in self.windows]
