"""MILQR: cost derivatives by finite differences, a 90-degree magnetorquer slew within the Gramian
horizon, the same discretised problem solved by IPOPT (casadi), and the stopping rules."""
import numpy as np
import pytest

from bench.gnc import quaternion as qt
from bench.gnc.milqr import GeodesicAttitudeCost, MilqrOptions, _backward_pass, milqr
from tests.milqr_reference import GOAL, LIMIT_AM2, X0, slew_cost, slew_problem

@pytest.fixture(scope="module")
def slew():
    # 60 s steps keep IPOPT's single-shooting problem small enough for a test (the benchmark uses 20 s)
    horizon, model = slew_problem(60.0)
    result = milqr(model, slew_cost(), X0, np.zeros((model.horizon_steps, 3)), -LIMIT_AM2, LIMIT_AM2)
    return horizon, model, result


def test_geodesic_cost_gradient_and_hessian_match_finite_differences():
    rng = np.random.default_rng(30)
    goal = qt.normalize(rng.normal(size=4))
    cost = slew_cost(goal)
    eps = 1e-5
    # near the goal, far from it, and on the far hemisphere (q_g'q < 0: the sign handling)
    for q in (qt.multiply(goal, qt.exp([0.01, -0.02, 0.005])), qt.normalize(rng.normal(size=4)),
              -qt.multiply(goal, qt.exp([0.3, 0.2, -0.1]))):
        x = np.concatenate([q, rng.normal(scale=0.01, size=3)])
        u = rng.normal(scale=0.1, size=3)
        lx, lu, lxx, luu = cost.stage_expansion(x, u)

        def perturbed(dx):
            return np.concatenate([qt.multiply(q, qt.cayley(dx[:3])), x[4:] + dx[3:]])

        grad_fd = np.array([(cost.stage(perturbed(eps * e), u) - cost.stage(perturbed(-eps * e), u)) / (2 * eps)
                            for e in np.eye(6)])
        np.testing.assert_allclose(lx, grad_fd, rtol=1e-6, atol=1e-9)
        h = 1e-4
        hess_fd = np.array([[(cost.stage(perturbed(h * (a + b)), u) - cost.stage(perturbed(h * (a - b)), u)
                              - cost.stage(perturbed(h * (b - a)), u) + cost.stage(perturbed(-h * (a + b)), u)) / (4 * h * h)
                             for b in np.eye(6)] for a in np.eye(6)])
        np.testing.assert_allclose(lxx, hess_fd, rtol=1e-5, atol=1e-6)
        assert np.all(np.linalg.eigvalsh(lxx) > 0)


def test_slew_converges_within_the_gramian_horizon(slew):
    horizon, model, result = slew
    assert horizon.reached and horizon.condition_number <= 3.0
    assert 15 * 60 <= horizon.horizon_s <= 45 * 60
    assert result.info["converged"], result.info["stop_reason"]
    assert qt.angle_between_rad(result.states[-1, :4], GOAL) < np.deg2rad(0.5)
    assert np.linalg.norm(result.states[-1, 4:]) < 1e-3
    assert np.all(np.abs(result.dipoles_am2) <= LIMIT_AM2)
    assert np.all(np.diff(result.info["cost_history"]) < 0)           # only improving steps accepted
    # the returned trajectory is a roll-out of the returned dipoles
    np.testing.assert_allclose(model.rollout(X0, result.dipoles_am2), result.states, atol=1e-12)


