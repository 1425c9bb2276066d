"""The MILQR slew problem transcribed for casadi + IPOPT (a general NLP solver; test/benchmark only).

Single shooting over the same discrete map as `MagnetorquerAttitudeModel.step` (RK4 with the field
held per step and rotated into the body at each stage, then q normalised), the same cost, the same
dipole box. Written with casadi's own algebra, not by calling the planning module, so a
disagreement in the dynamics shows up as a cost mismatch when IPOPT's controls are replayed.
"""
import time

import casadi as ca
import numpy as np

from bench.gnc import quaternion as qt
from bench.gnc.attitude_planning import MagnetorquerAttitudeModel, field_along_orbit_t, gramian_horizon
from bench.gnc.milqr import GeodesicAttitudeCost
from bench.plant.attitude import EARTH_RADIUS_M, CircularOrbit, TiltedDipole

# The 90-degree slew used by tests/test_milqr.py and benchmarks/bench_milqr.py: a 3U-class CubeSat
# at rest, yaw 90 deg, magnetorquers only (0.2 A m^2 per axis, the board's default limit), 500 km /
# 51.6 deg circular orbit, tilted-dipole field, horizon from the Gramian.
INERTIA = np.diag([0.03, 0.04, 0.02])
LIMIT_AM2 = 0.2
ORBIT = CircularOrbit(radius_m=EARTH_RADIUS_M + 500e3)     # 500 km, 51.6 deg
GOAL = qt.exp(np.deg2rad(90.0) * np.array([0.0, 0.0, 1.0]))
X0 = np.array([1.0, 0, 0, 0, 0, 0, 0])
# The second body of the large-slew study (issue 27): an elongated 6U-class body, long axis z,
# about three times the 3U's transverse inertia with the same 0.2 A m^2 torquers.
INERTIA_ELONGATED = np.diag([0.10, 0.12, 0.03])


def slew_cost(goal=GOAL):
    return GeodesicAttitudeCost(goal, np.zeros(3), attitude_weight=0.1, rate_weight=10.0 * np.eye(3),
                                dipole_weight=np.eye(3), final_attitude_weight=1000.0,
                                final_rate_weight=1e7 * np.eye(3))   # ends at rest (1e5 left 3e-4 rad/s)


def slew_problem(dt_s, inertia_kgm2=INERTIA):
    horizon = gramian_horizon(field_along_orbit_t(ORBIT, TiltedDipole(), 0.0, dt_s, int(6000 / dt_s)), dt_s)
    model = MagnetorquerAttitudeModel(inertia_kgm2, field_along_orbit_t(ORBIT, TiltedDipole(), 0.0, dt_s, horizon.steps), dt_s)
    return horizon, model


def _quat_rate(q, w):
    return 0.5 * ca.vertcat(-q[1] * w[0] - q[2] * w[1] - q[3] * w[2],
                            q[0] * w[0] + q[2] * w[2] - q[3] * w[1],
                            q[0] * w[1] - q[1] * w[2] + q[3] * w[0],
                            q[0] * w[2] + q[1] * w[1] - q[2] * w[0])


def _inertial_to_body(q, b):
    # q* (x) [0, b] (x) q, expanded: quadratic in q (no normalisation inside the RK stages)
    s, v = q[0], q[1:4]
    return (s * s - ca.dot(v, v)) * b + 2 * ca.dot(v, b) * v - 2 * s * ca.cross(v, b)


def discrete_step(inertia, dt_s):
    x, u, b = ca.SX.sym("x", 7), ca.SX.sym("u", 3), ca.SX.sym("b", 3)
    J = ca.DM(inertia)
    J_inv = ca.DM(np.linalg.inv(inertia))

    def f(z):
        q, w = z[:4], z[4:]
        tau = ca.cross(u, _inertial_to_body(q, b))
        return ca.vertcat(_quat_rate(q, w), ca.mtimes(J_inv, tau - ca.cross(w, ca.mtimes(J, w))))

    k1 = f(x)
    k2 = f(x + dt_s / 2 * k1)
    k3 = f(x + dt_s / 2 * k2)
    k4 = f(x + dt_s * k3)
    xt = x + dt_s / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return ca.Function("F", [x, u, b], [ca.vertcat(xt[:4] / ca.norm_2(xt[:4]), xt[4:])])


