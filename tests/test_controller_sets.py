"""LQR gain, the maximal positively invariant set, the minimal RPI set and the tightening."""
import numpy as np
import pytest

from bench.gnc.lqr import dlqr
from bench.gnc.sets import (Polytope, lqr_max_pi, max_positively_invariant, pontryagin_difference,
                                   remove_redundant_rows, support, vertices)
from bench.gnc.cwh import RendezvousParams, z_subsystem
from bench.gnc.tube import compute_min_rpi, compute_tightening, compute_tube_controller

Q_STAR = np.diag([94.0, 0.1579, 300.0, 0.01, 0.10, 0.10])


@pytest.fixture(scope="module")
def model():
    return RendezvousParams.from_reference().scaled


@pytest.fixture(scope="module")
def x_lqr(model):
    k, _ = dlqr(model.A, model.B, Q_STAR, np.eye(3))
    return k, lqr_max_pi(k, model.A, model.B, model.H_x, model.h_x, model.H_u, model.h_u)


def test_lqr_gain_is_the_limit_of_the_riccati_recursion(model):
    """Independent of the DARE solver: iterate the finite-horizon Riccati recursion to convergence."""
    k, p = dlqr(model.A, model.B, Q_STAR, np.eye(3))
    a, b, r = model.A, model.B, np.eye(3)
    p_k = Q_STAR.copy()
    for _ in range(20000):
        k_k = -np.linalg.solve(r + b.T @ p_k @ b, b.T @ p_k @ a)
        p_next = Q_STAR + a.T @ p_k @ (a + b @ k_k)
        if np.max(np.abs(p_next - p_k)) < 1e-13 * np.max(np.abs(p_k)):
            break
        p_k = p_next
    np.testing.assert_allclose(p, p_k, rtol=1e-8)
    np.testing.assert_allclose(k, k_k, rtol=1e-7, atol=1e-9)
    assert np.max(np.abs(np.linalg.eigvals(a + b @ k))) < 1


def _sample_inside(poly: Polytope, n: int, rng) -> np.ndarray:
    eye = np.eye(poly.dim)
    hi, lo = support(poly, eye), -support(poly, -eye)
    pts = np.empty((0, poly.dim))
    while len(pts) < n:
        draw = rng.uniform(lo, hi, size=(20000, poly.dim))
        pts = np.vstack([pts, draw[poly.contains(draw)]])
    return pts[:n]


def test_max_pi_set_is_invariant_and_keeps_the_constraints(model, x_lqr):
    k, s = x_lqr
    a_cl = model.A + model.B @ k
    rng = np.random.default_rng(0)
    x = _sample_inside(s, 300, rng)
    for _ in range(100):
        assert np.all(x @ model.H_x.T <= model.h_x + 1e-9)
        assert np.all((x @ k.T) @ model.H_u.T <= model.h_u + 1e-9)
        x = x @ a_cl.T
        assert np.all(s.contains(x, tol=1e-9))


def test_points_just_outside_the_max_pi_set_violate_a_constraint_in_closed_loop(model, x_lqr):
    k, s = x_lqr
    a_cl = model.A + model.B @ k
    rng = np.random.default_rng(1)
    for _ in range(50):
        d = rng.normal(size=6)
        rate = s.H @ d
        t = np.min(s.h[rate > 0] / rate[rate > 0])     # the ray from 0 leaves the set at t d
        x = 1.001 * t * d
        violated = False
        for _ in range(200):
            if np.any(model.H_x @ x > model.h_x) or np.any(model.H_u @ (k @ x) > model.h_u):
                violated = True
                break
            x = a_cl @ x
        assert violated


def test_initial_conditions_against_x_lqr(model, x_lqr):
    """Seed task 14: A lies in X_LQR, B and C do not (with the 2022 initial conditions)."""
    params = RendezvousParams.from_reference()
    _, s = x_lqr
    inside = {n: bool(s.contains(model.to_scaled(params.initial_state_m_mps(n)))) for n in "ABC"}
    assert inside == {"A": True, "B": False, "C": False}


def test_redundant_rows_are_removed_and_the_set_is_unchanged():
    box = Polytope(np.vstack([np.eye(2), -np.eye(2), [[1.0, 1.0]], [[2.0, 0.0]]]), np.array([1, 1, 1, 1, 5.0, 2.0]))
    minimal = remove_redundant_rows(box)
    assert minimal.H.shape[0] == 4
    rng = np.random.default_rng(2)
    pts = rng.uniform(-2, 2, size=(2000, 2))
    np.testing.assert_array_equal(box.contains(pts), minimal.contains(pts))


def test_max_pi_of_a_contracting_system_is_finitely_determined():
    a = np.diag([0.5, 0.25])
    s, k = max_positively_invariant(a, Polytope(np.vstack([np.eye(2), -np.eye(2)]), np.ones(4)))
    assert k == 0                                # the box is already invariant
    assert s.H.shape[0] == 4


@pytest.fixture(scope="module")
def tube_design():
    mz = z_subsystem(RendezvousParams.from_reference())
    k = compute_tube_controller([0.05, 0.1], mz)
    tube, n_iter = compute_min_rpi(k, mz)
    return mz, k, tube, n_iter


def test_tube_controller_places_the_poles(tube_design):
    mz, k, _, _ = tube_design
    np.testing.assert_allclose(np.sort(np.linalg.eigvals(mz.A + mz.B @ k).real), [0.05, 0.1], atol=1e-9)


def test_min_rpi_set_is_robustly_invariant_and_contains_w(tube_design):
    mz, k, tube, n_iter = tube_design
    a_cl = mz.A + mz.B @ k
    w_vertices = vertices(Polytope(mz.H_w, mz.h_w))
    assert np.all(tube.contains(w_vertices))
    e_vertices = vertices(tube)
    successors = (e_vertices @ a_cl.T)[:, None, :] + w_vertices[None, :, :]
    # E_i is invariant up to the truncated tail of the series (relative 1e-6 of the facet offsets)
    assert np.all(successors.reshape(-1, 2) @ tube.H.T <= tube.h * (1 + 1e-5))
    assert n_iter >= 2


def test_tightened_constraints_leave_room_for_the_tube(tube_design):
    mz, k, tube, _ = tube_design
    tight = compute_tightening(k, tube, mz)
    assert np.all(tight.h_x < mz.h_x) and np.all(tight.h_u < mz.h_u)
    e_vertices = vertices(tube)
    x_tight_vertices = vertices(Polytope(np.vstack([tight.H_x, [[0, 1.0], [0, -1.0]]]), np.concatenate([tight.h_x, [1, 1]])))
    sums = x_tight_vertices[:, None, :] + e_vertices[None, :, :]
    assert np.all(sums.reshape(-1, 2) @ mz.H_x.T <= mz.h_x + 1e-12)
    u_extremes = (e_vertices @ k.T).ravel()
    assert np.all(np.abs(u_extremes).max() + tight.h_u <= mz.h_u + 1e-12)


def test_pontryagin_difference_of_boxes():
    big = Polytope(np.vstack([np.eye(2), -np.eye(2)]), np.array([3.0, 2.0, 3.0, 2.0]))
    small = Polytope(np.vstack([np.eye(2), -np.eye(2)]), np.array([1.0, 0.5, 1.0, 0.5]))
    np.testing.assert_allclose(pontryagin_difference(big, small).h, [2.0, 1.5, 2.0, 1.5])
