"""Bad input is named, and the seed's metric and tuning functions do what the seed says."""
import numpy as np
import pytest

from bench.config.controller import ControllerConfig
from bench.controller.factory import build_controller
from bench.gnc.cwh import RendezvousParams, z_subsystem
from bench.gnc.lqr import LQR
from bench.gnc.mpc import MPC, MPC_TS_SC
from bench.gnc.sets import Polytope
from bench.gnc.tube import compute_tube_controller
from bench.studies.metrics import traj_constraints, traj_cost
from bench.studies.simulate import simulate
from bench.studies.tuning import lqr_tuning

Q_STAR = np.diag([94.0, 0.1579, 300.0, 0.01, 0.10, 0.10])


@pytest.fixture(scope="module")
def params():
    return RendezvousParams.from_reference()


@pytest.mark.parametrize("q, r, horizon, match", [
    (np.ones((6, 5)), np.eye(3), 30, "Q must be 6x6"),
    (Q_STAR, -np.eye(3), 30, "R must be positive definite"),
    (np.diag([1, 1, 1, 1, 1, 0.0]), np.eye(3), 30, "Q must be positive definite"),
    (Q_STAR, np.eye(3), 0, "horizon must be an integer >= 1"),
    (Q_STAR, np.eye(3), 2.5, "horizon must be an integer >= 1"),
])
def test_bad_weights_and_horizon_are_named(params, q, r, horizon, match):
    with pytest.raises(ValueError, match=match):
        MPC(q, r, horizon, params.scaled)


def test_inconsistent_model_dimensions_are_named(params):
    import dataclasses

    bad = dataclasses.replace(params.scaled, H_x=params.scaled.H_x[:, :5])
    with pytest.raises(ValueError, match="inconsistent model dimensions"):
        MPC(Q_STAR, np.eye(3), 30, bad)


def test_bad_soft_penalty_and_terminal_set_are_named(params):
    m = params.scaled
    box = Polytope(np.vstack([np.eye(6), -np.eye(6)]), np.ones(12))
    with pytest.raises(ValueError, match="S must be 6x6"):
        MPC_TS_SC(Q_STAR, np.eye(3), 30, box, np.eye(3), 1e5, m)
    with pytest.raises(ValueError, match="v must be"):
        MPC_TS_SC(Q_STAR, np.eye(3), 30, box, np.eye(6), float("nan"), m)
    with pytest.raises(ValueError, match="terminal set has 2 columns"):
        MPC_TS_SC(Q_STAR, np.eye(3), 30, Polytope(np.eye(2), np.ones(2)), np.eye(6), 1.0, m)


def test_eval_names_a_wrong_state_size_and_survives_a_non_finite_state(params):
    ctrl = MPC(Q_STAR, np.eye(3), 10, params.scaled)
    with pytest.raises(ValueError, match="state must have 6 entries"):
        ctrl.eval(np.zeros(5))
    u, info = ctrl.eval(np.full(6, np.nan))
    assert not info["ctrl_feas"] and info["status"] == "NON_FINITE_STATE" and np.all(u == 0)


def test_unstable_tube_poles_are_refused(params):
    with pytest.raises(ValueError, match="inside the unit circle"):
        compute_tube_controller([0.5, 1.2], z_subsystem(params))


def test_factory_builds_every_controller_type(params):
    x = params.scaled.to_scaled(params.initial_state_m_mps("A"))
    for kind in ["lqr", "mpc", "mpc_te", "mpc_ts", "mpc_ts_sc", "mpc_tube"]:
        u, info = build_controller(ControllerConfig(type=kind, horizon=30), params).eval(x)
        assert u.shape == (3,) and set(info) >= {"ctrl_feas", "objective", "solve_time", "iterations", "status"}
        assert info["ctrl_feas"], (kind, info["status"])
        assert np.all(np.abs(u) <= 1 + 1e-6)
        if kind != "lqr":            # every MPC returns its plan, for the shifted-plan fallback
            assert info["u_plan"].shape == (30, 3) and np.array_equal(info["u_plan"][0], u), kind


