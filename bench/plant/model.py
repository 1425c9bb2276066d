"""The translational plant: owns the true relative state and simulated time.

One object serves both the plant process and the in-process simulation, so that the two can
only differ in their wiring (the multi-process run must reproduce the in-process one).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bench.gnc.cwh import RendezvousParams
from bench.gnc.range_bearing import range_bearing
from bench.plant.curvilinear import cartesian_to_curvilinear, position_to_curvilinear_m, thrust_to_lvlh
from bench.plant.dynamics import propagate
from bench.scenario import Scenario


@dataclass
class RelativePositionSensor:
    """Relative position with white Gaussian noise, isotropic, in metres."""

    noise_std_m: float
    rng: np.random.Generator

    def measure(self, position_m: np.ndarray) -> np.ndarray:
        return position_m + self.noise_std_m * self.rng.standard_normal(3)


@dataclass
class RangeBearingSensor:
    """Range, azimuth and elevation of the relative position with white Gaussian noise; no fix
    when the measured range is at or below min_range_m."""

    range_noise_std_m: float
    bearing_noise_std_rad: float
    rng: np.random.Generator
    min_range_m: float = 0.0

    def measure(self, position_m: np.ndarray) -> np.ndarray | None:
        sigmas = np.array([self.range_noise_std_m, self.bearing_noise_std_rad, self.bearing_noise_std_rad])
        # Drawn with or without a fix, so that the noise of every later fix stays the same.
        noise = sigmas * self.rng.standard_normal(3)
        if np.linalg.norm(position_m) == 0.0:    # on the target: no bearing to measure
            return None
        measured = range_bearing(position_m) + noise
        return measured if measured[0] > self.min_range_m else None


@dataclass
class TranslationPlant:
    params: RendezvousParams
    model: str
    state_m_mps: np.ndarray
    sensor: RelativePositionSensor
    range_bearing_sensor: RangeBearingSensor | None = None
    step_index: int = 0
    # What the flight side sees and commands in: "cartesian" LVLH or "curvilinear" (the true state
    # and the recorded trajectory stay Cartesian LVLH; only sensing and commands are converted).
    navigation_frame: str = "cartesian"
    states_m_mps: list = field(default_factory=list)
    thrusts_n: list = field(default_factory=list)

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> "TranslationPlant":
        x0 = scenario.initial_state_m_mps()
        # One generator per sensor, seeded from the scenario: runs repeat to the last bit.
        rng = np.random.default_rng([scenario.run.seed, 1])
        sensor = RelativePositionSensor(scenario.plant.relpos_sensor.noise_std_m, rng)
        rb = scenario.plant.range_bearing_sensor
        # Its own generator: adding this sensor leaves the relative-position noise bit-identical.
        rb_sensor = RangeBearingSensor(rb.range_noise_std_m, rb.bearing_noise_std_rad,
                                       np.random.default_rng([scenario.run.seed, 2]), rb.min_range_m)
        plant = cls(scenario.params(), scenario.plant.dynamics, x0, sensor, rb_sensor,
                    navigation_frame=scenario.plant.navigation_frame)
        plant.states_m_mps.append(x0.copy())
        return plant

    @property
    def sim_time_s(self) -> float:
        return self.step_index * self.params.time_step_s

    @property
    def curvilinear(self) -> bool:
        return self.navigation_frame == "curvilinear"

    @property
    def navigation_state_m_mps(self) -> np.ndarray:
        """The true state in the flight side's coordinates (what full state knowledge gives)."""
        if self.curvilinear:
            return cartesian_to_curvilinear(self.state_m_mps, self.params.target_radius_m)
        return self.state_m_mps.copy()

    def measure_position_m(self) -> np.ndarray:
        """A noisy relative-position fix in the flight side's coordinates (noise is Cartesian)."""
        fix_m = self.sensor.measure(self.state_m_mps[:3])
        return position_to_curvilinear_m(fix_m, self.params.target_radius_m) if self.curvilinear else fix_m

    def measure_range_bearing(self) -> np.ndarray | None:
        """[range m, azimuth rad, elevation rad] of the chaser, with the sensor's noise; None
        without a fix."""
        return self.range_bearing_sensor.measure(self.state_m_mps[:3])

    def apply(self, thrust_n: np.ndarray) -> None:
        """Hold thrust (in the flight side's coordinates) over one step and advance the true state.

        A curvilinear command is along the local (e_r, e_theta, e_phi) at the chaser when it is
        applied, held fixed in LVLH over the step; the recorded thrust is the LVLH one.
        """
        thrust_n = np.asarray(thrust_n, dtype=float)
        if self.curvilinear:
            thrust_n = thrust_to_lvlh(thrust_n, self.state_m_mps[:3], self.params.target_radius_m)
        self.state_m_mps = propagate(self.state_m_mps, thrust_n, self.params.time_step_s, self.params, self.model)
        self.step_index += 1
        self.states_m_mps.append(self.state_m_mps.copy())
        self.thrusts_n.append(thrust_n.copy())

    def trajectory(self) -> dict[str, np.ndarray]:
        n = len(self.thrusts_n)
        return {
            "t_s": np.arange(n + 1) * self.params.time_step_s,
            "state_m_mps": np.array(self.states_m_mps),
            "thrust_n": np.array(self.thrusts_n).reshape(n, 3),
        }
