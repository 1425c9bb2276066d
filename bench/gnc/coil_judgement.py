"""How the FDIR actuator monitor reads one coil's single-fault fit (IsolationFit, made by
ActuatorMonitor.isolation_fits, bench/gnc/actuator_monitor.py): its distance to the nominal box
(detection) and the fault class it points to, with the coil as read for that class (classification).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class IsolationFit:
    """One coil's single-fault fit (ActuatorMonitor.isolation_fits): (g, s) absolute, from `onset_s`."""
    coil: int
    theta: np.ndarray        # (gain, offset)
    covariance: np.ndarray   # 2 x 2
    factor: float            # variance factor (>= 1)
    onset: int               # record index
    onset_s: float
    rss: float               # whitened residual sum of squares
    by_onset: dict = field(default_factory=dict)   # onset index -> (theta, covariance), the best's factor
    # The fit with the offset held at the belief (the gain alone differs), at its own best onset.
    gain_only: float = 1.0
    gain_only_std: float = float("inf")
    gain_only_onset_s: float = 0.0
    gain_only_rss: float = float("inf")


@dataclass(frozen=True)
class CoilReading:
    """What the monitor reads of a faulty coil, as classified (offset 0 when read on s = 0)."""
    gain: float
    gain_std: float
    offset_am2: float
    offset_std_am2: float
    onset_s: float


def box_distance2(x: np.ndarray, covariance: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> float:
    """Smallest Mahalanobis distance squared from x to the box [lower, upper] (2-D, exact)."""
    if np.all(x >= lower) and np.all(x <= upper):
        return 0.0
    w = np.linalg.inv(covariance)
    best = np.inf
    for fixed in (0, 1):
        free = 1 - fixed
        for edge in (lower[fixed], upper[fixed]):
            a = x[fixed] - edge
            # the free coordinate minimising the quadratic with this one fixed, kept on the edge
            y = np.clip(x[free] + w[fixed, free] * a / w[free, free], lower[free], upper[free])
            d = np.empty(2)
            d[fixed], d[free] = a, x[free] - y
            best = min(best, float(d @ w @ d))
    return best


def classify(fit: IsolationFit, consistency: float, max_gain_std: float) -> tuple[str | None, CoilReading]:
    """The fault class a coil's single-fault fit points to (None while the data cannot tell), and
    the coil as read for it.

    An offset is believed only when the data demand it: unless holding s at 0 costs the fit at
    least `consistency` (chi-square units), the coil is read on s = 0 (the gain-only fit at its own
    best onset: far sharper when the coil was commanded at a near-constant dipole, which makes gain
    and offset nearly collinear and the onset loose) and the class is "open" or "reversed" when 0
    or -1 is consistent with the gain (d^2 below `consistency`), else "gain". When s = 0 is
    rejected, the coil holds a dipole of its own: "stuck" when g = 0 is consistent, else "gain" (a
    gain and an offset; the event gives both). A class needs the gain it is read on known to
    max_gain_std."""
    if (fit.gain_only_rss - fit.rss) / fit.factor < consistency:
        g, sigma = fit.gain_only, fit.gain_only_std
        reading = CoilReading(g, sigma, 0.0, 0.0, fit.gain_only_onset_s)
        if sigma > max_gain_std:
            return None, reading
        to_open, to_reversed = (g / sigma) ** 2, ((g + 1.0) / sigma) ** 2
        if min(to_open, to_reversed) < consistency:
            return ("open" if to_open <= to_reversed else "reversed"), reading
        return "gain", reading
    (g, offset), p = fit.theta, fit.covariance
    reading = CoilReading(float(g), float(np.sqrt(p[0, 0])), float(offset), float(np.sqrt(p[1, 1])), fit.onset_s)
    if reading.gain_std > max_gain_std:
        return None, reading
    return ("stuck" if g**2 / p[0, 0] < consistency else "gain"), reading

