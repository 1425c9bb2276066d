"""Attitude truth model and attitude sensors for the magnetorquer loop (seed 004).

- Rigid body: quaternion q = ^N q ^B (body to inertial, scalar first [w, x, y, z]) and body rate
  omega in rad/s; Euler's equations J omega_dot = tau - omega x J omega; RK4 with the quaternion
  re-normalised after each step (RK4 does not stay on the unit sphere).
- Geomagnetic field: a tilted dipole co-rotating with the Earth, sampled along a circular orbit.
  Seed 004 uses IGRF along an SGP4 orbit; a dipole has the property the magnetorquer problem
  needs (the field direction sweeps as the spacecraft goes round) at a fraction of the code.
- Sensors: gyro (white noise plus a random-walk bias), magnetometer (body-frame field times a
  scale factor, plus a constant bias and white noise), star tracker (true attitude times a small
  random rotation, larger about the boresight than across it).

Inertial frame: ECI-like, z along the Earth's spin axis. All units SI (T for the field).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable
from functools import cached_property

import numpy as np
from scipy.spatial.transform import Rotation

from bench.gnc import quaternion as qt
from bench.gnc.quaternion import cross3

EARTH_RADIUS_M = 6.3712e6
EARTH_ROTATION_RADPS = 7.2921159e-5
# IGRF-13 (2020) dipole: g10 = -29404.8 nT; |g10, g11, h11| gives B0 ~ 3.0e-5 T and a dipole axis
# ~9.7 deg from the spin axis. Rounded; a dipole is a stand-in for IGRF, not a replacement.
DIPOLE_EQUATORIAL_FIELD_T = 3.0e-5
DIPOLE_TILT_RAD = np.deg2rad(9.7)


# ---- rigid body ---------------------------------------------------------------------------------

def quaternion_rate(q_wxyz: np.ndarray, omega_body_radps: np.ndarray) -> np.ndarray:
    """q_dot = 1/2 q (x) [0, omega] for body-to-inertial q and body-frame rate."""
    w, x, y, z = q_wxyz
    p, q, r = omega_body_radps
    return 0.5 * np.array([
        -x * p - y * q - z * r,
        w * p + y * r - z * q,
        w * q - x * r + z * p,
        w * r + x * q - y * p,
    ])


def euler_rate(omega_body_radps: np.ndarray, torque_body_nm: np.ndarray, inertia_kgm2: np.ndarray,
               inertia_inverse: np.ndarray | None = None) -> np.ndarray:
    rhs = torque_body_nm - cross3(omega_body_radps, inertia_kgm2 @ omega_body_radps)
    return inertia_inverse @ rhs if inertia_inverse is not None else np.linalg.solve(inertia_kgm2, rhs)


def rk4_attitude_step(q_wxyz: np.ndarray, omega_body_radps: np.ndarray, torque_body_nm: np.ndarray,
                      inertia_kgm2: np.ndarray, dt_s: float,
                      inertia_inverse: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One RK4 step of the rigid body with torque held constant over dt; q re-normalised.
    `inertia_inverse`: J^-1 if the caller keeps it (the plant does: inverting costs ~0.1 ms a step)."""
    j_inv = np.linalg.inv(inertia_kgm2) if inertia_inverse is None else inertia_inverse

    def f(q, w):
        return quaternion_rate(q, w), euler_rate(w, torque_body_nm, inertia_kgm2, j_inv)

    k1q, k1w = f(q_wxyz, omega_body_radps)
    k2q, k2w = f(q_wxyz + 0.5 * dt_s * k1q, omega_body_radps + 0.5 * dt_s * k1w)
    k3q, k3w = f(q_wxyz + 0.5 * dt_s * k2q, omega_body_radps + 0.5 * dt_s * k2w)
    k4q, k4w = f(q_wxyz + dt_s * k3q, omega_body_radps + dt_s * k3w)
    q_next = q_wxyz + dt_s / 6.0 * (k1q + 2 * k2q + 2 * k3q + k4q)
    w_next = omega_body_radps + dt_s / 6.0 * (k1w + 2 * k2w + 2 * k3w + k4w)
    return q_next / np.linalg.norm(q_next), w_next


def magnetorquer_torque_nm(dipole_body_am2: np.ndarray, field_body_t: np.ndarray) -> np.ndarray:
    """tau = m x B (seed 004 section 7): no torque along the field, hence the under-actuation."""
    return cross3(dipole_body_am2, field_body_t)


def body_to_inertial(q_wxyz: np.ndarray) -> Rotation:
    return Rotation.from_quat(q_wxyz, scalar_first=True)


# ---- orbit and geomagnetic field ----------------------------------------------------------------

