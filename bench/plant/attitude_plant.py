"""The attitude plant of the magnetorquer loop: rigid body, environment and sensors, built from a
scenario's [attitude] section, stepped at the gyro rate.

Per step k: `sense()` gives the sensors at t_k; the caller decides the applied dipole; `apply(m)`
integrates [t_k, t_k+1] with the torque held over the step (the board holds its dipole; the field
and the gravity gradient change by ~1e-3 relative in 0.1 s):

    tau = m x B_body + 3 mu / r^3 (r_b x J r_b) + m_res x B_body

Every quantity a report or a test needs is logged per step (`trajectory()`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.bus.spill import SpilledRows
from bench.gnc import quaternion as qt
from bench.plant.attitude import (
    AttitudeSample, AttitudeSensorSpec, AttitudeSimulation, CircularOrbit, TiltedDipole,
    magnetorquer_torque_nm, EARTH_RADIUS_M,
)
from bench.plant.coils import CoilModel
from bench.config.plant import AttitudePlantConfig
from bench.gnc.environment import (
    EARTH_MU_M3PS2, IgrfAlongOrbit, Sgp4Orbit, gravity_gradient_torque_nm, residual_dipole_torque_nm,
)


def sensor_spec(config: AttitudePlantConfig) -> AttitudeSensorSpec:
    s = config.sensors
    return AttitudeSensorSpec(
        gyro_rate_hz=s.gyro_rate_hz,
        gyro_noise_density_radps_per_rthz=s.gyro_noise_density_radps_per_rthz,
        gyro_bias_random_walk_radps2_per_rthz=s.gyro_bias_random_walk_radps2_per_rthz,
        initial_gyro_bias_std_radps=s.initial_gyro_bias_std_radps,
        magnetometer_period_s=s.magnetometer_period_s,
        magnetometer_noise_std_t=s.magnetometer_noise_std_t,
        star_tracker_period_s=s.star_tracker_period_s,
        star_tracker_noise_std_rad=s.star_tracker_noise_std_rad,
        star_tracker_boresight_noise_std_rad=s.star_tracker_noise_std_rad * s.star_tracker_boresight_noise_factor,
        star_tracker_outages_s=tuple((float(a), float(b)) for a, b in s.star_tracker_outages_s),
        magnetometer_bias_t=tuple(s.magnetometer_bias_t),
    )


def build_orbit(config: AttitudePlantConfig):
    o = config.orbit
    if o.model == "sgp4":
        return Sgp4Orbit.from_tle(*o.tle, config.epoch())
    return CircularOrbit(radius_m=EARTH_RADIUS_M + o.altitude_m, inclination_rad=np.deg2rad(o.inclination_deg),
                         raan_rad=np.deg2rad(o.raan_deg),
                         initial_argument_of_latitude_rad=np.deg2rad(o.initial_argument_of_latitude_deg),
                         gravitational_parameter_m3ps2=EARTH_MU_M3PS2)


def build_field(config: AttitudePlantConfig, orbit, duration_s: float):
    if config.field.model == "dipole":
        return TiltedDipole()
    epoch = orbit.epoch if isinstance(orbit, Sgp4Orbit) else config.epoch()
    return IgrfAlongOrbit.tabulate(orbit, epoch, duration_s + 1.0, config.field.grid_s)


class LastTimeOrbit:
    """The orbit with its last position kept (asked up to four times a step at the same t_k)."""

    def __init__(self, model):
        self.model = model
        self._time_s: float | None = None
        self._position_m: np.ndarray | None = None

    def position_m(self, time_s: float) -> np.ndarray:
        if time_s != self._time_s:
            self._position_m, self._time_s = self.model.position_m(time_s), time_s
        return self._position_m.copy()

    def __getattr__(self, name):
        return getattr(self.model, name)


class LastTimeField:
    """The field model with its last answer kept: the plant asks for the field at t_k up to three
    times a step (sensors, torque, truth); the spline costs ~40 us a call. Same values, bit for bit.
    Only for a field along the plant's own orbit (the position is a function of the time)."""

    def __init__(self, model):
        self.model = model
        self._time_s: float | None = None
        self._field_t: np.ndarray | None = None

    def field_t(self, position_m: np.ndarray, time_s: float) -> np.ndarray:
        if time_s != self._time_s:
            self._field_t, self._time_s = self.model.field_t(position_m, time_s), time_s
        return self._field_t.copy()

    def __getattr__(self, name):
        return getattr(self.model, name)


