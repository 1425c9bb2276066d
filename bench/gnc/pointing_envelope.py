"""FDIR at the system level: the pointing error outside its envelope.

The actuator monitor (bench.gnc.actuator_monitor) judges each coil from the dynamics, and needs the
coils to work hard enough to tell a fault from the gyro's noise. A hold flown at a DAC step of
command can lose its attitude to a fault the coils' torques cannot show: a reversed coil carrying
the calibrated residual-dipole compensation doubles the residual dipole, a constant torque that the
monitor reads as a residual it does not know. What the mission sees is the pointing error growing.
Flight FDIR watches that too (the attitude-error limit that sends a spacecraft to safe mode): this
monitor raises one event when the law's pointing error has stayed above `limit_rad` for
`persistence_s` of simulated time, and is armed again once the error is back below the limit. It
names no coil: it says the mission is being lost, whatever the cause.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

FAULT_CLASS = "pointing"


@dataclass(frozen=True)
class EnvelopeEvent:
    """The pointing error above its limit since `alarm_s`, for `window_s`, at `time_s` (simulated)."""
    time_s: float
    alarm_s: float
    error_deg: float
    limit_deg: float
    fault_class: str = FAULT_CLASS
    axis_name: str = "-"          # no coil: the attitude as a whole

    @property
    def kind(self) -> str:
        return f"fdir_{self.fault_class}"

    @property
    def window_s(self) -> float:
        return self.time_s - self.alarm_s

    def describe(self) -> str:
        return (f"pointing error {self.error_deg:.2f} deg above the {self.limit_deg:g} deg envelope since "
                f"{self.alarm_s:.3f} s, at {self.time_s:.3f} s")


@dataclass
class PointingEnvelope:
    limit_rad: float
    persistence_s: float
    events: list[EnvelopeEvent] = field(default_factory=list)
    peak_error_rad: float = 0.0
    _above_since_s: float | None = None
    _raised: bool = False

    def step(self, time_s: float, error_rad: float | None) -> list[EnvelopeEvent]:
        """One cycle's error (None or non-finite: the law gave none; the envelope waits)."""
        if error_rad is None or not np.isfinite(error_rad):
            return []
        self.peak_error_rad = max(self.peak_error_rad, float(error_rad))
        if error_rad <= self.limit_rad:
            self._above_since_s, self._raised = None, False     # back inside: armed again
            return []
        if self._above_since_s is None:
            self._above_since_s = time_s
        if self._raised or time_s - self._above_since_s < self.persistence_s:
            return []
        self._raised = True
        event = EnvelopeEvent(time_s, self._above_since_s, float(np.rad2deg(error_rad)), float(np.rad2deg(self.limit_rad)))
        self.events.append(event)
        return [event]

    def summary(self) -> dict:
        return {"limit_deg": float(np.rad2deg(self.limit_rad)), "persistence_s": self.persistence_s,
                "peak_error_deg": float(np.rad2deg(self.peak_error_rad)),
                "events": [{"time_s": e.time_s, "alarm_s": e.alarm_s, "error_deg": e.error_deg} for e in self.events]}
