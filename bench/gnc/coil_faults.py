"""The FDIR actuator monitor's terms (bench/gnc/actuator_monitor.py): how it decides
(MonitorSettings), what the flight side believes of the board and of each coil (OnboardActuatorModel,
CoilBelief), the fault classes and the model each leaves a coil with, and what the monitor reports
(FdirEvent; CoilEstimate at each evaluation).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Literal

import numpy as np

AXES = ("x", "y", "z")
CLASSES = ("open", "reversed", "gain", "stuck")
EARTH_MU_M3PS2 = 3.986004418e14
# The identified model each class leaves the coil with (gain, offset); None: as estimated.
CLASS_MODELS: dict[str, tuple[float | None, float | None]] = {
    "open": (0.0, 0.0), "reversed": (-1.0, 0.0), "gain": (None, 0.0), "stuck": (0.0, None)}


@dataclass(frozen=True)
class MonitorSettings:
    """How the monitor decides (scenario [attitude_control.fdir]; docs/fdir.md for the figures)."""
    window_s: float = 60.0               # least-squares window
    min_window_s: float = 20.0           # no judgement before this much contiguous data
    evaluate_every_s: float = 1.0
    gain_tolerance: float = 0.3          # |g - 1| within this is a healthy coil
    offset_tolerance_am2: float = 0.01   # |s| within this is a healthy coil
    threshold: float = 40.0              # d^2 to the nominal box above this: a fault
    persistence: int = 3                 # evaluations in a row with the same class
    onset_step_s: float = 0.0            # onsets tried within the window (0: every step)
    detection_onsets: int = 4            # onsets detected on (the window's start and evenly after)
    isolation_margin: float = 13.8       # residual (chi-square) by which the faulty coil's hypothesis must win
    max_gain_std: float = 0.08           # excitation: a coil is judged only with its gain this well known
    class_consistency: float = 13.8      # chi-square(2) at 0.999: (0, 0) or (-1, 0) consistent
    prior_gain_std: float = 10.0         # weak priors: an unexcited parameter keeps a finite, wide variance
    prior_offset_std_am2: float = 1.0
    prior_residual_std_am2: float = 0.01  # the believed residual dipole's error (a nuisance the fit estimates)


@dataclass(frozen=True)
class OnboardActuatorModel:
    """What the flight side believes, for the monitor."""
    inertia_kgm2: np.ndarray
    step_s: float
    gyro_noise_std_radps: float                    # per rate sample (noise density / sqrt(step))
    rate_sample: Literal["mean", "instant"] = "mean"
    residual_dipole_am2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    dipole_limit_am2: float = 0.2                  # the board's per-axis saturation
    dipole_resolution_am2: float | None = 1e-3     # the board's DAC step (None: none)
    position_m: Callable[[float], np.ndarray] | None = None   # believed orbit; None: no gravity gradient
    # The board's setting for a command, if the flight side has its model (the command frame's
    # scaling, then the DAC step and the limit: bench.controller.fdir); None: the two numbers above.
    board_model: Callable[[np.ndarray], np.ndarray] | None = None
    mu_m3ps2: float = EARTH_MU_M3PS2


@dataclass(frozen=True)
class FdirEvent:
    """A coil fault the monitor detected, at `time_s` (the run's simulated time)."""
    time_s: float
    axis: int
    fault_class: str
    gain: float
    gain_std: float
    offset_am2: float
    offset_std_am2: float
    statistic: float          # d^2 to the nominal box
    window_s: float           # the evidence: data over this long before time_s
    alarm_s: float            # when d^2 first crossed the threshold (the class may take longer: excitation)
    onset_s: float            # the onset the isolating fit found (maximum likelihood)

    @property
    def kind(self) -> str:
        return f"fdir_{self.fault_class}"

    @property
    def axis_name(self) -> str:
        return AXES[self.axis]

    def describe(self) -> str:
        return (f"coil {self.axis_name}: {self.fault_class} at {self.time_s:.3f} s, alarm since {self.alarm_s:.3f} s, "
                f"onset fitted at {self.onset_s:.3f} s (gain {self.gain:.3f} "
                f"+- {self.gain_std:.3f}, offset {self.offset_am2:.2e} +- {self.offset_std_am2:.1e} A m^2, "
                f"d2 {self.statistic:.1f}, over {self.window_s:.0f} s)")

    def to_dict(self) -> dict:
        return {"monitor": "FDIR", "kind": self.kind, "axis": self.axis_name, "class": self.fault_class,
                "time_s": self.time_s, "gain": self.gain, "gain_std": self.gain_std, "offset_am2": self.offset_am2,
                "offset_std_am2": self.offset_std_am2, "statistic": self.statistic, "window_s": self.window_s,
                "alarm_s": self.alarm_s, "onset_s": self.onset_s}


@dataclass
class CoilBelief:
    """The model the flight side holds of one coil: healthy (1, 0) until the monitor latches a fault."""
    gain: float = 1.0
    offset_am2: float = 0.0
    fault: str | None = None
    detected_s: float | None = None
    onset_s: float = 0.0          # the fault's onset as estimated: the belief holds from then on

    @property
    def usable(self) -> bool:
        """Whether commanding this coil moves its torque (open and stuck coils: no)."""
        return self.fault is None or (self.fault in ("reversed", "gain") and abs(self.gain) >= 0.2)


@dataclass(frozen=True)
class CoilEstimate:
    """A coil at the latest evaluation (`ActuatorMonitor.last`), as detection saw it."""
    gain: float
    offset_am2: float
    covariance: np.ndarray       # 2 x 2, of (gain, offset)
    observable: bool
    statistic: float             # d^2 to the nominal box (0 inside; NaN when not judged)
