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


@dataclass
class QPSolution:
    y: np.ndarray
    solved: bool
    status: str
    iterations: int
    objective: float          # 1/2 y'Hy + g'y, without the caller's constant


class DenseBoxQP:
    """One proxsuite dense QP with native box constraints, re-solved for new vectors g, b, l, u."""

    def __init__(self, H: np.ndarray, A: np.ndarray | None, C: np.ndarray | None,
                 l_box: np.ndarray, u_box: np.ndarray,
                 eps_abs: float = DEFAULT_EPS_ABS, max_iter: int = DEFAULT_MAX_ITER,
                 max_iter_in: int = DEFAULT_MAX_ITER_IN, precondition: bool = False,
                 duality_gap_eps: float | None = DUALITY_GAP_EPS, infeasibility_eps: float = INFEASIBILITY_EPS):
        self.n = H.shape[0]
        self.n_eq = 0 if A is None else A.shape[0]
        self.n_in = 0 if C is None else C.shape[0]
        self._H, self._A, self._C = H, A, C
        self._l_box, self._u_box = np.asarray(l_box, float), np.asarray(u_box, float)
        self._eps_abs, self._max_iter, self._max_iter_in = eps_abs, max_iter, max_iter_in
        self._precondition = precondition
        self._duality_gap_eps = duality_gap_eps
        self._infeasibility_eps = infeasibility_eps
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

    def solve(self, g: np.ndarray, b: np.ndarray, l: np.ndarray, u: np.ndarray) -> QPSolution:
        if self._needs_fresh:
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
        )
