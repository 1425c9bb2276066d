"""TVLQR against scipy: the DARE gain far from the horizon's end, and cont2discrete for the hold."""
import numpy as np
import pytest
from scipy.linalg import solve_discrete_are
from scipy.signal import cont2discrete

from bench.gnc.tvlqr import bryson_weights, tracking_control, tvlqr_gains, zero_order_hold


def test_lti_gain_far_from_the_end_is_the_dare_gain():
    rng = np.random.default_rng(20)
    n, m, steps = 5, 2, 400
    A = rng.normal(size=(n, n)) * 0.4 + np.eye(n) * 0.8     # open-loop unstable draws are fine
    B = rng.normal(size=(n, m))
    Q, R = np.diag(rng.uniform(0.5, 2.0, n)), np.diag(rng.uniform(0.1, 1.0, m))
    K, S = tvlqr_gains(np.repeat(A[None], steps, 0), np.repeat(B[None], steps, 0), Q, R, np.zeros((n, n)))
    P = solve_discrete_are(A, B, Q, R)
    K_dare = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
    np.testing.assert_allclose(K[0], K_dare, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(S[0], P, rtol=1e-9)
    # ...and not at the end, where the terminal weight (zero here) rules: the test can fail.
    assert np.abs(K[-1]).max() < 1e-12 and np.abs(K_dare).max() > 1e-3


def test_time_varying_gains_match_brute_force_least_squares():
    """Two-step problem solved as one stacked least squares: u0 = -K0 x0 exactly."""
    rng = np.random.default_rng(21)
    n, m = 3, 1
    A, B = rng.normal(size=(2, n, n)), rng.normal(size=(2, n, m))
    Q, R, QN = np.eye(n), 0.3 * np.eye(m), 2.0 * np.eye(n)
    K, _ = tvlqr_gains(A, B, Q, R, QN)
    x0 = rng.normal(size=n)
    # x1 = A0 x0 + B0 u0, x2 = A1 x1 + B1 u1; minimise |u0|_R + |x1|_Q + |u1|_R + |x2|_QN over (u0, u1)
    M1 = np.hstack([B[0], np.zeros((n, m))])
    M2 = np.hstack([A[1] @ B[0], B[1]])
    rows = [np.sqrt(0.3) * np.eye(2 * m), M1, np.sqrt(2.0) * M2]
    rhs = [np.zeros(2 * m), -A[0] @ x0, -np.sqrt(2.0) * A[1] @ A[0] @ x0]
    u = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
    np.testing.assert_allclose(u[:m], -K[0] @ x0, rtol=1e-10)


def test_zero_order_hold_matches_scipy_and_handles_singular_a():
    rng = np.random.default_rng(22)
    A, B = rng.normal(size=(4, 4)), rng.normal(size=(4, 2))
    Ad, Bd = zero_order_hold(A, B, 0.3)
    Ad_ref, Bd_ref, *_ = cont2discrete((A, B, np.eye(4), np.zeros((4, 2))), 0.3, method="zoh")
    np.testing.assert_allclose(Ad, Ad_ref, rtol=1e-12)
    np.testing.assert_allclose(Bd, Bd_ref, rtol=1e-12)
    # double integrator: A singular, B_d = [dt^2/2, dt] in closed form
    Ad, Bd = zero_order_hold(np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [1.0]]), 2.0)
    np.testing.assert_allclose(Bd.ravel(), [2.0, 2.0], rtol=1e-14)
    np.testing.assert_allclose(Ad, [[1.0, 2.0], [0.0, 1.0]], rtol=1e-14)


def test_bryson_and_tracking_law():
    Q, R = bryson_weights([0.1, 2.0], [0.5])
    np.testing.assert_allclose(np.diag(Q), [100.0, 0.25])
    np.testing.assert_allclose(np.diag(R), [4.0])
    np.testing.assert_allclose(tracking_control(np.array([1.0]), np.array([[2.0, 3.0]]), np.array([0.5, -1.0])), [3.0])
    with pytest.raises(ValueError, match="max_control"):
        bryson_weights([1.0], [0.0])
    with pytest.raises(ValueError, match="A must be"):
        tvlqr_gains(np.zeros((2, 3, 3)), np.zeros((3, 3, 1)), np.eye(3), np.eye(1), np.eye(3))
