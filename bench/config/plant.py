"""Scenario sections [plant] (translational: dynamics, where the chaser starts, the sensors) and
[attitude] (the attitude loop's spacecraft, orbit, field, disturbances and sensors).

[attitude] is the truth the plant simulates; what the flight side believes (its inertia, its law) is in
[attitude_control], and the smoother's noise beliefs in [estimator.attitude].

Defaults are a 1U CubeSat (1.3 kg, J ~ 2e-3 kg m^2) with 0.2 A m^2 coils (the [can.board] limit):
in a ~3e-5 T field that is up to 6e-6 N m, ~3e-3 rad/s^2, so a detumble from 8 deg/s or a
large slew takes minutes, a fraction of a 95-minute orbit, which keeps closed-loop runs short.

Every number has a documented range (docs/run_safety.md): finite, and bounded so that no value a
file can hold makes the plant allocate without limit or integrate nonsense.
"""
from __future__ import annotations

from datetime import datetime, timezone
from typing import Annotated, Literal

import msgspec
import numpy as np

from bench.data import load_reference

MODEL = load_reference()["model"]     # the defaults below are the reference's (seed 003)
NonNegative = Annotated[float, msgspec.Meta(ge=0, le=1e9)]
# 1e9 m is 2.5 times the Moon's distance: no relative-motion scenario starts farther out.
StateValue = Annotated[float, msgspec.Meta(ge=-1e9, le=1e9)]
State6 = Annotated[list[StateValue], msgspec.Meta(min_length=6, max_length=6)]


class RelativePositionSensorConfig(msgspec.Struct, forbid_unknown_fields=True):
    noise_std_m: NonNegative = 10.0


class RangeBearingSensorConfig(msgspec.Struct, forbid_unknown_fields=True):
    # A radar- or camera-like sensor: range, azimuth atan2(y, x) and elevation asin(z / r) of the
    # chaser in the target's LVLH frame, each with white Gaussian noise.
    range_noise_std_m: NonNegative = 10.0
    bearing_noise_std_rad: NonNegative = 1.0e-4
    # A measured range at or below this is no fix (a sensor's minimum range; 0: only a range that
    # noise took to zero or below, which a range sensor cannot report).
    min_range_m: NonNegative = 0.0


class CommandAcceptanceConfig(msgspec.Struct, forbid_unknown_fields=True):
    """[plant.command_acceptance]: what the output stage does with a refused command
    (bench/plant/acceptance.py). The envelope is the reference's u_max per axis."""

    # "hold": keep applying the last accepted command; "zero": apply no thrust.
    on_reject: Literal["hold", "zero"] = "hold"


class DivergenceConfig(msgspec.Struct, forbid_unknown_fields=True):
    """[plant.divergence]: a state beyond these (or non-finite) ends the run (exit code 3)."""

    # 1e8 m (100 000 km) and 1e4 m/s: a hundred times the seed's y_max and far beyond any
    # relative velocity in the seeds; only a broken integration or command gets there.
    max_abs_position_m: Annotated[float, msgspec.Meta(gt=0, le=1e12)] = 1.0e8
    max_abs_velocity_mps: Annotated[float, msgspec.Meta(gt=0, le=1e8)] = 1.0e4


