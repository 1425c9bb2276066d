"""Factor-graph factors of the estimators, built the cheap way where the model allows.

A linear Gaussian term ||sum_i A_i x_i - b||^2_Sigma is a whitened `JacobianFactor` wrapped in a
`LinearContainerFactor` whose linearisation point is zero, so the container's delta *is* the
variable and the factor is exact at every linearisation (no Python callback per update). Python
`CustomFactor`s are used only where the model is nonlinear: the CWH motion with an unknown mean
motion, and range/bearing measurements.
"""
from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from bench.estimator.motion_model import CwhMotionModel, DiscreteModel
from bench.gnc.quaternion import skew
from bench.gnc.range_bearing import range_bearing, range_bearing_jacobian, wrap_angle_rad  # noqa: F401 (re-exported)


def whitening_matrix(covariance: np.ndarray) -> np.ndarray:
    """W with W' W = Sigma^-1 (inverse of the lower Cholesky factor); raises naming a bad Sigma."""
    covariance = np.atleast_2d(np.asarray(covariance, dtype=float))
    if not np.all(np.isfinite(covariance)):
        raise ValueError("covariance has non-finite entries")
    try:
        lower = np.linalg.cholesky(covariance)
    except np.linalg.LinAlgError:
        raise ValueError("covariance is not positive definite") from None
    # numpy, not scipy.linalg.solve_triangular: the latter measured ~12 ms per 3x3 call here.
    return np.linalg.inv(lower)


def linear_factor(terms: Sequence[tuple[int, np.ndarray]], rhs: np.ndarray, covariance: np.ndarray | None = None,
                  *, whiten: np.ndarray | None = None) -> gtsam.LinearContainerFactor:
    """The Gaussian term ||sum_i A_i x_i - rhs||^2 over covariance, on vector-valued keys.

    Give either the covariance or, when the caller has it cached, its whitening matrix.
    """
    if whiten is None:
        whiten = whitening_matrix(covariance)
    rows = len(rhs)
    unit = gtsam.noiseModel.Unit.Create(rows)
    args: list = []
    zero_point = gtsam.Values()
    for key, matrix in terms:
        args += [key, whiten @ matrix]
        zero_point.insert(key, np.zeros(matrix.shape[1]))
    jacobian = gtsam.JacobianFactor(*args, whiten @ np.asarray(rhs, dtype=float), unit)
    return gtsam.LinearContainerFactor(jacobian, zero_point)


def joint_prior_factor(keys_and_means: Sequence[tuple[int, object]], covariance: np.ndarray) -> gtsam.LinearContainerFactor:
    """A Gaussian prior on several variables together (vectors or Rot3), cross-covariances kept.

    The error of each variable is its local coordinates at the mean (for a Rot3 R0: Log(R0' R),
    the body-frame error), so this is the first-order prior gtsam's own marginal factors are.
    """
    whiten = whitening_matrix(covariance)
    point = gtsam.Values()
    args: list = []
    column = 0
    for key, mean in keys_and_means:
        if isinstance(mean, gtsam.Rot3):
            point.insert(key, mean)
            dim = 3
        else:
            mean = np.asarray(mean, dtype=float)
            point.insert(key, mean)
            dim = mean.size
        args += [key, whiten[:, column:column + dim]]
        column += dim
    if column != whiten.shape[0]:
        raise ValueError(f"covariance is {whiten.shape[0]} square but the variables have {column} dimensions")
    jacobian = gtsam.JacobianFactor(*args, np.zeros(column), gtsam.noiseModel.Unit.Create(column))
    return gtsam.LinearContainerFactor(jacobian, point)


def prior_factor(key: int, mean: np.ndarray, covariance: np.ndarray) -> gtsam.LinearContainerFactor:
    mean = np.asarray(mean, dtype=float)
    return linear_factor([(key, np.eye(mean.size))], mean, covariance)


def cwh_motion_factor(previous_key: int, key: int, thrust_n: np.ndarray,
                      model: DiscreteModel) -> gtsam.LinearContainerFactor:
    """x_k - Ad x_{k-1} = Bd u_{k-1} + w, for a known model."""
    return linear_factor(
        [(previous_key, -model.transition), (key, np.eye(model.transition.shape[0]))],
        model.input_matrix @ np.asarray(thrust_n, dtype=float),
        whiten=model.process_whitening,
    )


