"""Scenario section [plant]: which dynamics, where the chaser starts, the sensors.

Every number has a documented range (docs/run_safety.md): finite, and bounded so that no value a
file can hold makes the plant allocate without limit or integrate nonsense.
"""
from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from bench.data import load_reference

MODEL = load_reference()["model"]     # the defaults below are the reference's (seed 003)
NonNegative = Annotated[float, msgspec.Meta(ge=0, le=1e9)]
# 1e9 m is 2.5 times the Moon's distance: no relative-motion scenario starts farther out.
StateValue = Annotated[float, msgspec.Meta(ge=-1e9, le=1e9)]
State6 = Annotated[list[StateValue], msgspec.Meta(min_length=6, max_length=6)]


class RelativePositionSensorConfig(msgspec.Struct, forbid_unknown_fields=True):
    noise_std_m: NonNegative = 10.0


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
    mass_kg: Annotated[float, msgspec.Meta(gt=0, le=1e9)] = MODEL["mass_kg"]
    gravitational_parameter_m3ps2: Annotated[float, msgspec.Meta(gt=0, le=1e21)] = MODEL["gravitational_parameter"]
    target_radius_m: Annotated[float, msgspec.Meta(gt=0, le=1e12)] = MODEL["target_radius_m"]
    time_step_s: Annotated[float, msgspec.Meta(gt=0, le=86_400)] = MODEL["time_step_s"]
    relpos_sensor: RelativePositionSensorConfig = msgspec.field(default_factory=RelativePositionSensorConfig)
    command_acceptance: CommandAcceptanceConfig = msgspec.field(default_factory=CommandAcceptanceConfig)
    divergence: DivergenceConfig = msgspec.field(default_factory=DivergenceConfig)
