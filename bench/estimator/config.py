"""Scenario section [estimator]: which estimator, and what the smoothers assume about the world.

The numbers here are the estimator's *beliefs* (assumed noise levels). What the whole flight side
believes about the orbit, which the controller shares, is in [onboard] (bench.scenario); the
truth the plant simulates is in [plant]. A mistuned estimator is a legitimate scenario.
"""
from __future__ import annotations

from typing import Annotated, Literal

import msgspec

Positive = Annotated[float, msgspec.Meta(gt=0, le=1e15)]
NonNegative = Annotated[float, msgspec.Meta(ge=0, le=1e15)]
# Window lengths and decimations: the smoother keeps lag_steps states, so bounded by memory.
PositiveInt = Annotated[int, msgspec.Meta(ge=1, le=10_000)]


class TranslationSmootherConfig(msgspec.Struct, forbid_unknown_fields=True):
    # Fixed-lag window in plant steps: the smoother keeps the states of the last lag_steps steps.
    lag_steps: PositiveInt = 20
    # Spectral density of a white acceleration the smoother assumes acts on the chaser (Van Loan
    # discretisation over each step). The plant's linear CWH has none; a small value keeps the
    # estimator honest about unmodelled dynamics. 1e-9 m^2/s^3 is ~0.8 mm/s of velocity random
    # walk per 600 s step.
    process_noise_psd_m2ps3: Positive = 1.0e-9
    # Prior on the initial relative velocity (the first position fix gives the position).
    initial_velocity_std_mps: Positive = 10.0
    # Relative-position noise assumed when a measurement does not carry its own noise level.
    position_noise_std_m: Positive = 10.0
    # Use one relative-position fix every this many plant steps (a slower sensor).
    measurement_every_steps: PositiveInt = 1
    # "relpos": Cartesian relative position; "range_bearing": range, azimuth and elevation derived
    # from it (a radar or camera-like sensor), with the noise levels below.
    sensor: Literal["relpos", "range_bearing"] = "relpos"
    range_noise_std_m: Positive = 10.0
    bearing_noise_std_rad: Positive = 1.0e-4
    # Uncertain target orbit (seed 001, third case): estimate the mean motion jointly with the
    # state, starting from the believed value ([onboard]) with this relative 1-sigma.
    estimate_mean_motion: bool = False
    mean_motion_prior_rel_std: Positive = 0.03


class AttitudeSmootherConfig(msgspec.Struct, forbid_unknown_fields=True):
    # One smoother state (attitude, gyro bias) per magnetometer or star-tracker sample; gyro
    # samples in between are preintegrated. The window keeps the states of the last lag_s seconds.
    lag_s: Positive = 20.0
    # Assumed sensor noise. Gyro: white rate noise density and bias random walk (continuous).
    gyro_noise_density_radps_per_rthz: Positive = 1.0e-4
    gyro_bias_random_walk_radps2_per_rthz: Positive = 1.0e-6
    initial_gyro_bias_std_radps: Positive = 1.0e-3
    magnetometer_noise_std_t: Positive = 1.0e-7
    star_tracker_noise_std_rad: Positive = 1.0e-4


class EstimatorConfig(msgspec.Struct, forbid_unknown_fields=True):
    # "truth": full state knowledge, seed 001's first case (ground truth passed through).
    # "smoother": gtsam fixed-lag smoothing of the noisy relative position (seed 001's second and,
    # with translation.estimate_mean_motion, third case).
    mode: Literal["truth", "smoother"] = "truth"
    translation: TranslationSmootherConfig = msgspec.field(default_factory=TranslationSmootherConfig)
    attitude: AttitudeSmootherConfig = msgspec.field(default_factory=AttitudeSmootherConfig)