def cwh_motion_factor_unknown_mean_motion(
    previous_key: int, key: int, mean_motion_key: int, thrust_n: np.ndarray, n_steps: int,
    model: CwhMotionModel, believed_mean_motion_radps: float,
    nonlinear_correction: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> gtsam.CustomFactor:
    """x_k - Ad(n) x_{k-1} - Bd(n) u = w with n = n_believed (1 + delta) and delta a variable.

    nonlinear_correction (c, dF, x*): a nonlinear model's difference from CWH linearised at x*,
    x_k = Ad(n) x_{k-1} + Bd(n) u + c + dF (x_{k-1} - x*) + w (the two-body model's factor).

    delta is relative (dimensionless, order 1e-2) rather than n itself (order 1e-3 rad/s) so the
    smoother's relinearisation thresholds mean the same thing for it as for the states.
    Q is taken at the believed mean motion: it depends on n only weakly.
    """
    thrust_n = np.asarray(thrust_n, dtype=float).copy()
    whiten = model.discrete(believed_mean_motion_radps, n_steps).process_whitening
    if nonlinear_correction is None:
        offset, d_transition_nl, about = np.zeros(6), np.zeros((6, 6)), np.zeros(6)
    else:
        offset, d_transition_nl, about = (np.asarray(v, dtype=float).copy() for v in nonlinear_correction)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
        x_prev = values.atVector(previous_key)
        x_now = values.atVector(key)
        delta = values.atVector(mean_motion_key)[0]
        mean_motion = believed_mean_motion_radps * (1.0 + delta)
        transition, input_matrix = model.transition_and_input(mean_motion, n_steps)
        residual = x_now - transition @ x_prev - input_matrix @ thrust_n - offset - d_transition_nl @ (x_prev - about)
        if jacobians is not None:
            d_transition, d_input = model.derivative(mean_motion, n_steps)
            d_residual_d_delta = -(d_transition @ x_prev + d_input @ thrust_n) * believed_mean_motion_radps
            jacobians[0] = -whiten @ (transition + d_transition_nl)
            jacobians[1] = whiten
            jacobians[2] = (whiten @ d_residual_d_delta).reshape(-1, 1)
        return whiten @ residual

    unit = gtsam.noiseModel.Unit.Create(whiten.shape[0])
    return gtsam.CustomFactor(unit, [previous_key, key, mean_motion_key], error)


def position_factor(key: int, measured_m: np.ndarray, noise: gtsam.noiseModel.Base) -> gtsam.CustomFactor:
    """The relative position (the state's first three) with any gtsam noise model, robust ones too.

    The plain Gaussian case is cheaper as `linear_factor`; gtsam's m-estimators reweight only
    noise-model factors, hence this one (one Python callback per linearisation).
    """
    measured_m = np.asarray(measured_m, dtype=float).copy()
    jacobian = np.hstack([np.eye(3), np.zeros((3, 3))])

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
        if jacobians is not None:
            jacobians[0] = jacobian
        return values.atVector(key)[:3] - measured_m

    return gtsam.CustomFactor(noise, [key], error)


def range_bearing_factor(key: int, measured: np.ndarray, noise: gtsam.noiseModel.Base) -> gtsam.CustomFactor:
    """Range, azimuth, elevation of the chaser's relative position (the state's first three).

    noise: sigmas [range m, bearing rad, bearing rad], possibly inside a gtsam robust model.
    """
    measured = np.asarray(measured, dtype=float).copy()

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
        position = values.atVector(key)[:3]
        residual = range_bearing(position) - measured
        residual[1] = wrap_angle_rad(residual[1])    # azimuth wraps
        if jacobians is not None:
            jacobians[0] = np.hstack([range_bearing_jacobian(position), np.zeros((3, 3))])
        return residual

    return gtsam.CustomFactor(noise, [key], error)


# The calibration variable holds the magnetometer bias in microtesla, not tesla: whitened by a
# 1e-7 T noise, a bias column in tesla would be 1e7 against ~300 for the attitude columns, a
# needlessly ill-conditioned system; in microtesla it is 10.
MAGNETOMETER_BIAS_UNIT_T = 1.0e-6


def magnetometer_calibrated_factor(rotation_key: int, calibration_key: int, measured_t: np.ndarray,
                                   field_inertial_t: np.ndarray, noise: gtsam.noiseModel.Base) -> gtsam.CustomFactor:
    """measured = (1 + c[3]) R' B_inertial + c[:3] * 1 uT + noise, with R and c = [bias uT; scale - 1] variables.

    gtsam's MagFactor1 is this model with the bias and scale known; MagFactor2/3 estimate them for
    a known rotation (and are not in gtsam's Python wrapper). Here both are unknown. Jacobian in
    R's right perturbation R Exp(theta): (R Exp(theta))' B = R' B + [R' B]x theta.
    """
    measured_t = np.asarray(measured_t, dtype=float).copy()
    field_inertial_t = np.asarray(field_inertial_t, dtype=float).copy()

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
        calibration = values.atVector(calibration_key)
        body = values.atRot3(rotation_key).unrotate(field_inertial_t)
        scale = 1.0 + calibration[3]
        if jacobians is not None:
            jacobians[0] = scale * skew(body)
            jacobians[1] = np.hstack([np.eye(3) * MAGNETOMETER_BIAS_UNIT_T, body.reshape(3, 1)])
        return scale * body + calibration[:3] * MAGNETOMETER_BIAS_UNIT_T - measured_t

    return gtsam.CustomFactor(noise, [rotation_key, calibration_key], error)

