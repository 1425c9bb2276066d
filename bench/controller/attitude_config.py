"""Scenario section [attitude_control]: which attitude law the flight software runs, its gains,
the target, and what the flight side believes about the spacecraft.

The law's dipole limit defaults to the board's ([can.board] max_dipole_am2); the believed inertia
to the plant's (set it to fly a mistuned law).
"""
from __future__ import annotations

from typing import Annotated, Literal

import msgspec

Positive = Annotated[float, msgspec.Meta(gt=0)]
Vec4 = Annotated[list[float], msgspec.Meta(min_length=4, max_length=4)]


class AttitudeTargetConfig(msgspec.Struct, forbid_unknown_fields=True):
    # "inertial": hold q_wxyz (target to inertial). "nadir": body z to nadir, body x along the
    # velocity (the orbit of [attitude.orbit], which the flight side knows).
    kind: Literal["inertial", "nadir"] = "inertial"
    q_wxyz: Vec4 = msgspec.field(default_factory=lambda: [1.0, 0.0, 0.0, 0.0])


class AttitudeControlConfig(msgspec.Struct, forbid_unknown_fields=True):
    law: str = "bdot"                       # a key of bench.controller.attitude_laws.ATTITUDE_LAWS
    # Not constrained here so that a zero or negative limit gets the scenario's own message.
    dipole_limit_am2: float | None = None   # default: [can.board] max_dipole_am2
    inertia_kgm2: list[float] | None = None  # believed; default: [attitude] inertia_kgm2
    target: AttitudeTargetConfig = msgspec.field(default_factory=AttitudeTargetConfig)
    # B-dot: m = -k dB/dt. Avanzini & Giulietti (2012) give k = 2 n (1 + sin xi) J_min / |B|^2,
    # ~1e4 A m^2 s / T for the default body at 500 km. Measured here: 5e5 (too high) locks the spin
    # to the field and stalls at ~2.7 deg/s for two orbits; 1e4 reaches 0.3 deg/s in 3200 s.
    bdot_gain_am2_s_per_t: Positive = 1.0e4
    # Seed 002 sliding mode (lambda, k) and PD (kp, kd).
    sliding_gain_radps: Positive = 0.05
    convergence_gain_radps: Positive = 0.02
    kp_nm: Positive = 1.0e-5
    kd_nms: Positive = 5.0e-4
