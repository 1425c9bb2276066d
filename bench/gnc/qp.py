"""A parametric dense QP on proxsuite: matrices fixed at construction, vectors updated per solve.

    min_y 1/2 y'Hy + g'y   s.t.  A y = b,  l <= C y <= u,  l_box <= y <= u_box

proxsuite 0.8.0 behaviour this wrapper works around (measured on the CWH MPC):
- `init` then `update` then `solve` with WARM_START_WITH_PREVIOUS_RESULT can segfault unless
  `solve()` runs once right after `init()`: the constructor does that solve.
- with box constraints, explicit x/z warm starts passed to `solve` misbehave: none are passed.
- every solve is preceded by `update()` of the vectors that changed.
- any status other than PROXQP_SOLVED is a failed solve, confirmed by a cold solve from a fresh
  `init`, and the next cycle starts from that fresh state: warm-started from an infeasible problem's iterate, proxsuite ran 1.6 million inner
  iterations (54 s) on the next, feasible-looking cycle despite max_iter.
- Ruiz preconditioning together with warm starts returned "solved" points whose first input was
  5e-4 N off the optimum (residuals met, complementarity not); the seed's scaling V already
  conditions this problem, so the preconditioner is off.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import proxsuite
from scipy.optimize import linprog

from bench.gnc.kkt import ActiveSet, ActiveSetQP

SOLVED = proxsuite.proxqp.QPSolverOutput.PROXQP_SOLVED
CONFIRM_COLD = (proxsuite.proxqp.QPSolverOutput.PROXQP_PRIMAL_INFEASIBLE,
                proxsuite.proxqp.QPSolverOutput.PROXQP_DUAL_INFEASIBLE)

# Tolerance on the primal and dual residuals (scaled problem, eps_rel = 0). The first input must
# match an independent solver to 1e-5 N: at 1e-7 it was up to 9e-5 N off, at 1e-9 within 1e-6 N.
DEFAULT_EPS_ABS = 1e-9
# Warm-started cycles take 1 to 20 iterations; infeasibility is detected within ~30 from a fresh
# init. These limits do not bound the wall time: on the nonlinear plant a failing MPC_TS_SC solve
# (n = 307) reported up to 3000 iterations and took up to 4.5 s. Only the bench's deadline
# monitor bounds a cycle.
DEFAULT_MAX_ITER = 300
DUALITY_GAP_EPS = 1e-9
DEFAULT_MAX_ITER_IN = 100
# proxsuite's default 1e-4 for the infeasibility certificates declared feasible warm-started MPC
# problems infeasible after one iteration (constraints here are ~0.1 in scaled units).
INFEASIBILITY_EPS = 1e-9
# Active-set corrections tried from a guess (last cycle's, or proxsuite's) before giving up on it:
# between consecutive closed-loop cycles the active set changes by one or two bounds.
ACTIVE_SET_CHANGES = 4
# ... and when proxsuite has failed from warm and cold starts.
ACTIVE_SET_WALK = 200
# The last resort before "not solved": a cold proxsuite solve with residuals and duality gap at
# this tolerance and this many iterations.
TIGHT_EPS_ABS = 1e-11
TIGHT_MAX_ITER = 1000


@dataclass
class QPSolution:
    y: np.ndarray
    solved: bool
    status: str
    iterations: int
    objective: float          # 1/2 y'Hy + g'y, without the caller's constant
    # The KKT conditions were checked on y (bench.gnc.kkt): y is the optimum to rounding.
    certified: bool = False
    # How y was found, certified unless said otherwise: "active_set" (last cycle's active set, no
    # iterative solve), "proxsuite" (warm start, then exact on its active set), "proxsuite_cold"
    # (the warm-started result failed the certificate; cold solve), "active_set_walk" (proxsuite
    # failed from both starts; active-set steps from the last, proxsuite's or the nominal active
    # set), "proxsuite_tight" (a cold solve at tighter settings); not solved: "uncertified"
    # (proxsuite said solved, nothing certified), "failed" (proxsuite did not solve either),
    # "infeasible" (proxsuite did not solve from its warm start and a simplex proved infeasibility).
    path: str = "proxsuite"


class DenseBoxQP:
    """One proxsuite dense QP with native box constraints, re-solved for new vectors g, b, l, u."""

    def __init__(self, H: np.ndarray, A: np.ndarray | None, C: np.ndarray | None,
                 l_box: np.ndarray, u_box: np.ndarray,
                 eps_abs: float = DEFAULT_EPS_ABS, max_iter: int = DEFAULT_MAX_ITER,
                 max_iter_in: int = DEFAULT_MAX_ITER_IN, precondition: bool = False,
                 duality_gap_eps: float | None = DUALITY_GAP_EPS, infeasibility_eps: float = INFEASIBILITY_EPS,
                 start_active: ActiveSet | None = None):
        self.n = H.shape[0]
        self.n_eq = 0 if A is None else A.shape[0]
        self.n_in = 0 if C is None else C.shape[0]
        self._H, self._A, self._C = H, A, C
        self._l_box, self._u_box = np.asarray(l_box, float), np.asarray(u_box, float)
        self._eps_abs, self._max_iter, self._max_iter_in = eps_abs, max_iter, max_iter_in
        self._precondition = precondition
        self._duality_gap_eps = duality_gap_eps
        self._infeasibility_eps = infeasibility_eps
        self.kkt = ActiveSetQP(H, A, C, self._l_box, self._u_box)
        self._last_active: ActiveSet | None = None
        # Where the exact fallback walk starts when nothing better is known (cold: no last
        # active set): the caller's nominal active set, else nothing active.
        self._start_active = start_active if start_active is not None else ActiveSet.empty(self.n_in, self.n)
        self.paths: dict[str, int] = {}
        self._fresh(np.zeros(self.n), np.zeros(self.n_eq), np.full(self.n_in, -np.inf), np.full(self.n_in, np.inf))

    def reset(self) -> None:
        """Forget the warm start and the last active set: the state of a freshly built solver (a
        worker start, restart or model update). Cached factorisations are kept: they depend on the
        matrices only."""
        self._last_active = None
        self._fresh(np.zeros(self.n), np.zeros(self.n_eq), np.full(self.n_in, -np.inf), np.full(self.n_in, np.inf))

    def _fresh(self, g: np.ndarray, b: np.ndarray, l: np.ndarray, u: np.ndarray) -> None:
        qp = proxsuite.proxqp.dense.QP(self.n, self.n_eq, self.n_in, True)
        qp.settings.eps_abs = self._eps_abs
        qp.settings.eps_rel = 0.0
        qp.settings.max_iter = self._max_iter
        qp.settings.max_iter_in = self._max_iter_in
        qp.settings.eps_primal_inf = self._infeasibility_eps
        qp.settings.eps_dual_inf = self._infeasibility_eps
        qp.settings.verbose = False
        # Residuals alone let proxsuite stop at points with the wrong active set (first input
        # 2e-4 N off, objective 2e-5 high); the duality gap closes that.
        if self._duality_gap_eps is not None:
            qp.settings.check_duality_gap = True
            qp.settings.eps_duality_gap_abs = self._duality_gap_eps
            qp.settings.eps_duality_gap_rel = 0.0
        qp.settings.initial_guess = proxsuite.proxqp.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
        qp.init(self._H, g, self._A, self._b_or_none(b), self._C, self._in_or_none(l),
                self._in_or_none(u), self._l_box, self._u_box, compute_preconditioner=self._precondition)
        qp.solve()                       # required before the first warm-started update/solve
        self._qp = qp
        self._needs_fresh = False

    def _b_or_none(self, b):
        return b if self.n_eq else None

    def _in_or_none(self, v):
        return v if self.n_in else None

    def solve(self, g: np.ndarray, b: np.ndarray, l: np.ndarray, u: np.ndarray,
              active_guess: ActiveSet | None = None) -> QPSolution:
        """The certified optimum for vectors (g, b, l, u), or a solution marked not solved.

        First the exact solution on `active_guess` (default the last certified active set);
        proxsuite only when that fails its KKT certificate, and proxsuite's answer is made exact
        on its own active set and certified in turn. Every answer returned as solved has passed
        the certificate (bench.gnc.kkt); when nothing certifies, whatever proxsuite's status,
        the result is not solved (path "uncertified": proxsuite said solved; "failed": it did not).
        """
        guess = active_guess if active_guess is not None else self._last_active
        if guess is not None:
            point = self.kkt.solve_and_certify(g, b, l, u, guess, max_changes=ACTIVE_SET_CHANGES)
            if point is not None:
                return self._certified(point, g, "active_set", 0)
        # proxsuite's iterate seeds the guess even when it stopped on its iteration limit: the
        # certificate, not proxsuite's status, decides.
        sol = self._proxsuite(g, b, l, u, cold=False)
        point, proxsuite_guess = self._polish(g, b, l, u)
        if point is not None:
            return self._certified(point, g, "proxsuite", sol.iterations)
        # Not solved from the warm start: before the expensive part (a cold solve that runs to its
        # iteration limit on an infeasible problem, 0.3 to 8 s on the tube MPC, and the walks),
        # ask an exact simplex whether any point satisfies the constraints.
        if not sol.solved and not self._feasible(b, l, u):
            self._last_active = None
            return self._count(QPSolution(y=sol.y, solved=False, status="INFEASIBLE", iterations=sol.iterations,
                                          objective=float("nan"), path="infeasible"))
        # A warm start that fails the certificate: the multipliers carried over from the last
        # cycle were wrong (see bench.gnc.kkt). Solve from a fresh init and certify again.
        cold = self._proxsuite(g, b, l, u, cold=True)
        iterations = sol.iterations + cold.iterations
        point, cold_guess = self._polish(g, b, l, u)
        if point is not None:
            return self._certified(point, g, "proxsuite_cold", iterations)
        # proxsuite failed from both starts (on the tube MPC: false infeasibility certificates,
        # 6 cycles in 360; from a fresh controller, "solved" points off the optimum whose active
        # set did not certify, 10 states in 202, issue 27). Walk the active set as an active-set
        # solver would, from the last certified set, from proxsuite's, and from the nominal one
        # (nothing active: no previous set is needed); the certificate still decides.
        # From a start other than the last certified set, at most n changes (one per variable:
        # enough to reach any vertex from nothing; on the tube MPC the walks that certified took
        # 6 to 26): on an infeasible problem each walk runs to its limit.
        starts = [(guess, ACTIVE_SET_WALK)] + [(a, min(ACTIVE_SET_WALK, self.n))
                                                for a in (cold_guess, proxsuite_guess, self._start_active)]
        tried: set[bytes] = set()
        for start, max_changes in starts:
            if start is None or start.key in tried:
                continue
            tried.add(start.key)
            point = self.kkt.solve_and_certify(g, b, l, u, start, max_changes=max_changes)
            if point is not None:
                return self._certified(point, g, "active_set_walk", iterations)
        # Last: proxsuite from a fresh init with tighter settings (residuals and duality gap at
        # TIGHT_EPS_ABS, more iterations), its active set certified as before.
        # Only when proxsuite claims an optimum: on an infeasible problem this solve ran to its
        # iteration limit (up to 30 s on the tube MPC) for nothing.
        tight_solved = False
        if cold.solved:
            tight = self._proxsuite_tight(g, b, l, u)
            iterations += tight.iterations
            tight_solved = tight.solved
            point, _ = self._polish(g, b, l, u)
            if point is not None:
                return self._certified(point, g, "proxsuite_tight", iterations)
        self._last_active = None
        proxsuite_said_solved = cold.solved or tight_solved
        return self._count(QPSolution(
            y=cold.y, solved=False,
            status="UNCERTIFIED" if proxsuite_said_solved else cold.status,
            iterations=iterations, objective=cold.objective,
            path="uncertified" if proxsuite_said_solved else "failed"))

    def _feasible(self, b, l, u) -> bool:
        """False only if HiGHS's simplex proves that no y meets A y = b, l <= C y <= u and the box
        (to its feasibility tolerance, 1e-7: lenient, so a barely feasible problem is not thrown
        away); proxsuite's own infeasibility certificates were false on feasible tube problems."""
        kkt = self.kkt
        fu, fl = np.isfinite(u), np.isfinite(l)
        a_ub = np.vstack([kkt.C[fu], -kkt.C[fl]])
        b_ub = np.concatenate([u[fu], -l[fl]])
        bounds = np.column_stack([np.where(np.isfinite(kkt.l_box), kkt.l_box, None),
                                  np.where(np.isfinite(kkt.u_box), kkt.u_box, None)])
        res = linprog(np.zeros(self.n), A_ub=a_ub if a_ub.size else None, b_ub=b_ub if a_ub.size else None,
                      A_eq=kkt.A if self.n_eq else None, b_eq=np.asarray(b, float) if self.n_eq else None,
                      bounds=bounds, method="highs")
        return res.status != 2                      # 2: infeasible; anything else is not a proof

    def _polish(self, g, b, l, u):
        """(certified point or None, the active set read off proxsuite's iterate or None)."""
        res = self._qp.results
        if not np.all(np.isfinite(res.x)) or not np.all(np.isfinite(res.z)):
            return None, None
        z = np.asarray(res.z)
        guess = self.kkt.guess_active_set(res.x, z[:self.n_in], z[self.n_in:], l, u)
        return self.kkt.solve_and_certify(g, b, l, u, guess, max_changes=ACTIVE_SET_CHANGES), guess

    def _certified(self, point, g, path: str, iterations: int) -> QPSolution:
        self._last_active = point.active
        y = point.y
        return self._count(QPSolution(y=y, solved=True, status="SOLVED", iterations=iterations,
                                      objective=float(0.5 * y @ self.kkt.H @ y + g @ y), certified=True, path=path))

    def _count(self, sol: QPSolution) -> QPSolution:
        self.paths[sol.path] = self.paths.get(sol.path, 0) + 1
        return sol

    def _proxsuite_tight(self, g, b, l, u) -> QPSolution:
        """A cold proxsuite solve at tighter settings; the next cycle starts from a fresh init."""
        saved = (self._eps_abs, self._max_iter, self._duality_gap_eps)
        self._eps_abs = min(self._eps_abs, TIGHT_EPS_ABS)
        self._max_iter = max(self._max_iter, TIGHT_MAX_ITER)
        self._duality_gap_eps = TIGHT_EPS_ABS
        try:
            sol = self._proxsuite(g, b, l, u, cold=True)
        finally:
            self._eps_abs, self._max_iter, self._duality_gap_eps = saved
        self._needs_fresh = True
        return sol

    def _proxsuite(self, g, b, l, u, cold: bool) -> QPSolution:
        if self._needs_fresh or cold:
            self._fresh(g, b, l, u)            # init + cold solve of this very problem
        else:
            self._qp.update(g=g, b=self._b_or_none(b), l=self._in_or_none(l), u=self._in_or_none(u))
            self._qp.solve()
            if self._qp.results.info.status in CONFIRM_COLD:
                # A warm start from a distant point has produced false infeasibility certificates
                # (tube MPC, 1 cycle in ~6000): confirm them from a cold start. An iteration limit
                # is not retried: it already cost the cycle's worst case.
                self._fresh(g, b, l, u)
        res = self._qp.results
        status = res.info.status
        solved = status == SOLVED
        self._needs_fresh = not solved
        return QPSolution(
            y=res.x.copy(), solved=solved, status=status.name,
            iterations=int(res.info.iter), objective=float(res.info.objValue),
            path="proxsuite_uncertified" if solved else "failed",
        )