@dataclass(frozen=True)
class CircularOrbit:
    radius_m: float = 6.9e6
    inclination_rad: float = np.deg2rad(51.6)
    raan_rad: float = 0.0
    initial_argument_of_latitude_rad: float = 0.0
    gravitational_parameter_m3ps2: float = 3.986e14

    @property
    def mean_motion_radps(self) -> float:
        return float(np.sqrt(self.gravitational_parameter_m3ps2 / self.radius_m**3))

    @cached_property
    def _inertial_from_orbit_plane(self) -> np.ndarray:
        # Built once: scipy's Rotation costs ~50-300 us per construction, the plant asks every step.
        return Rotation.from_euler("ZX", [self.raan_rad, self.inclination_rad]).as_matrix()

    def position_m(self, time_s: float) -> np.ndarray:
        u = self.initial_argument_of_latitude_rad + self.mean_motion_radps * time_s
        return self._inertial_from_orbit_plane @ (self.radius_m * np.array([np.cos(u), np.sin(u), 0.0]))


@dataclass(frozen=True)
class TiltedDipole:
    equatorial_field_t: float = DIPOLE_EQUATORIAL_FIELD_T
    tilt_rad: float = DIPOLE_TILT_RAD
    initial_longitude_rad: float = np.deg2rad(-72.6)   # of the dipole's northern pole at t = 0

    def dipole_axis(self, time_s: float) -> np.ndarray:
        """Unit dipole moment direction (it points to the southern hemisphere)."""
        lon = self.initial_longitude_rad + EARTH_ROTATION_RADPS * time_s
        north_pole = np.array([np.sin(self.tilt_rad) * np.cos(lon),
                               np.sin(self.tilt_rad) * np.sin(lon),
                               np.cos(self.tilt_rad)])
        return -north_pole

    def field_t(self, position_m: np.ndarray, time_s: float) -> np.ndarray:
        """B = B0 (Re / r)^3 [3 (m . r_hat) r_hat - m], inertial frame, T."""
        r = np.linalg.norm(position_m)
        r_hat = position_m / r
        m = self.dipole_axis(time_s)
        return self.equatorial_field_t * (EARTH_RADIUS_M / r) ** 3 * (3.0 * (m @ r_hat) * r_hat - m)


