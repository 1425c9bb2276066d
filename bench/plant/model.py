"""The translational plant: owns the true relative state and simulated time.

One object serves both the plant process and the in-process simulation, so that the two can
only differ in their wiring (the multi-process run must reproduce the in-process one).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bench.gnc.cwh import RendezvousParams
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
class TranslationPlant:
    params: RendezvousParams
    model: str
    state_m_mps: np.ndarray
    sensor: RelativePositionSensor
    step_index: int = 0
    states_m_mps: list = field(default_factory=list)
    thrusts_n: list = field(default_factory=list)

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> "TranslationPlant":
        x0 = scenario.initial_state_m_mps()
        # One generator per sensor, seeded from the scenario: runs repeat to the last bit.
        rng = np.random.default_rng([scenario.run.seed, 1])
        sensor = RelativePositionSensor(scenario.plant.relpos_sensor.noise_std_m, rng)
        plant = cls(scenario.params(), scenario.plant.dynamics, x0, sensor)
        plant.states_m_mps.append(x0.copy())
        return plant

    @property
    def sim_time_s(self) -> float:
        return self.step_index * self.params.time_step_s

    def measure_position_m(self) -> np.ndarray:
        return self.sensor.measure(self.state_m_mps[:3])

    def apply(self, thrust_n: np.ndarray) -> None:
        """Hold thrust over one step and advance the true state."""
        thrust_n = np.asarray(thrust_n, dtype=float)
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