class PlantConfig(msgspec.Struct, forbid_unknown_fields=True):
    # "cwh": linear CWH, exact discretisation; "nonlinear": two-body chaser and target (seed 001).
    dynamics: Literal["cwh", "nonlinear"] = "cwh"
    # A name from the reference (A, B, C) or an explicit state in m and m/s.
    initial_condition: Annotated[str, msgspec.Meta(max_length=32)] = "A"
    initial_state_m_mps: State6 | None = None
    # Lower bounds too: 5e-324 kg made B = dt/m infinite. 1 g is a chip satellite; mu = 1 m^3/s^2
    # a small asteroid; 1 m and 1 ms are the least that are still a radius and a step. What the
    # mean motion makes of a step (n dt) is bounded in bench.scenario.
    mass_kg: Annotated[float, msgspec.Meta(ge=1e-3, le=1e9)] = MODEL["mass_kg"]
    gravitational_parameter_m3ps2: Annotated[float, msgspec.Meta(ge=1.0, le=1e21)] = MODEL["gravitational_parameter"]
    target_radius_m: Annotated[float, msgspec.Meta(ge=1.0, le=1e12)] = MODEL["target_radius_m"]
    time_step_s: Annotated[float, msgspec.Meta(ge=1e-3, le=86_400)] = MODEL["time_step_s"]
    relpos_sensor: RelativePositionSensorConfig = msgspec.field(default_factory=RelativePositionSensorConfig)
    range_bearing_sensor: RangeBearingSensorConfig = msgspec.field(default_factory=RangeBearingSensorConfig)
    command_acceptance: CommandAcceptanceConfig = msgspec.field(default_factory=CommandAcceptanceConfig)
    divergence: DivergenceConfig = msgspec.field(default_factory=DivergenceConfig)
    # The coordinates the flight side sees and commands in (bench/plant/curvilinear.py): "cartesian"
    # LVLH, or "curvilinear" (arc length, radial difference, cross-track angle x radius), converted
    # at the plant boundary so CWH-based controllers fly long approaches on the nonlinear plant.
    navigation_frame: Literal["cartesian", "curvilinear"] = "cartesian"

    def __post_init__(self):
        if self.navigation_frame == "curvilinear" and self.dynamics != "nonlinear":
            raise ValueError("navigation_frame = \"curvilinear\" needs dynamics = \"nonlinear\" "
                             "(the linear CWH plant is Cartesian by construction)")


# ---- [attitude] (issue 11) ----------------------------------------------------------------------
def _vector(length: int, bound: float):
    return Annotated[list[Annotated[float, msgspec.Meta(ge=-bound, le=bound)]],
                     msgspec.Meta(min_length=length, max_length=length)]


# A unit quaternion's components are within [-1, 1]; the unit-norm check names a wrong one.
Quaternion = _vector(4, 1.5)
# Residual dipoles (A m^2): the board's coils give 0.2, a bad CubeSat 0.1; 100 is no spacecraft.
Dipole3 = _vector(3, 100.0)
# Magnetometer biases (T): the Earth's field is at most 6.5e-5 T; 1e-2 T is 150 times that.
FieldBias3 = _vector(3, 1e-2)
# Inertia entries (kg m^2): the ISS is ~1e8; off-diagonal products may be negative.
InertiaEntries = Annotated[list[Annotated[float, msgspec.Meta(ge=-1e9, le=1e9)]], msgspec.Meta(min_length=3, max_length=9)]
Window = Annotated[list[NonNegative], msgspec.Meta(min_length=2, max_length=2)]
Degrees = Annotated[float, msgspec.Meta(ge=-360.0, le=360.0)]


class AttitudeConfigError(ValueError):
    """A physically impossible [attitude] value; the message starts with the field's path."""


class OrbitConfig(msgspec.Struct, forbid_unknown_fields=True):
    # "sgp4": propagate `tle` (two lines); "circular": the fast option below.
    model: Literal["sgp4", "circular"] = "circular"
    tle: Annotated[list[Annotated[str, msgspec.Meta(max_length=80)]], msgspec.Meta(max_length=2)] | None = None
    # The run's start (UTC, ISO 8601); also the IGRF date. Default for sgp4: the TLE's epoch.
    epoch_utc: Annotated[str, msgspec.Meta(max_length=64)] | None = None
    # Up to 1e9 m (2.5 times the Moon's distance), as the relative state.
    altitude_m: Annotated[float, msgspec.Meta(gt=0, le=1e9)] = 500e3
    inclination_deg: Annotated[float, msgspec.Meta(ge=0, le=180)] = 97.4
    raan_deg: Degrees = 0.0
    initial_argument_of_latitude_deg: Degrees = 0.0


class FieldConfig(msgspec.Struct, forbid_unknown_fields=True):
    # "igrf": IGRF-14 along the orbit, tabulated every grid_s and splined; "dipole": tilted dipole.
    model: Literal["igrf", "dipole"] = "dipole"
    # The table holds (run + planner horizon) / grid_s points, at most 1e6 (bench.scenario).
    grid_s: Annotated[float, msgspec.Meta(ge=1e-3, le=60)] = 10.0