# ---- sensors ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class AttitudeSensorSpec:
    """True sensor characteristics and rates (the smoother has its own, possibly wrong, beliefs)."""

    gyro_rate_hz: float = 10.0
    gyro_noise_density_radps_per_rthz: float = 1.0e-4
    gyro_bias_random_walk_radps2_per_rthz: float = 1.0e-6
    initial_gyro_bias_std_radps: float = 1.0e-3
    magnetometer_period_s: float = 1.0
    magnetometer_noise_std_t: float = 1.0e-7
    # Hard-iron bias (body frame) and scale factor: measured = scale * B_body + bias + noise.
    magnetometer_bias_t: tuple[float, float, float] = (0.0, 0.0, 0.0)
    magnetometer_scale: float = 1.0
    star_tracker_period_s: float = 10.0
    # A star tracker sees the roll about its boresight (body axis below) through the small
    # angular displacement of stars across the field of view: its error about the boresight is
    # several times its error across it (typically 5 to 10 times); 8 here.
    star_tracker_noise_std_rad: float = 1.0e-4          # across the boresight, per axis
    star_tracker_boresight_noise_std_rad: float = 8.0e-4
    star_tracker_boresight_body: tuple[float, float, float] = (0.0, 0.0, 1.0)
    star_tracker_outages_s: tuple[tuple[float, float], ...] = ()   # (start, end): no fix (Sun or Earth in view)

    def __post_init__(self):
        for name in ("gyro_rate_hz", "magnetometer_period_s", "star_tracker_period_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"AttitudeSensorSpec.{name} must be positive, got {getattr(self, name)}")
        for name in ("magnetometer_period_s", "star_tracker_period_s"):
            ratio = getattr(self, name) * self.gyro_rate_hz
            if abs(ratio - round(ratio)) > 1e-9:
                raise ValueError(f"AttitudeSensorSpec.{name} must be a whole number of gyro samples, "
                                 f"got {getattr(self, name)} s at {self.gyro_rate_hz} Hz")


@dataclass
class AttitudeSample:
    """What the sensors report at one gyro tick (magnetometer and star tracker only on their ticks)."""

    time_s: float
    gyro_radps: np.ndarray
    magnetometer_t: np.ndarray | None = None
    field_inertial_t: np.ndarray | None = None    # the field model's prediction (known on board)
    star_tracker_wxyz: np.ndarray | None = None   # None off its ticks and in an outage
    star_tracker_tick: bool = False               # the star tracker reports (a fix or "no fix")


@dataclass
class AttitudeTruth:
    time_s: float
    q_wxyz: np.ndarray
    omega_body_radps: np.ndarray
    gyro_bias_radps: np.ndarray


@dataclass
class AttitudeSimulation:
    """Torque-free (or torqued) rigid body with the three attitude sensors, stepped at the gyro rate."""

    inertia_kgm2: np.ndarray
    q_wxyz: np.ndarray
    omega_body_radps: np.ndarray
    sensors: AttitudeSensorSpec = field(default_factory=AttitudeSensorSpec)
    orbit: CircularOrbit = field(default_factory=CircularOrbit)
    geomagnetic: TiltedDipole = field(default_factory=TiltedDipole)
    seed: int = 0
    # When set, says at each tick whether the magnetometer samples (the plant's coil-blanking
    # gate); otherwise it samples every magnetometer_period_s.
    magnetometer_due: Callable[[], bool] | None = None

    def __post_init__(self):
        self.rng = np.random.default_rng(self.seed)
        self.inertia_kgm2 = np.asarray(self.inertia_kgm2, dtype=float)
        self.q_wxyz = np.asarray(self.q_wxyz, dtype=float) / np.linalg.norm(self.q_wxyz)
        self.omega_body_radps = np.asarray(self.omega_body_radps, dtype=float)
        self.gyro_bias_radps = self.rng.normal(0.0, self.sensors.initial_gyro_bias_std_radps, 3)
        self.tick = 0
        self._inertia_inverse = np.linalg.inv(self.inertia_kgm2)

    @property
    def dt_s(self) -> float:
        return 1.0 / self.sensors.gyro_rate_hz

    @property
    def time_s(self) -> float:
        return self.tick * self.dt_s

    def truth(self) -> AttitudeTruth:
        return AttitudeTruth(self.time_s, self.q_wxyz.copy(), self.omega_body_radps.copy(), self.gyro_bias_radps.copy())

    def field_body_t(self) -> np.ndarray:
        """The true geomagnetic field in the body frame now (what a magnetorquer acts against)."""
        field_inertial = self.geomagnetic.field_t(self.orbit.position_m(self.time_s), self.time_s)
        return qt.rotation_matrix(self.q_wxyz).T @ field_inertial

    def step(self, torque_body_nm: np.ndarray = np.zeros(3)) -> AttitudeSample:
        """Advance one gyro period; the gyro reports the mean rate over it, the others the end state.

        The gyro measures the average rate over its sample period (an integrating rate gyro), so
        integrating its samples reproduces the attitude change up to the sensor noise.
        """
        dt = self.dt_s
        q_before = self.q_wxyz
        self.q_wxyz, self.omega_body_radps = rk4_attitude_step(
            self.q_wxyz, self.omega_body_radps, np.asarray(torque_body_nm, float), self.inertia_kgm2, dt,
            self._inertia_inverse)
        self.tick += 1
        mean_rate = qt.log(qt.multiply(qt.conjugate(q_before), self.q_wxyz)) / dt
        return self.measure(mean_rate)

    def measure(self, mean_rate_radps: np.ndarray) -> AttitudeSample:
        """The sensors at the current tick, the gyro reading `mean_rate_radps` (at tick 0, before
        any step, the closed loop's first sample reads the initial rate)."""
        spec, dt = self.sensors, self.dt_s
        mean_rate = np.asarray(mean_rate_radps, dtype=float)
        # Bias is constant over the sample and then walks (what the preintegration assumes).
        gyro = mean_rate + self.gyro_bias_radps + self.rng.normal(0.0, spec.gyro_noise_density_radps_per_rthz / np.sqrt(dt), 3)
        self.gyro_bias_radps = self.gyro_bias_radps + self.rng.normal(
            0.0, spec.gyro_bias_random_walk_radps2_per_rthz * np.sqrt(dt), 3)
        sample = AttitudeSample(self.time_s, gyro)
        due = self._on_tick(spec.magnetometer_period_s) if self.magnetometer_due is None else self.magnetometer_due()
        if due:
            field_inertial = self.geomagnetic.field_t(self.orbit.position_m(self.time_s), self.time_s)
            sample.field_inertial_t = field_inertial
            field_body = qt.rotation_matrix(self.q_wxyz).T @ field_inertial
            sample.magnetometer_t = (spec.magnetometer_scale * field_body + np.asarray(spec.magnetometer_bias_t)
                                     + self.rng.normal(0.0, spec.magnetometer_noise_std_t, 3))
        if self._on_tick(spec.star_tracker_period_s):
            sample.star_tracker_tick = True
            # e = sigma z + (sigma_b - sigma)(a . z) a: covariance sigma^2 across a, sigma_b^2 along.
            axis = np.asarray(spec.star_tracker_boresight_body, dtype=float)
            axis = axis / np.linalg.norm(axis)
            z = self.rng.normal(0.0, 1.0, 3)
            rotvec = spec.star_tracker_noise_std_rad * z + (
                spec.star_tracker_boresight_noise_std_rad - spec.star_tracker_noise_std_rad) * (axis @ z) * axis
            if not any(start <= self.time_s < end for start, end in spec.star_tracker_outages_s):
                measured = qt.multiply(self.q_wxyz, qt.exp(rotvec))
                sample.star_tracker_wxyz = measured if measured[0] >= 0 else -measured
        return sample

    def _on_tick(self, period_s: float) -> bool:
        return self.tick % int(round(period_s * self.sensors.gyro_rate_hz)) == 0