@dataclass
class StepLog:
    """Per integrated step, one row per column, on disk as it comes (bench/bus/spill.py): a plant
    of any run length keeps a flat memory (issue 44); `AttitudePlant.trajectory()` reads them back."""
    time_s: SpilledRows
    q_wxyz: SpilledRows
    omega_radps: SpilledRows
    field_body_t: SpilledRows
    field_inertial_t: SpilledRows
    dipole_applied_am2: SpilledRows
    torque_control_nm: SpilledRows
    torque_disturbance_nm: SpilledRows

    @classmethod
    def empty(cls) -> "StepLog":
        widths = {"time_s": (), "q_wxyz": (4,)}
        return cls(**{name: SpilledRows(widths.get(name, (3,))) for name in cls.__dataclass_fields__})


class AttitudePlant:
    def __init__(self, config: AttitudePlantConfig, n_steps: int, seed: int, magnetometer_due=None):
        """`magnetometer_due`: called at each tick, says whether the magnetometer samples (the
        coil-blanking gate of the plant process); None: every magnetometer_period_s."""
        self.config = config
        self.n_steps = n_steps
        orbit = build_orbit(config)
        spec = sensor_spec(config)
        self.field = LastTimeField(build_field(config, orbit, n_steps / spec.gyro_rate_hz))
        self.orbit = LastTimeOrbit(orbit)
        self.sim = AttitudeSimulation(config.inertia_matrix(), np.asarray(config.initial_q_wxyz, float),
                                      np.deg2rad(config.initial_rate_dps), spec, self.orbit, self.field, seed=seed,
                                      magnetometer_due=magnetometer_due)
        self.residual_dipole_am2 = np.asarray(config.disturbances.residual_dipole_am2, float)
        self.coils = CoilModel(config.coils)     # [attitude.coils]: what the coils make of the applied dipole
        self.log = StepLog.empty()
        self._sample = self.sim.measure(self.sim.omega_body_radps)

    @property
    def step_index(self) -> int:
        return self.sim.tick

    @property
    def time_s(self) -> float:
        return self.sim.time_s

    @property
    def dt_s(self) -> float:
        return self.sim.dt_s

    def sense(self) -> AttitudeSample:
        """The sensors at t_k: the gyro every tick; the magnetometer (with the on-board field
        model's inertial prediction beside it) and the star tracker only on their own ticks."""
        return self._sample

    def field_inertial_t(self) -> np.ndarray:
        return self.field.field_t(self.orbit.position_m(self.time_s), self.time_s)

    def disturbance_torque_nm(self, field_body_t: np.ndarray) -> np.ndarray:
        torque = residual_dipole_torque_nm(self.residual_dipole_am2, field_body_t)
        if self.config.disturbances.gravity_gradient:
            position_body = qt.rotation_matrix(self.sim.q_wxyz).T @ self.orbit.position_m(self.time_s)
            torque = torque + gravity_gradient_torque_nm(position_body, self.sim.inertia_kgm2)
        return torque

    def apply(self, dipole_applied_am2: np.ndarray) -> None:
        """Integrate one step with the board's applied dipole held over it."""
        dipole = np.asarray(dipole_applied_am2, dtype=float)
        field_inertial = self.field_inertial_t()
        field_body = qt.rotation_matrix(self.sim.q_wxyz).T @ field_inertial
        control = magnetorquer_torque_nm(self.coils.dipole_am2(self.time_s, dipole), field_body)
        disturbance = self.disturbance_torque_nm(field_body)
        log = self.log
        log.time_s.append(self.time_s)
        log.q_wxyz.append(self.sim.q_wxyz.copy())
        log.omega_radps.append(self.sim.omega_body_radps.copy())
        log.field_body_t.append(field_body)
        log.field_inertial_t.append(field_inertial)
        log.dipole_applied_am2.append(dipole)
        log.torque_control_nm.append(control)
        log.torque_disturbance_nm.append(disturbance)
        self._sample = self.sim.step(control + disturbance)

    def trajectory(self) -> dict[str, np.ndarray]:
        """Per integrated step: the state at its start and what acted over it."""
        return {f"att_{name}": getattr(self.log, name).array() for name in StepLog.__dataclass_fields__}
