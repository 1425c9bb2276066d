"""Quaternion toolkit against independent references: scipy's Rotation and finite differences."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bench.gnc import quaternion as qt


def random_unit(rng):
    return qt.normalize(rng.normal(size=4))


def test_products_match_scipy():
    rng = np.random.default_rng(0)
    for _ in range(20):
        a, b = random_unit(rng), random_unit(rng)
        expected = (Rotation.from_quat(a, scalar_first=True) * Rotation.from_quat(b, scalar_first=True))
        got = qt.multiply(a, b)
        assert qt.angle_between_rad(got, expected.as_quat(scalar_first=True)) < 1e-12
        assert np.allclose(qt.left_matrix(a) @ b, qt.right_matrix(b) @ a)
        assert np.allclose(qt.rotation_matrix(a), Rotation.from_quat(a, scalar_first=True).as_matrix())


def test_cayley_round_trip_and_unit_norm():
    rng = np.random.default_rng(1)
    for scale in (1e-6, 0.3, 5.0, 300.0):
        phi = scale * rng.normal(size=3)
        q = qt.cayley(phi)
        assert abs(np.linalg.norm(q) - 1.0) < 1e-12
        assert np.allclose(qt.inverse_cayley(q), phi, rtol=1e-12, atol=0.0)
    with pytest.raises(ValueError, match="180"):
        qt.inverse_cayley(np.array([0.0, 1.0, 0.0, 0.0]))


def test_exp_log_match_scipy_rotvec():
    rng = np.random.default_rng(2)
    for angle in (1e-10, 0.1, 2.0, np.pi - 1e-6):
        axis = qt.normalize(np.concatenate([[0.0], rng.normal(size=3)]))[1:]
        r = angle * axis
        q = qt.exp(r)
        assert np.allclose(q, Rotation.from_rotvec(r).as_quat(scalar_first=True), atol=1e-12)
        assert np.allclose(qt.log(q), r, atol=1e-9)
        assert np.allclose(qt.log(-q), r, atol=1e-9)  # the same attitude


def test_attitude_jacobian_by_central_differences():
    rng = np.random.default_rng(3)
    near_pi = qt.exp(np.array([0.0, 0.0, np.pi - 1e-3]))
    for q in (qt.IDENTITY_WXYZ, near_pi, random_unit(rng), random_unit(rng)):
        h = 1e-6
        numeric = np.column_stack([
            (qt.multiply(q, qt.cayley(h * e)) - qt.multiply(q, qt.cayley(-h * e))) / (2 * h) for e in np.eye(3)
        ])
        assert np.allclose(numeric, qt.attitude_jacobian(q), atol=1e-9)


def test_error_state_short_way_and_bad_input():
    q_ref = qt.IDENTITY_WXYZ
    q = qt.exp(np.array([0.0, 0.0, np.deg2rad(200.0)]))  # 200 deg one way is 160 deg the other
    err = qt.error_state(q, np.zeros(3), q_ref, np.zeros(3))
    assert np.isclose(2 * np.arctan(np.linalg.norm(err[:3])), np.deg2rad(160.0))
    with pytest.raises(ValueError, match="normalised"):
        qt.normalize(np.array([np.nan, 0, 0, 0]))


def test_rotation_matrix_written_out_equals_the_matrix_product():
    rng = np.random.default_rng(11)
    for _ in range(50):
        q = rng.normal(size=4) * rng.uniform(0.5, 2.0)     # not unit either: the identity is quadratic in q
        assert np.allclose(qt.rotation_matrix(q), qt.H.T @ qt.left_matrix(q) @ qt.right_matrix(q).T @ qt.H,
                           rtol=0, atol=1e-14 * (q @ q))
