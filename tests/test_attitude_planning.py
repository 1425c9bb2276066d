"""Planning dynamics: Jacobians against central finite differences of the same discrete map."""
import numpy as np
import pytest

from bench.gnc import quaternion as qt
from bench.gnc.attitude_planning import MagnetorquerAttitudeModel, field_along_orbit_t, state_from
from bench.plant.attitude import CircularOrbit, TiltedDipole, rk4_attitude_step

INERTIA = np.diag([0.03, 0.04, 0.02]) + 0.002 * np.array([[0, 1, 0], [1, 0, -1], [0, -1, 0]])


def model(dt_s=10.0, steps=4):
    field = field_along_orbit_t(CircularOrbit(), TiltedDipole(), 100.0, dt_s, steps)
    return MagnetorquerAttitudeModel(INERTIA, field, dt_s)


def random_states(rng):
    """Random attitudes, plus ones within 1e-4 rad of the identity and of a 180-degree rotation."""
    axis = qt.normalize(rng.normal(size=3))
    yield qt.normalize(rng.normal(size=4))
    yield qt.exp(1e-4 * axis)
    yield qt.exp((np.pi - 1e-4) * axis)
    yield qt.exp(np.pi * qt.normalize(rng.normal(size=3)))


def fd_reduced(m, x, u, k, eps=1e-6):
    """Central differences of phi_{k+1}(phi_k, dw_k, u_k) through the Cayley map."""
    x_next = m.step(x, u, k)

    def out(dx, du):
        q = qt.multiply(x[:4], qt.cayley(dx[:3]))
        y = m.step(np.concatenate([q, x[4:] + dx[3:]]), u + du, k)
        return qt.error_state(y[:4], y[4:], x_next[:4], x_next[4:])

    A = np.column_stack([(out(eps * e, 0 * u) - out(-eps * e, 0 * u)) / (2 * eps) for e in np.eye(6)])
    B = np.column_stack([(out(np.zeros(6), eps * e) - out(np.zeros(6), -eps * e)) / (2 * eps) for e in np.eye(3)])
    return A, B


def rel_err(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


def test_reduced_jacobians_match_central_differences():
    rng = np.random.default_rng(10)
    m = model()
    for trial in range(3):
        for q in random_states(rng):
            x = state_from(q, rng.normal(scale=0.02, size=3))
            u = rng.uniform(-0.2, 0.2, size=3)
            k = int(rng.integers(0, m.horizon_steps))
            _, A, B = m.reduced_jacobians(x, u, k)
            A_fd, B_fd = fd_reduced(m, x, u, k)
            assert rel_err(A, A_fd) < 1e-6, (q, rel_err(A, A_fd))
            assert rel_err(B, B_fd) < 1e-6, (q, rel_err(B, B_fd))


def test_full_jacobians_match_central_differences_including_normalisation():
    rng = np.random.default_rng(11)
    m = model()
    eps = 1e-6
    for q in random_states(rng):
        x = state_from(q, rng.normal(scale=0.05, size=3))
        u = rng.uniform(-0.2, 0.2, size=3)
        _, A, B = m.step_jacobians(x, u, 2)
        A_fd = np.column_stack([(m.step(x + eps * e, u, 2) - m.step(x - eps * e, u, 2)) / (2 * eps) for e in np.eye(7)])
        B_fd = np.column_stack([(m.step(x, u + eps * e, 2) - m.step(x, u - eps * e, 2)) / (2 * eps) for e in np.eye(3)])
        assert rel_err(A, A_fd) < 1e-6
        assert rel_err(B, B_fd) < 1e-6


def test_step_with_zero_dipole_equals_the_truth_model_rk4():
    """With zero dipole both integrators are the same RK4 on the torque-free body."""
    rng = np.random.default_rng(12)
    m = model(dt_s=0.5)
    q, w = qt.normalize(rng.normal(size=4)), rng.normal(scale=0.1, size=3)
    x_next = m.step(np.concatenate([q, w]), np.zeros(3), 0)
    q_ref, w_ref = rk4_attitude_step(q, w, np.zeros(3), INERTIA, 0.5)
    np.testing.assert_allclose(x_next, np.concatenate([q_ref, w_ref]), atol=1e-14)


def test_magnetorquer_torque_is_m_cross_body_field():
    rng = np.random.default_rng(13)
    m = model()
    q = qt.normalize(rng.normal(size=4))
    u = rng.normal(size=3)
    xdot = m.derivative(np.concatenate([q, np.zeros(3)]), u, m.field_inertial_t[0])
    b_body = qt.rotation_matrix(q).T @ m.field_inertial_t[0]
    np.testing.assert_allclose(INERTIA @ xdot[4:], np.cross(u, b_body), rtol=1e-12)


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="inertia_kgm2"):
        MagnetorquerAttitudeModel(-np.eye(3), np.zeros((2, 3)), 1.0)
    with pytest.raises(ValueError, match="field_inertial_t"):
        MagnetorquerAttitudeModel(np.eye(3), np.full((2, 3), np.nan), 1.0)
    with pytest.raises(ValueError, match="dt_s"):
        MagnetorquerAttitudeModel(np.eye(3), np.zeros((2, 3)), 0.0)


def test_whole_horizon_linearisation_equals_step_by_step():
    rng = np.random.default_rng(14)
    m = model(steps=6)
    X = np.array([state_from(rng.normal(size=4), rng.normal(scale=0.02, size=3)) for _ in range(7)])
    U = rng.uniform(-0.2, 0.2, size=(6, 3))
    A, B = m.linearise(X, U)
    for k in range(6):
        _, A_k, B_k = m.reduced_jacobians(X[k], U[k], k)
        np.testing.assert_allclose(A[k], A_k, rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(B[k], B_k, rtol=1e-13, atol=1e-18)
    from bench.gnc.attitude_planning import _state_error_jacobian, body_vector
    np.testing.assert_allclose(_state_error_jacobian(X[0]), qt.state_error_jacobian(X[0][:4]), atol=1e-15)
    b = rng.normal(size=3)
    np.testing.assert_allclose(body_vector(X[1][:4], b), qt.rotation_matrix(X[1][:4]).T @ b, atol=1e-14)


def test_one_state_and_stacked_derivative_agree():
    rng = np.random.default_rng(15)
    m = model()
    X = rng.normal(size=(5, 7))          # off the unit sphere too, as inside the RK stages
    U, F = rng.normal(size=(5, 3)), m.field_inertial_t[rng.integers(0, 4, 5)]
    stacked = m.derivative(X, U, F)
    for i in range(5):
        np.testing.assert_allclose(m.derivative(X[i], U[i], F[i]), stacked[i], rtol=1e-13, atol=1e-20)