def test_traj_constraints_on_a_hand_made_trajectory(params):
    X = np.zeros((6, 3))
    X[:, 0] = [50e3, -200e3, -120e3, 0, 0, 0]          # m, m/s; z beyond s_max = 100 km
    X[:, 2] = [30.0, 40.0, 0.0, 0.0, 0.3, 0.4]
    U = np.array([[0.5, -0.2], [0.0, 0.9], [0.1, 0.0]])
    m = traj_constraints(X * np.asarray(params.scaling)[:, None], U, params)
    assert m.max_abs_position_xz_m == pytest.approx(120e3)
    assert m.max_abs_position_y_m == pytest.approx(200e3)
    assert m.max_abs_thrust_n == pytest.approx(0.9)
    assert m.input_cost_n2 == pytest.approx(0.25 + 0.04 + 0.81 + 0.01)
    assert m.final_distance_m == pytest.approx(50.0)
    assert m.final_speed_mps == pytest.approx(0.5)
    assert not m.feasible
    X[2, 0] = -90e3
    assert traj_constraints(X * np.asarray(params.scaling)[:, None], U, params).feasible


def test_traj_cost_is_the_running_quadratic_cost(params):
    m = params.scaled
    X, U, _ = simulate(m.to_scaled(params.initial_state_m_mps("A")), LQR(Q_STAR, np.eye(3), m.A, m.B), m, 10)
    expected = sum(X[:, k] @ Q_STAR @ X[:, k] + U[:, k] @ U[:, k] for k in range(10))
    assert traj_cost(X, U, Q_STAR, np.eye(3)) == pytest.approx(expected, rel=1e-12)


def test_simulate_applies_inputs_unsaturated(params):
    m = params.scaled
    ctrl = LQR(Q_STAR * 100, np.eye(3), m.A, m.B)        # aggressive: asks for more than 1 N
    X, U, infos = simulate(m.to_scaled(params.initial_state_m_mps("B")), ctrl, m, 5)
    assert np.abs(U).max() > 1
    np.testing.assert_allclose(X[:, 1], m.A @ X[:, 0] + m.B @ U[:, 0])
    assert len(infos) == 5 and X.shape == (6, 6)


def test_lqr_tuning_picks_the_cheapest_feasible_q(params):
    x0 = params.scaled.to_scaled(params.initial_state_m_mps("A"))
    qs = np.array([
        [94.0, 0.1579, 300.0, 0.01, 0.10, 0.10],      # Q*: ends ~170 m out, infeasible at 100 m
        [94.0, 0.1579, 500.0, 0.01, 0.10, 0.01],      # the default scenario's q
        [940.0, 1.579, 5000.0, 0.1, 1.0, 0.1],        # stiffer: feasible? it pays more fuel
        [1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3],         # too soft to arrive
    ])
    rows, best = lqr_tuning(x0, qs, params)
    assert len(rows) == 4
    assert not rows[0].metrics.feasible and not rows[3].metrics.feasible
    feasible = [i for i, r in enumerate(rows) if r.metrics.feasible]
    assert best == min(feasible, key=lambda i: rows[i].metrics.input_cost_n2)
    _, none = lqr_tuning(x0, qs[[0, 3]], params)
    assert none is None
    with pytest.raises(ValueError, match="6 weights"):
        lqr_tuning(x0, np.ones((2, 5)), params)


def test_tuning_survives_a_dare_failure_at_one_candidate(params, monkeypatch):
    """Issue 17: a q whose DARE fails is an infeasible row, not the end of the study."""
    import bench.studies.tuning as tuning

    real = tuning.lqr_trajectory
    bad_q = np.array([94.0, 0.1579, 500.0, 0.01, 0.10, 0.01])
    failing_qs = [bad_q]

    def failing(x0, q, p):
        if any(np.allclose(q, b) for b in failing_qs):
            raise np.linalg.LinAlgError("Failed to find a finite solution.")
        return real(x0, q, p)

    monkeypatch.setattr(tuning, "lqr_trajectory", failing)
    x0 = params.scaled.to_scaled(params.initial_state_m_mps("A"))
    tuned = [108.55, 0.0887937, 372.281, 0.000133352, 0.00133352, 0.00133352]     # feasible from A
    rows, best = tuning.lqr_tuning(x0, np.array([bad_q, tuned]), params)
    assert not rows[0].metrics.feasible and rows[0].metrics.input_cost_n2 == np.inf
    assert best == 1
    failing_qs.append(np.array(tuned))         # the centre of refine_q's out-of-plane grid
    q, j_u = tuning.refine_q(x0, tuned, params, rounds=1, points_in_plane=3, points_out_of_plane=3, span_decades=0.02)
    assert np.isfinite(j_u)
