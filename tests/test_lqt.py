"""LQT (bench/gnc/lqt.py): reduces to LQR, and matches the same problem solved as one dense
least-squares problem (numpy lstsq over the stacked inputs), on models the other tests do not use."""
import numpy as np
import pytest
from scipy.linalg import solve_discrete_are

from bench.gnc.lqt import TrackingLQT, glide_slope_reference, lqt_gains


def _random_system(rng, n_x=4, n_u=2):
    a = np.eye(n_x) + 0.1 * rng.standard_normal((n_x, n_x))
    b = rng.standard_normal((n_x, n_u))
    q = np.diag(rng.uniform(0.5, 2.0, n_x))
    r = np.diag(rng.uniform(0.5, 2.0, n_u))
    return a, b, q, r


def _dlqr(a, b, q, r):
    p = solve_discrete_are(a, b, q, r)
    return -np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a), p


def test_zero_reference_with_dare_terminal_cost_is_the_lqr_at_every_step():
    rng = np.random.default_rng(21)
    a, b, q, r = _random_system(rng)
    k_lqr, p = _dlqr(a, b, q, r)
    gains = lqt_gains(a, b, q, r, p, np.zeros((41, 4)))
    for k in range(40):
        np.testing.assert_allclose(gains.K[k], k_lqr, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(gains.P[k], p, rtol=1e-8, atol=1e-10)
    assert np.all(gains.d == 0) and np.all(gains.s == 0)


def test_zero_reference_long_horizon_converges_to_lqr_from_any_terminal_weight():
    rng = np.random.default_rng(22)
    a, b, q, r = _random_system(rng)
    k_lqr, _ = _dlqr(a, b, q, r)
    gains = lqt_gains(a, b, q, r, q, np.zeros((301, 4)))       # Q_f = Q, not the DARE solution
    np.testing.assert_allclose(gains.K[0], k_lqr, rtol=1e-6, atol=1e-9)
    assert not np.allclose(gains.K[-1], k_lqr, rtol=1e-3)


def _dense_tracking_solution(a_seq, b_seq, q, r, q_f, reference, x0):
    """Inputs minimising the tracking cost, as one least-squares problem over u_0 .. u_{N-1}."""
    n_steps, n_x, n_u = len(a_seq), q.shape[0], r.shape[0]
    # x_k = Phi_k x0 + Gamma_k u (stacked); build by forward substitution.
    phi = [np.eye(n_x)]
    gamma = [np.zeros((n_x, n_steps * n_u))]
    for k in range(n_steps):
        phi.append(a_seq[k] @ phi[-1])
        g = a_seq[k] @ gamma[-1]
        g[:, k * n_u:(k + 1) * n_u] += b_seq[k]
        gamma.append(g)
    rows, rhs = [], []
    for k in range(n_steps + 1):
        w = np.linalg.cholesky(q_f if k == n_steps else q).T        # ||W (x_k - r_k)||^2
        rows.append(w @ gamma[k])
        rhs.append(w @ (reference[k] - phi[k] @ x0))
    for k in range(n_steps):
        row = np.zeros((n_u, n_steps * n_u))
        row[:, k * n_u:(k + 1) * n_u] = np.linalg.cholesky(r).T
        rows.append(row)
        rhs.append(np.zeros(n_u))
    u, *_ = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)
    return u.reshape(n_steps, n_u)


def test_matches_dense_least_squares_on_a_time_varying_system_with_a_reference():
    rng = np.random.default_rng(23)
    n_steps = 25
    _, _, q, r = _random_system(rng, 5, 2)
    a_seq = np.array([np.eye(5) + 0.15 * rng.standard_normal((5, 5)) for _ in range(n_steps)])
    b_seq = rng.standard_normal((n_steps, 5, 2))
    q_f = 3.0 * np.eye(5)
    reference = np.cumsum(rng.standard_normal((n_steps + 1, 5)), axis=0)
    x0 = rng.standard_normal(5)
    gains = lqt_gains(a_seq, b_seq, q, r, q_f, reference)
    x, u_recursion = x0, []
    for k in range(n_steps):
        u = gains.K[k] @ x + gains.d[k]
        u_recursion.append(u)
        x = a_seq[k] @ x + b_seq[k] @ u
    np.testing.assert_allclose(np.array(u_recursion), _dense_tracking_solution(a_seq, b_seq, q, r, q_f, reference, x0),
                               rtol=1e-7, atol=1e-8)


def test_glide_slope_reference_starts_at_x0_position_and_ends_at_the_target():
    x0 = np.array([-0.015, -0.4, 0.0244, 0.0, 0.0081, 0.0])
    ref = glide_slope_reference(x0, 288, 100)
    np.testing.assert_allclose(ref[0, :3], x0[:3])
    assert np.all(ref[100:] == 0)
    # velocity is the per-step derivative of the position profile (central differences)
    np.testing.assert_allclose(ref[1:99, 3:], (ref[2:100, :3] - ref[0:98, :3]) / 2, rtol=1e-9, atol=1e-12)


def test_tracking_lqt_keeps_its_clock_and_plan_across_a_model_update():
    rng = np.random.default_rng(24)
    a, b, q, r = _random_system(rng, 4, 2)
    _, p = _dlqr(a, b, q, r)
    law = TrackingLQT(q, r, p, a, b, horizon=30, glide_fraction=0.5, velocity_per_step=1.0)
    x = np.array([1.0, -2.0, 0.0, 0.0])
    for _ in range(5):
        law.eval(x)
    updated = TrackingLQT(q, r, p, 1.01 * a, b, horizon=30, glide_fraction=0.5, velocity_per_step=1.0)
    updated.continue_from(law)
    assert updated.step == 5 and updated.reference is law.reference
    expected = lqt_gains(1.01 * a, b, q, r, p, law.reference[5:])
    u, _ = updated.eval(x)
    np.testing.assert_allclose(u, expected.K[0] @ x + expected.d[0])


def test_bad_input_named():
    with pytest.raises(ValueError, match="reference"):
        lqt_gains(np.eye(2), np.ones((2, 1)), np.eye(2), np.eye(1), np.eye(2), np.zeros((1, 2)))
    with pytest.raises(ValueError, match="B must be"):
        lqt_gains(np.eye(2), np.ones((3, 1)), np.eye(2), np.eye(1), np.eye(2), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="glide_fraction"):
        TrackingLQT(np.eye(2), np.eye(1), np.eye(2), np.eye(2), np.ones((2, 1)), 10, 0.0, 1.0)