class DisturbanceConfig(msgspec.Struct, forbid_unknown_fields=True):
    gravity_gradient: bool = True
    # The spacecraft's own magnetic moment (body axes); 1e-3 A m^2 is a tidy CubeSat.
    residual_dipole_am2: Dipole3 = msgspec.field(default_factory=lambda: [0.0, 0.0, 0.0])


class CoilsConfig(msgspec.Struct, forbid_unknown_fields=True):
    """[attitude.coils]: what each coil makes of the dipole its driver is set to (bench.plant.coils):
    torque = (gain * applied) x B per coil from from_s (simulated s) on. 1 healthy, 0 open, -1
    reversed (wired backwards after the current sensor), 0.5 weak. The board and its telemetry
    know nothing of it: only the dynamics show it (the FDIR monitor's test case)."""
    gain: _vector(3, 2.0) = msgspec.field(default_factory=lambda: [1.0, 1.0, 1.0])   # per coil, within +-2
    from_s: Annotated[float, msgspec.Meta(ge=0, le=1e8)] = 0.0


class AttitudeSensorsConfig(msgspec.Struct, forbid_unknown_fields=True):
    """Rates and true noise levels (bench.plant.attitude.AttitudeSensorSpec)."""
    # The plant's step rate; at most 1 kHz (a fast MEMS gyro), at least one step per 1000 s.
    gyro_rate_hz: Annotated[float, msgspec.Meta(ge=1e-3, le=1000.0)] = 10.0
    gyro_noise_density_radps_per_rthz: NonNegative = 1.0e-4
    gyro_bias_random_walk_radps2_per_rthz: NonNegative = 1.0e-6
    initial_gyro_bias_std_radps: NonNegative = 1.0e-3
    magnetometer_period_s: Annotated[float, msgspec.Meta(gt=0, le=1e6)] = 1.0
    # "schedule": every magnetometer_period_s. "coil_blanking": once per coil-blanking window of the
    # magnetorquer board ([can.board] mag_window_*), on the first gyro tick at which the board
    # reports its coils off (real-time runs: the windows are wall-clock).
    magnetometer_sampling: Literal["schedule", "coil_blanking"] = "schedule"
    magnetometer_noise_std_t: NonNegative = 1.0e-7
    magnetometer_bias_t: FieldBias3 = msgspec.field(default_factory=lambda: [0.0, 0.0, 0.0])
    star_tracker_period_s: Annotated[float, msgspec.Meta(gt=0, le=1e6)] = 1.0
    star_tracker_noise_std_rad: NonNegative = 1.0e-4
    star_tracker_boresight_noise_factor: Annotated[float, msgspec.Meta(ge=1, le=1e6)] = 8.0
    star_tracker_outages_s: Annotated[list[Window], msgspec.Meta(max_length=1000)] = []


class AttitudePlantConfig(msgspec.Struct, forbid_unknown_fields=True):
    # run.steps overrides (steps at the gyro rate); duration x rate is at most 1e5 steps (bench.scenario).
    duration_s: Annotated[float, msgspec.Meta(gt=0, le=1e8)] = 60.0
    # Principal moments [Jxx, Jyy, Jzz] or a full row-major 3x3 matrix, kg m^2.
    inertia_kgm2: InertiaEntries = msgspec.field(default_factory=lambda: [2.2e-3, 2.3e-3, 2.0e-3])
    initial_q_wxyz: Quaternion = msgspec.field(default_factory=lambda: [1.0, 0.0, 0.0, 0.0])   # body to inertial
    # Body axes; 3600 deg/s (10 turns a second) is beyond any tumble a detumble starts from.
    initial_rate_dps: _vector(3, 3600.0) = msgspec.field(default_factory=lambda: [0.0, 0.0, 0.0])
    orbit: OrbitConfig = msgspec.field(default_factory=OrbitConfig)
    field: FieldConfig = msgspec.field(default_factory=FieldConfig)
    disturbances: DisturbanceConfig = msgspec.field(default_factory=DisturbanceConfig)
    sensors: AttitudeSensorsConfig = msgspec.field(default_factory=AttitudeSensorsConfig)
    coils: CoilsConfig = msgspec.field(default_factory=CoilsConfig)

    def inertia_matrix(self) -> np.ndarray:
        return inertia_matrix(self.inertia_kgm2, "attitude.inertia_kgm2")

    def epoch(self) -> datetime | None:
        return parse_epoch(self.orbit.epoch_utc, "attitude.orbit.epoch_utc")


