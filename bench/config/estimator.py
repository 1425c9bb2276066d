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
Probability = Annotated[float, msgspec.Meta(gt=0, lt=1)]
# Magnetometer bias beliefs (T; the Earth's field is at most 6.5e-5 T) and the boresight direction.
FieldBias3 = Annotated[list[Annotated[float, msgspec.Meta(ge=-1e-2, le=1e-2)]], msgspec.Meta(min_length=3, max_length=3)]
Direction3 = Annotated[list[Annotated[float, msgspec.Meta(ge=-1e3, le=1e3)]], msgspec.Meta(min_length=3, max_length=3)]


class TranslationSmootherConfig(msgspec.Struct, forbid_unknown_fields=True):
    # Fixed-lag window in plant steps: the smoother keeps the states of the last lag_steps steps.
    lag_steps: PositiveInt = 20
    # Spectral density of a white acceleration the smoother believes acts on the chaser (Van Loan
    # discretisation over each step). None: the flight side's belief ([onboard]), whose default
    # is none, as the linear CWH plant has none (an assumed 1e-9 m^2/s^3, ~0.8 mm/s of velocity
    # random walk per 600 s step, made the in-loop NEES 3.2 instead of 6).
    process_noise_psd_m2ps3: NonNegative | None = None
    # The smoother's motion model between steps. "cwh": the linear CWH equations (exact for the
    # linear plant). "two_body_cartesian" / "two_body_curvilinear": the exact relative motion of
    # two-body gravity about a circular orbit (bench/estimator/two_body_model.py), in the flight
    # side's navigation frame (plant.navigation_frame), linearised once about the previous
    # estimate when each step's motion factor is made; the model for the nonlinear plant.
    motion_model: Literal["cwh", "two_body_cartesian", "two_body_curvilinear"] = "cwh"
    # Prior on the initial relative velocity (the first position fix gives the position).
    initial_velocity_std_mps: Positive = 10.0
    # Relative-position noise the estimator believes; None: [onboard]'s belief, else the plant's
    # sensor noise (a well-tuned flight side). The noise level a message carries is never used.
    position_noise_std_m: Positive | None = None
    # Use one relative-position fix every this many plant steps (a slower sensor).
    measurement_every_steps: PositiveInt = 1
    # "relpos": Cartesian relative position; "range_bearing": range, azimuth and elevation derived
    # from it (a radar or camera-like sensor), with the noise levels below.
    sensor: Literal["relpos", "range_bearing"] = "relpos"
    # "prediction": each range/bearing fix is one linear factor, linearised (iterated-EKF) about
    # the state's prediction and never relinearised (fast: no Python callback per update);
    # "every_update": gtsam's nonlinear factor, relinearised while the state moves.
    range_bearing_linearisation: Literal["prediction", "every_update"] = "prediction"
    # Believed range/bearing noise; None: [onboard]'s belief, else the plant's sensor's.
    range_noise_std_m: Positive | None = None
    bearing_noise_std_rad: Positive | None = None
    # Uncertain target orbit (seed 001, third case): estimate the mean motion jointly with the
    # state, starting from the believed value ([onboard]) with this relative 1-sigma.
    estimate_mean_motion: bool = False
    mean_motion_prior_rel_std: Positive = 0.03
    # Innovation gate: a measurement whose NIS against the prediction exceeds the chi-square
    # quantile of this probability (3 degrees of freedom; 0.9999: NIS 21.1, one good fix in
    # 10 000 lost) is not used. None: no gate (and none of the protections below).
    gate_probability: Probability | None = 0.9999
    # A run of rejected fixes must not walk the gate open: while fixes are being rejected the
    # prediction widens (process noise), until a fix of an outlier burst fits it. The rejected
    # fixes of the run are tracked on their own (a track started from them alone); a fix the
    # gate would pass but which that track explains better than the prediction by this
    # likelihood ratio is taken for the burst's next fix and rejected too.
    gate_burst_likelihood_ratio: Annotated[float, msgspec.Meta(ge=1, le=1e15)] = 1.0
    # Re-acquisition: after at least this many consecutive rejected fixes, when the last
    # reacquire_consistent_fixes of them form a consistent track (each within the gate of the
    # track made by the ones before it), the smoother restarts from that track. A one-sided
    # burst shorter than this is never adopted; a longer consistent one cannot be told from a
    # real unmodelled motion by the fixes alone.
    reacquire_after_rejections: PositiveInt = 8
    reacquire_consistent_fixes: Annotated[int, msgspec.Meta(ge=3, le=10_000)] = 4
    # Robust measurement noise (gtsam's m-estimators): "huber" or "cauchy" down-weight residuals
    # beyond robust_threshold_sigma (norm of the whitened residual); "none" is least squares.
    # Relinearised as the state moves (iterated, as iSAM2 / batch Levenberg-Marquardt would), so
    # the weights are those of the converged estimate, not of the prediction.
    robust_loss: Literal["none", "huber", "cauchy"] = "none"
    robust_threshold_sigma: Positive = 3.0


class AttitudeSmootherConfig(msgspec.Struct, forbid_unknown_fields=True):
    # One smoother state (attitude, gyro bias) per magnetometer or star-tracker sample; gyro
    # samples in between are preintegrated. The window keeps the states of the last lag_s seconds.
    lag_s: Positive = 20.0
    # Assumed sensor noise. Gyro: white rate noise density and bias random walk (continuous).
    gyro_noise_density_radps_per_rthz: Positive = 1.0e-4
    gyro_bias_random_walk_radps2_per_rthz: Positive = 1.0e-6
    initial_gyro_bias_std_radps: Positive = 1.0e-3
    magnetometer_noise_std_t: Positive = 1.0e-7
    # Magnetometer calibration believed: measured = scale * B_body + bias + noise. With
    # estimate_magnetometer_calibration the bias and scale are estimated (one constant variable)
    # from these as the prior mean with the prior sigmas below.
    magnetometer_bias_t: FieldBias3 = msgspec.field(default_factory=lambda: [0.0, 0.0, 0.0])
    magnetometer_scale: Positive = 1.0
    estimate_magnetometer_calibration: bool = False
    magnetometer_bias_prior_std_t: Positive = 5.0e-6
    magnetometer_scale_prior_std: Positive = 0.02
    # Star tracker: error across the boresight (per axis) and about it, boresight in body axes.
    star_tracker_noise_std_rad: Positive = 1.0e-4
    star_tracker_boresight_noise_std_rad: Positive = 8.0e-4
    star_tracker_boresight_body: Direction3 = msgspec.field(default_factory=lambda: [0.0, 0.0, 1.0])
    # Innovation gate on each keyframe's measurements together (chi-square quantile of this
    # probability, 3 dof per sensor); None: no gate.
    gate_probability: Probability | None = None


class EstimatorConfig(msgspec.Struct, forbid_unknown_fields=True):
    # "truth": full state knowledge, seed 001's first case (ground truth passed through).
    # "smoother": gtsam fixed-lag smoothing of the noisy relative position (seed 001's second and,
    # with translation.estimate_mean_motion, third case).
    mode: Literal["truth", "smoother"] = "truth"
    translation: TranslationSmootherConfig = msgspec.field(default_factory=TranslationSmootherConfig)
    attitude: AttitudeSmootherConfig = msgspec.field(default_factory=AttitudeSmootherConfig)
