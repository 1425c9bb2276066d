"""Scenario section [plant]: which dynamics, where the chaser starts, the sensors."""
from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from bench.data import load_reference

MODEL = load_reference()["model"]     # the defaults below are the reference's (seed 003)
Positive = Annotated[float, msgspec.Meta(gt=0)]
NonNegative = Annotated[float, msgspec.Meta(ge=0)]
State6 = Annotated[list[float], msgspec.Meta(min_length=6, max_length=6)]


class RelativePositionSensorConfig(msgspec.Struct, forbid_unknown_fields=True):
    noise_std_m: NonNegative = 10.0


class RangeBearingSensorConfig(msgspec.Struct, forbid_unknown_fields=True):
    # A radar- or camera-like sensor: range, azimuth atan2(y, x) and elevation asin(z / r) of the
    # chaser in the target's LVLH frame, each with white Gaussian noise.
    range_noise_std_m: NonNegative = 10.0
    bearing_noise_std_rad: NonNegative = 1.0e-4


class PlantConfig(msgspec.Struct, forbid_unknown_fields=True):
    # "cwh": linear CWH, exact discretisation; "nonlinear": two-body chaser and target (seed 001).
    dynamics: Literal["cwh", "nonlinear"] = "cwh"
    # A name from the reference (A, B, C) or an explicit state in m and m/s.
    initial_condition: str = "A"
    initial_state_m_mps: State6 | None = None
    mass_kg: Positive = MODEL["mass_kg"]
    gravitational_parameter_m3ps2: Positive = MODEL["gravitational_parameter"]
    target_radius_m: Positive = MODEL["target_radius_m"]
    time_step_s: Positive = MODEL["time_step_s"]
    relpos_sensor: RelativePositionSensorConfig = msgspec.field(default_factory=RelativePositionSensorConfig)
    range_bearing_sensor: RangeBearingSensorConfig = msgspec.field(default_factory=RangeBearingSensorConfig)
    # The coordinates the flight side sees and commands in (bench/plant/curvilinear.py): "cartesian"
    # LVLH, or "curvilinear" (arc length, radial difference, cross-track angle x radius), converted
    # at the plant boundary so CWH-based controllers fly long approaches on the nonlinear plant.
    navigation_frame: Literal["cartesian", "curvilinear"] = "cartesian"

    def __post_init__(self):
        if self.navigation_frame == "curvilinear" and self.dynamics != "nonlinear":
            raise ValueError("navigation_frame = \"curvilinear\" needs dynamics = \"nonlinear\" "
                             "(the linear CWH plant is Cartesian by construction)")
