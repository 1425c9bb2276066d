"""The space environment of the attitude plant (seed 004 section 7): orbit, geomagnetic field,
and the disturbance torques the environment puts on the body.

- Orbit: SGP4 (the `sgp4` package, Vallado's code) on a two-line element set, positions in its
  TEME frame, which this plant takes as inertial (TEME precesses by ~50"/year: nothing over a run);
  or a circular orbit (`bench.plant.attitude.CircularOrbit`) as the fast option.
- Field: IGRF (`ppigrf`, IGRF-14 coefficients) along the orbit. One `ppigrf` call costs ~25-60 ms
  whatever the number of points (measured here: 54 ms for 1 point, 64 ms for 100), so the field is
  evaluated once, vectorised, on a time grid over the whole run and interpolated by a cubic spline
  (`IgrfAlongOrbit`). The tilted dipole (`bench.plant.attitude.TiltedDipole`) is the fast option.
- Torques: gravity gradient 3 mu / r^3 (r_b x J r_b) and a residual-dipole torque m_res x B.

Frames: inertial = TEME (z along the Earth's spin axis), Earth-fixed via the Greenwich mean
sidereal angle (sgp4's `gstime`; polar motion and UT1-UTC ignored: metres at the field's scale).
"""
from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from typing import Protocol

import numpy as np
from scipy.interpolate import CubicSpline
from sgp4.api import SGP4_ERRORS, WGS72, Satrec, jday
from sgp4.propagation import gstime

from bench.gnc.quaternion import cross3

EARTH_MU_M3PS2 = 3.986004418e14
IGRF_REFERENCE_RADIUS_KM = 6371.2   # IGRF's reference radius a (Alken et al. 2021)


class Orbit(Protocol):
    def position_m(self, time_s: float) -> np.ndarray:
        """Inertial position at `time_s` after the run's epoch, m."""


class GeomagneticField(Protocol):
    def field_t(self, position_m: np.ndarray, time_s: float) -> np.ndarray:
        """Inertial field vector at `position_m` and `time_s`, T."""


# ---- time ---------------------------------------------------------------------------------------

def julian_date(epoch: datetime, time_s: float = 0.0) -> tuple[float, float]:
    """(whole, fraction) Julian date of epoch + time_s, split as sgp4 wants it for precision."""
    t = epoch + timedelta(seconds=float(time_s))
    jd, fr = jday(t.year, t.month, t.day, t.hour, t.minute, t.second + t.microsecond * 1e-6)
    return jd, fr


def greenwich_angle_rad(epoch: datetime, time_s: float) -> float:
    jd, fr = julian_date(epoch, time_s)
    return float(gstime(jd + fr))


