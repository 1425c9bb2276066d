"""Projected-Newton box QP against proxsuite (an independent interior/ALM QP solver)."""
import numpy as np
import proxsuite
import pytest

from bench.gnc.boxqp import objective, solve_box_qp


def proxsuite_box_qp(H, g, lower, upper):
    n = len(g)
    qp = proxsuite.proxqp.dense.QP(n, 0, n)
    qp.settings.eps_abs = 1e-13
    qp.settings.eps_rel = 0.0
    qp.settings.max_iter = 100000
    qp.settings.verbose = False
    qp.init(H, g, None, None, np.eye(n), lower, upper)
    qp.solve()
    return qp.results.x


def random_problem(rng, n, all_active=False):
    M = rng.normal(size=(n, n))
    H = M @ M.T + 0.1 * np.eye(n)
    lower = -rng.uniform(0.1, 1.0, n)
    upper = rng.uniform(0.1, 1.0, n)
    g = rng.normal(scale=3.0, size=n)
    if all_active:
        # unconstrained optimum far outside the box in every coordinate, and H diagonal dominated
        H = np.diag(rng.uniform(1.0, 2.0, n)) + 0.01 * (M @ M.T) / n
        g = rng.choice([-1.0, 1.0], n) * 100.0
    return H, g, lower, upper


@pytest.mark.parametrize("n", [3, 4, 6, 9, 15, 22, 30])
def test_matches_proxsuite_on_random_box_qps(n):
    rng = np.random.default_rng(100 + n)
    for trial in range(6):
        H, g, lower, upper = random_problem(rng, n, all_active=(trial == 0))
        ref = proxsuite_box_qp(H, g, lower, upper)
        warm = rng.uniform(lower, upper) if trial % 2 else None
        res = solve_box_qp(H, g, lower, upper, warm)
        assert res.ok, res.status
        np.testing.assert_allclose(res.x, ref, atol=1e-8)
        assert abs(objective(H, g, res.x) - objective(H, g, ref)) <= 1e-8 * (1 + abs(objective(H, g, ref)))
        if trial == 0:
            assert res.clamped.all() and res.status == "all_clamped"
        # the clamped set is the active set the solution sits on
        on_bound = np.isclose(res.x, lower, atol=0) | np.isclose(res.x, upper, atol=0)
        assert np.all(on_bound[res.clamped])


def test_interior_optimum_is_the_newton_step_and_warm_start_at_it_stops_at_once():
    rng = np.random.default_rng(7)
    H, g, _, _ = random_problem(rng, 5)
    x_star = -np.linalg.solve(H, g)
    lower, upper = x_star - 1.0, x_star + 1.0
    res = solve_box_qp(H, g, lower, upper)
    np.testing.assert_allclose(res.x, x_star, rtol=1e-12)
    assert not res.clamped.any()
    assert solve_box_qp(H, g, lower, upper, x_star).iterations == 1


def test_indefinite_hessian_and_bad_box_are_reported():
    H = np.diag([1.0, -1.0])
    assert solve_box_qp(H, np.array([0.1, 0.1]), -np.ones(2), np.ones(2)).status == "not_positive_definite"
    with pytest.raises(ValueError, match="lower > upper"):
        solve_box_qp(np.eye(2), np.zeros(2), np.ones(2), np.zeros(2))