def inertia_matrix(values: list[float], field: str) -> np.ndarray:
    """3 principal moments or 9 entries; symmetric positive definite, or AttitudeConfigError."""
    j = np.asarray(values, dtype=float)
    if j.size == 3:
        j = np.diag(j)
    elif j.size == 9:
        j = j.reshape(3, 3)
    else:
        raise AttitudeConfigError(f"{field}: needs 3 principal moments or 9 matrix entries, got {j.size}")
    if not np.all(np.isfinite(j)):
        raise AttitudeConfigError(f"{field}: not finite")
    if not np.allclose(j, j.T, rtol=0, atol=1e-12 * np.abs(j).max()):
        raise AttitudeConfigError(f"{field}: not symmetric")
    eigenvalues = np.linalg.eigvalsh(j)
    if eigenvalues.min() <= 0:
        raise AttitudeConfigError(f"{field}: not positive definite (eigenvalues {eigenvalues.tolist()})")
    # A rigid body's principal moments obey the triangle inequality (J1 + J2 >= J3).
    if eigenvalues[0] + eigenvalues[1] < eigenvalues[2] * (1 - 1e-9):
        raise AttitudeConfigError(f"{field}: principal moments {eigenvalues.tolist()} break the triangle "
                                  "inequality, no rigid body has them")
    return j


def check_unit_quaternion(values: list[float], field: str, tolerance: float = 1e-6) -> np.ndarray:
    q = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(q)):
        raise AttitudeConfigError(f"{field}: not finite ({values})")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > tolerance:
        raise AttitudeConfigError(f"{field}: not a unit quaternion (norm {norm:.9g}; scalar first [w, x, y, z])")
    return q / norm


def parse_epoch(text: str | None, field: str) -> datetime | None:
    if text is None:
        return None
    try:
        epoch = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise AttitudeConfigError(f"{field}: {text!r} is not an ISO 8601 time") from None
    return epoch if epoch.tzinfo else epoch.replace(tzinfo=timezone.utc)


def check_attitude_plant(config: AttitudePlantConfig) -> None:
    """Everything msgspec's per-field types cannot say; raises AttitudeConfigError."""
    config.inertia_matrix()
    check_unit_quaternion(config.initial_q_wxyz, "attitude.initial_q_wxyz")
    if not all(np.isfinite(config.initial_rate_dps)):
        raise AttitudeConfigError("attitude.initial_rate_dps: not finite")
    config.epoch()
    orbit = config.orbit
    if orbit.model == "sgp4":
        if orbit.tle is None or len(orbit.tle) != 2:
            raise AttitudeConfigError("attitude.orbit.tle: the sgp4 orbit needs the two lines of a TLE")
        from bench.gnc.environment import Sgp4Orbit, TleError

        try:
            Sgp4Orbit.from_tle(*orbit.tle, config.epoch())
        except TleError as exc:
            raise AttitudeConfigError(f"attitude.orbit.tle: {exc}") from None
    elif orbit.tle is not None:
        raise AttitudeConfigError("attitude.orbit.tle: given but attitude.orbit.model is 'circular'")
    if config.field.model == "igrf" and orbit.model == "circular" and orbit.epoch_utc is None:
        raise AttitudeConfigError("attitude.orbit.epoch_utc: IGRF along a circular orbit needs a date")
    s = config.sensors
    for name in ("magnetometer_period_s", "star_tracker_period_s"):
        ratio = getattr(s, name) * s.gyro_rate_hz
        if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
            raise AttitudeConfigError(f"attitude.sensors.{name}: must be a whole number of gyro samples "
                                      f"({getattr(s, name)} s at {s.gyro_rate_hz} Hz)")
    for i, (start, end) in enumerate(s.star_tracker_outages_s):
        if end <= start:
            raise AttitudeConfigError(f"attitude.sensors.star_tracker_outages_s[{i}]: end must follow start")