# At the board's limit it is a study (16 s of IPOPT); the saturated case runs in every test run.
@pytest.mark.parametrize("limit_am2", [pytest.param(LIMIT_AM2, marks=pytest.mark.study), 0.03])
def test_ipopt_on_the_same_discretised_problem_reaches_the_same_cost(slew, limit_am2):
    """At the board's 0.2 A m^2 no dipole saturates; at 0.03 A m^2 about a fifth of the samples sit on
    the box, so the box-QP path is compared too."""
    from tests.milqr_reference import projected_gradient_fd, solve_with_ipopt
    _, model, result = slew
    cost = slew_cost()
    if limit_am2 != LIMIT_AM2:
        result = milqr(model, cost, X0, np.zeros((model.horizon_steps, 3)), -limit_am2, limit_am2)
        assert result.info["converged"] and np.mean(np.isclose(np.abs(result.dipoles_am2), limit_am2)) > 0.1
    objective, dipoles, _, status, _ = solve_with_ipopt(model, cost, X0, limit_am2, max_iter=3000, max_cpu_time_s=240.0)
    # IPOPT's own status is not the judge: releases differ on whether the same point is "succeeded" or
    # "solved to acceptable level" (casadi 3.8.2 says the latter here). Its answer is checked instead:
    # feasible on the box, the same objective when replayed through the planning model (same
    # problem), and stationary by finite differences on that model, the same test MILQR's answer passes.
    assert np.all(np.abs(dipoles) <= limit_am2 + 1e-8), status
    assert cost.total(model.rollout(X0, dipoles), dipoles) == pytest.approx(objective, rel=1e-8), status
    # stationary: the projected gradient six orders below the one at the zero-dipole start (2.7e4;
    # measured 5e-5 at 0.2 A m^2 and 1.9e-3 at 0.03 A m^2, where IPOPT's barrier keeps its dipoles
    # a few 1e-8 inside the box)
    start = np.max(np.abs(projected_gradient_fd(model, cost, X0, np.zeros_like(dipoles), limit_am2)))
    for name, U in (("IPOPT", dipoles), ("MILQR", result.dipoles_am2)):
        stationarity = np.max(np.abs(projected_gradient_fd(model, cost, X0, U, limit_am2)))
        assert stationarity <= 1e-6 * start, f"{name} ({status=}): projected gradient {stationarity:.2e}"
    assert abs(objective - result.cost) <= 0.01 * result.cost, status


def test_caps_return_the_best_iterate_and_say_why():
    _, model = slew_problem(120.0)
    cost = slew_cost()
    U0 = np.zeros((model.horizon_steps, 3))
    initial = cost.total(model.rollout(X0, U0), U0)
    capped = milqr(model, cost, X0, U0, -LIMIT_AM2, LIMIT_AM2, MilqrOptions(max_iterations=2))
    assert capped.info["stop_reason"] == "max_iterations" and not capped.info["converged"]
    assert capped.cost < initial
    assert capped.cost == pytest.approx(cost.total(capped.states, capped.dipoles_am2))
    timed = milqr(model, cost, X0, U0, -LIMIT_AM2, LIMIT_AM2, MilqrOptions(max_wall_time_s=0.0))
    assert timed.info["stop_reason"] == "wall_time" and timed.info["iterations"] == 0
    assert timed.cost == pytest.approx(initial)


def test_clamped_controls_get_zero_feedback_rows():
    _, model = slew_problem(120.0)
    cost = slew_cost()
    N = model.horizon_steps
    limit = 1e-3                                    # tight box: the unconstrained step leaves it
    U = np.full((N, 3), limit)
    X = model.rollout(X0, U)
    A, B = zip(*[model.reduced_jacobians(X[k], U[k], k)[1:] for k in range(N)])
    l, K, dV, failed = _backward_pass(cost, X, U, np.array(A), np.array(B), -limit, limit, 0.0, np.zeros((N, 3)))
    assert failed is None and dV[0] < 0
    at_bound = np.isclose(np.abs(U + l), limit)
    zero_rows = np.all(K == 0.0, axis=2)
    assert zero_rows.any()
    assert np.all(at_bound[zero_rows])              # a zeroed row is always a control on its bound


def test_bad_inputs_are_named():
    _, model = slew_problem(120.0)
    with pytest.raises(ValueError, match="x0"):
        milqr(model, slew_cost(), np.full(7, np.nan), np.zeros((model.horizon_steps, 3)), -1, 1)
    with pytest.raises(ValueError, match="dipoles_init_am2"):
        milqr(model, slew_cost(), X0, np.zeros((3, 3)), -1, 1)
    with pytest.raises(ValueError, match="dipole_weight"):
        GeodesicAttitudeCost(GOAL, np.zeros(3), 1.0, np.eye(3), np.zeros((3, 3)), 1.0, np.eye(3))


def test_trajectory_cost_is_the_sum_of_stage_costs():
    rng = np.random.default_rng(31)
    cost = slew_cost(qt.normalize(rng.normal(size=4)))
    X = np.concatenate([np.array([qt.normalize(rng.normal(size=4)) for _ in range(6)]), rng.normal(size=(6, 3))], axis=1)
    U = rng.normal(size=(5, 3))
    assert cost.total(X, U) == pytest.approx(sum(cost.stage(x, u) for x, u in zip(X[:-1], U)) + cost.final(X[-1]), rel=1e-13)