def inertial_from_earth_fixed(angle_rad: float) -> np.ndarray:
    """Rotation taking Earth-fixed vectors to inertial ones (about z by the sidereal angle)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# ---- orbit --------------------------------------------------------------------------------------

class TleError(ValueError):
    """A two-line element set that does not parse or does not propagate."""


def tle_checksum(line: str) -> str:
    """Column 69 of a TLE line: the digits of columns 1-68 summed, each '-' counting 1, modulo 10.
    sgp4's parser does not check it, and reads some corrupted fields silently (a letter in the
    inclination parses)."""
    return str(sum(int(c) if c.isdigit() else (1 if c == "-" else 0) for c in line[:68]) % 10)


@dataclass
class Sgp4Orbit:
    """SGP4 on a TLE; time counts from `epoch` (the run's start), not from the TLE's own epoch."""

    satellite: Satrec
    epoch: datetime

    @classmethod
    def from_tle(cls, line1: str, line2: str, epoch: datetime | None = None) -> "Sgp4Orbit":
        """The run starts at `epoch`, default the TLE's epoch. Raises TleError naming the problem."""
        line1, line2 = line1.strip(), line2.strip()
        if not (line1.startswith("1 ") and line2.startswith("2 ")) or len(line1) < 69 or len(line2) < 69:
            raise TleError("expects two 69-character lines starting '1 ' and '2 '")
        for number, line in ((1, line1), (2, line2)):
            if tle_checksum(line) != line[68]:
                raise TleError(f"line {number} checksum: column 69 is {line[68]!r}, the line sums to {tle_checksum(line)}")
        try:
            satellite = Satrec.twoline2rv(line1, line2, WGS72)
        except Exception as exc:      # sgp4 raises ValueError or IndexError on malformed fields
            raise TleError(f"does not parse: {exc}") from None
        if satellite.error != 0:
            raise TleError(f"SGP4 initialisation failed: {SGP4_ERRORS.get(satellite.error, satellite.error)}")
        tle_epoch = datetime(2000, 1, 1, 12, tzinfo=timezone.utc) + timedelta(
            days=satellite.jdsatepoch + satellite.jdsatepochF - 2451545.0)
        orbit = cls(satellite, epoch or tle_epoch)
        orbit.position_m(0.0)     # a TLE that decays at once is refused now, not mid-run
        return orbit

    def position_m(self, time_s: float) -> np.ndarray:
        jd, fr = julian_date(self.epoch, time_s)
        error, position_km, _ = self.satellite.sgp4(jd, fr)
        if error != 0:
            raise TleError(f"SGP4 failed at t = {time_s} s: {SGP4_ERRORS.get(error, error)}")
        return np.asarray(position_km) * 1e3

    def positions_m(self, times_s: np.ndarray) -> np.ndarray:
        return np.array([self.position_m(t) for t in times_s])


# ---- field --------------------------------------------------------------------------------------

def igrf_field_inertial_t(positions_m: np.ndarray, times_s: np.ndarray, epoch: datetime) -> np.ndarray:
    """IGRF at inertial positions (N, 3) and times (N,), inertial frame, T; one vectorised call.

    ppigrf takes geocentric spherical coordinates (r km, colatitude, east longitude in degrees)
    and returns (B_r, B_theta, B_phi) in nT; the date is the run's epoch (the secular variation
    over a run of hours is ~0.01 % and is ignored).
    """
    import ppigrf   # imported here: loading the coefficient file costs time nobody else should pay

    positions_m = np.atleast_2d(positions_m)
    angles = np.array([greenwich_angle_rad(epoch, t) for t in np.atleast_1d(times_s)])
    rotations = np.array([inertial_from_earth_fixed(a) for a in angles])          # N x 3 x 3
    earth_fixed = np.einsum("nji,nj->ni", rotations, positions_m)                  # R^T r
    r_m = np.linalg.norm(earth_fixed, axis=1)
    colat = np.arccos(np.clip(earth_fixed[:, 2] / r_m, -1.0, 1.0))
    lon = np.arctan2(earth_fixed[:, 1], earth_fixed[:, 0])
    br, btheta, bphi = (np.asarray(b, float).reshape(-1) for b in ppigrf.igrf_gc(
        r_m / 1e3, np.rad2deg(colat), np.rad2deg(lon), epoch.replace(tzinfo=None)))
    # Spherical unit vectors in the Earth-fixed frame.
    st, ct, sp, cp = np.sin(colat), np.cos(colat), np.sin(lon), np.cos(lon)
    e_r = np.stack([st * cp, st * sp, ct], axis=1)
    e_theta = np.stack([ct * cp, ct * sp, -st], axis=1)
    e_phi = np.stack([-sp, cp, np.zeros_like(sp)], axis=1)
    field_fixed_t = (br[:, None] * e_r + btheta[:, None] * e_theta + bphi[:, None] * e_phi) * 1e-9
    return np.einsum("nij,nj->ni", rotations, field_fixed_t)


@dataclass
class IgrfAlongOrbit:
    """IGRF tabulated along one orbit on a time grid and splined; `field_t` ignores its position
    argument (the orbit is fixed), which is what makes it cheap."""

    times_s: np.ndarray
    field_table_t: np.ndarray
    _spline: CubicSpline | None = None

    @classmethod
    def tabulate(cls, orbit: Orbit, epoch: datetime, duration_s: float, grid_s: float = 10.0) -> "IgrfAlongOrbit":
        # 10 s of LEO is ~75 km, 0.6 deg of orbit: the cubic spline's error against IGRF at the
        # grid midpoints is below 1e-5 relative (tests/test_attitude_environment.py).
        n = int(np.ceil(max(duration_s, grid_s) / grid_s)) + 4
        times_s = np.arange(-1, n) * grid_s
        positions = np.array([orbit.position_m(t) for t in times_s])
        table = igrf_field_inertial_t(positions, times_s, epoch)
        return cls(times_s, table, CubicSpline(times_s, table, axis=0))

    def field_t(self, position_m: np.ndarray, time_s: float) -> np.ndarray:
        if not self.times_s[0] <= time_s <= self.times_s[-1]:
            raise ValueError(f"time {time_s} s is outside the tabulated field [{self.times_s[0]}, {self.times_s[-1]}] s")
        return np.asarray(self._spline(time_s), dtype=float)


# ---- disturbance torques ------------------------------------------------------------------------

def gravity_gradient_torque_nm(position_body_m: np.ndarray, inertia_kgm2: np.ndarray,
                               mu_m3ps2: float = EARTH_MU_M3PS2) -> np.ndarray:
    """tau = 3 mu / r^3 (r_hat x J r_hat), r_hat the unit position in body axes (Wie, eq. 6.20)."""
    r = float(np.linalg.norm(position_body_m))
    r_hat = position_body_m / r
    return 3.0 * mu_m3ps2 / r**3 * cross3(r_hat, inertia_kgm2 @ r_hat)


def residual_dipole_torque_nm(residual_dipole_am2: np.ndarray, field_body_t: np.ndarray) -> np.ndarray:
    """A spacecraft's own magnetic moment (harness currents, magnetised parts) in the field."""
    return cross3(residual_dipole_am2, field_body_t)