class IpoptSlew:
    """The discretised slew as a casadi NLP for IPOPT, built once and solved from any start.

    Single shooting: the dipoles are the only variables and the states are the step map applied N
    times. (Multiple shooting with free state variables diverged here: the step normalises q, so a
    state's scale along q is free in the constraints while the cost, linear in q near the goal,
    rewards growing it; IPOPT's first step went to |q| ~ 1e4.)
    """

    def __init__(self, model, cost, x0, dipole_limit_am2, max_iter=500, max_cpu_time_s=240.0, print_level=0):
        N, F = model.horizon_steps, discrete_step(model.inertia_kgm2, model.dt_s)
        U = ca.SX.sym("U", 3, N)
        qg, wg = ca.DM(cost.q_goal_wxyz), ca.DM(cost.omega_goal_radps)
        Q, R, Qf = ca.DM(cost.rate_weight), ca.DM(cost.dipole_weight), ca.DM(cost.final_rate_weight)
        x = ca.DM(x0)
        obj = 0
        states = [x]
        for k in range(N):
            dw = x[4:] - wg
            obj += cost.attitude_weight * (1 - ca.fabs(ca.dot(qg, x[:4]))) + 0.5 * ca.bilin(Q, dw, dw) \
                + 0.5 * ca.bilin(R, U[:, k], U[:, k])
            x = F(x, U[:, k], ca.DM(model.field_inertial_t[k]))
            states.append(x)
        dw = x[4:] - wg
        obj += cost.final_attitude_weight * (1 - ca.fabs(ca.dot(qg, x[:4]))) + 0.5 * ca.bilin(Qf, dw, dw)
        self.steps, self.limit_am2 = N, dipole_limit_am2
        self._solver = ca.nlpsol("slew", "ipopt", {"x": ca.vec(U), "f": obj},
                                 {"print_time": False,
                                  "ipopt": {"print_level": print_level, "max_iter": max_iter,
                                            "max_cpu_time": max_cpu_time_s, "tol": 1e-10, "sb": "yes"}})
        self._states = ca.Function("X", [U], [ca.horzcat(*states)])

    def solve(self, dipoles_init_am2=None):
        """(objective, U (N,3), X (N+1,7), ipopt status, wall time, iterations) from the given start
        (zero dipole when None: nothing of MILQR's answer is given to IPOPT)."""
        start = np.zeros((self.steps, 3)) if dipoles_init_am2 is None else np.asarray(dipoles_init_am2, dtype=float)
        t = time.perf_counter()
        # vec() is column-major: U[:, k] contiguous, i.e. the row-major flattening of (N, 3)
        sol = self._solver(x0=start.reshape(-1), lbx=-self.limit_am2, ubx=self.limit_am2)
        wall = time.perf_counter() - t
        u_opt = np.array(sol["x"]).reshape(self.steps, 3)
        X = np.array(self._states(u_opt.T)).T
        stats = self._solver.stats()
        return float(sol["f"]), u_opt, X, stats["return_status"], wall, int(stats.get("iter_count", -1))


def solve_with_ipopt(model, cost, x0, dipole_limit_am2, max_iter=500, max_cpu_time_s=240.0, print_level=0,
                     dipoles_init_am2=None):
    """Returns (objective, U (N,3), X (N+1,7), ipopt status, wall time), started from zero dipole
    unless `dipoles_init_am2` (N, 3) is given."""
    nlp = IpoptSlew(model, cost, x0, dipole_limit_am2, max_iter, max_cpu_time_s, print_level)
    return nlp.solve(dipoles_init_am2)[:5]


def ipopt_best_of_starts(model, cost, x0, dipole_limit_am2, starts, max_iter=3000, max_cpu_time_s=240.0):
    """IPOPT from each named start {name: (N, 3) dipoles}; returns (best, all) where each entry is a
    dict (name, cost, dipoles, status, wall_s, iterations). The cost is the planning model's roll-out of
    IPOPT's dipoles clipped to the box (IPOPT's barrier leaves them a few 1e-8 inside it anyway)."""
    nlp = IpoptSlew(model, cost, x0, dipole_limit_am2, max_iter, max_cpu_time_s)
    runs = []
    for name, U0 in starts.items():
        objective, U, _, status, wall, iterations = nlp.solve(np.clip(U0, -dipole_limit_am2, dipole_limit_am2))
        U = np.clip(U, -dipole_limit_am2, dipole_limit_am2)
        runs.append(dict(name=name, cost=cost.total(model.rollout(x0, U), U), objective=objective, dipoles=U,
                         status=status, wall_s=wall, iterations=iterations))
    return min(runs, key=lambda r: r["cost"]), runs


def slew_goal(angle_deg, seed):
    """A rotation of angle_deg from the identity about a random axis drawn with `seed`."""
    axis = np.random.default_rng(seed).normal(size=3)
    return qt.exp(np.deg2rad(angle_deg) * axis / np.linalg.norm(axis))


def projected_gradient_fd(model, cost, x0, dipoles_am2, dipole_limit_am2, eps=1e-6):
    """First-order optimality of a dipole sequence on the box, by central differences of the rolled-out
    cost (no derivative of MILQR's or IPOPT's is used). Returns the projected gradient (N, 3): the
    gradient where a dipole is inside the box; on a bound, only the part whose descent direction points
    back into the box (at +limit a positive gradient: lowering u would still reduce the cost)."""
    U = np.asarray(dipoles_am2, dtype=float)
    grad = np.zeros_like(U)
    for idx in np.ndindex(U.shape):
        step = np.zeros_like(U)
        step[idx] = eps
        grad[idx] = (cost.total(model.rollout(x0, U + step), U + step)
                     - cost.total(model.rollout(x0, U - step), U - step)) / (2 * eps)
    # an interior-point answer sits a few 1e-8 A m^2 inside its bound: 1e-6 A m^2 counts as on it
    at_upper = U >= dipole_limit_am2 - 1e-6
    at_lower = U <= -dipole_limit_am2 + 1e-6
    projected = grad.copy()
    projected[at_upper] = np.maximum(grad[at_upper], 0.0)   # on +limit only a decrease of u is allowed
    projected[at_lower] = np.minimum(grad[at_lower], 0.0)   # on -limit only an increase
    return projected
