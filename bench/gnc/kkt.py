"""Exact solution of a convex QP on a guessed active set, and its optimality certificate.

    min_y 1/2 y'Hy + g'y   s.t.  A y = b,  l <= C y <= u,  l_box <= y <= u_box      (H > 0)

Multipliers follow proxsuite's sign convention: H y + g + A'lam + C'z + z_box = 0, with z_i >= 0
on a row held at its upper bound, z_i <= 0 at its lower bound, 0 on an inactive row (same for
z_box). Given a guess of which bounds are active, `solve_on_active_set` solves the equality-
constrained QP exactly (one KKT system, LU-factored once per distinct active set and cached), and
`certify` checks the rest of the KKT conditions: primal feasibility of every constraint and the
sign of every multiplier. A point that passes is the optimum of the convex QP (the KKT conditions
are sufficient), to rounding: this is what lets an MPC accept a solution without trusting an
iterative solver's stopping test, and skip the iterative solver when last cycle's active set (or
the empty one: the unconstrained, explicit law) is still optimal.

Why the certificate is needed (measured on seed 003's tube MPC): proxsuite stops on primal and
dual residuals; the tube set E has 16 pairs of nearly parallel facets, so warm-started multipliers
drifted along the near-null space of C' to +-5e6 on inactive rows, cancelling in C'z: residuals
below 1e-9, duality gap 2426, first input 0.27 N off.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy.linalg import LinAlgWarning, lu_factor, lu_solve

# Relative tolerances of the certificate (constraint values in this bench's scaled units are
# ~1e-4 to 1; rounding of the KKT solve leaves ~1e-13). Primal 1e-10, not 1e-9: on the tube MPC a
# point 8.8e-10 outside one of two nearly parallel tube facets passed at 1e-9 with z_0 1.5e-6 off
# along them, its first input 7.2e-4 N from quadprog's (issue 27); at 1e-11 a closed-loop cycle
# of the 100 sampled-disturbance runs (tests/test_controller_tube.py) could not be certified.
PRIMAL_TOL = 1e-10
DUAL_SIGN_TOL = 1e-9
# Stationarity residual H y + g + A'lam + C'z + z_box, relative to the largest of its terms: the
# exact solve leaves ~1e-15 of them; an ill-conditioned active set (nearly parallel tube facets)
# can leave far more.
STATIONARITY_TOL = 1e-9
# Cached factorisations per solver: closed loops revisit a handful of active sets.
MAX_CACHED_FACTORS = 64


@dataclass(frozen=True)
class ActiveSet:
    """Which bounds hold with equality: per inequality row (upper, lower), per variable (box)."""

    upper: np.ndarray
    lower: np.ndarray
    box_upper: np.ndarray
    box_lower: np.ndarray

    @classmethod
    def empty(cls, n_in: int, n: int) -> "ActiveSet":
        f = np.zeros(n_in, dtype=bool)
        v = np.zeros(n, dtype=bool)
        return cls(f, f.copy(), v, v.copy())

    @property
    def key(self) -> bytes:
        return np.concatenate([self.upper, self.lower, self.box_upper, self.box_lower]).tobytes()

    @property
    def size(self) -> int:
        return int(self.upper.sum() + self.lower.sum() + self.box_upper.sum() + self.box_lower.sum())


@dataclass
class KKTPoint:
    y: np.ndarray
    lam: np.ndarray        # equality multipliers
    z: np.ndarray          # inequality-row multipliers
    z_box: np.ndarray      # box multipliers
    active: ActiveSet


class ActiveSetQP:
    """The fixed matrices of one QP; solves and certifies it for new vectors on a guessed active set."""

    def __init__(self, H: np.ndarray, A: np.ndarray | None, C: np.ndarray | None,
                 l_box: np.ndarray, u_box: np.ndarray):
        self.H = np.asarray(H, float)
        self.n = self.H.shape[0]
        self.A = np.zeros((0, self.n)) if A is None else np.asarray(A, float)
        self.C = np.zeros((0, self.n)) if C is None else np.asarray(C, float)
        self.l_box, self.u_box = np.asarray(l_box, float), np.asarray(u_box, float)
        self._factors: dict[bytes, tuple] = {}

    def _factor(self, active: ActiveSet):
        key = active.key
        cached = self._factors.get(key)
        if cached is not None:
            return cached
        fixed = active.box_upper | active.box_lower
        free = ~fixed
        rows = active.upper | active.lower
        Ca = np.vstack([self.A, self.C[rows]])
        Ca_free = Ca[:, free]
        n_f, m = int(free.sum()), Ca.shape[0]
        kkt = np.zeros((n_f + m, n_f + m))
        kkt[:n_f, :n_f] = self.H[np.ix_(free, free)]
        kkt[:n_f, n_f:] = Ca_free.T
        kkt[n_f:, :n_f] = Ca_free
        # A singular KKT matrix (dependent active rows) means the guess cannot be certified this way.
        entry = None
        if not (m > n_f or (m > 0 and np.linalg.matrix_rank(Ca_free) < m)):
            # A free variable without curvature and without an active row (a soft constraint's
            # t_i off its bound) also makes the KKT matrix singular: check the pivots, quietly.
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", LinAlgWarning)
                lu = lu_factor(kkt, check_finite=False)
            pivots = np.abs(np.diag(lu[0]))
            if pivots.size == 0 or pivots.min() > 1e-14 * pivots.max():
                entry = (lu, free, fixed, rows, Ca)
        if len(self._factors) >= MAX_CACHED_FACTORS:
            self._factors.pop(next(iter(self._factors)))
        self._factors[key] = entry
        return entry

    def solve_on_active_set(self, g, b, l, u, active: ActiveSet) -> KKTPoint | None:
        """The stationary point with the guessed bounds held as equalities; None if singular."""
        entry = self._factor(active)
        if entry is None:
            return None
        lu, free, fixed, rows, Ca = entry
        y = np.empty(self.n)
        y[fixed] = np.where(active.box_upper, self.u_box, self.l_box)[fixed]
        row_values = np.where(active.upper, u, l)[rows]
        rhs_eq = np.concatenate([np.asarray(b, float).reshape(-1), row_values]) - Ca[:, fixed] @ y[fixed]
        rhs = np.concatenate([-(g[free] + self.H[np.ix_(free, fixed)] @ y[fixed]), rhs_eq])
        sol = lu_solve(lu, rhs, check_finite=False)
        n_f = int(free.sum())
        y[free] = sol[:n_f]
        mult = sol[n_f:]
        lam = mult[:self.A.shape[0]]
        z = np.zeros(self.C.shape[0])
        z[rows] = mult[self.A.shape[0]:]
        z_box = np.zeros(self.n)
        z_box[fixed] = -(self.H[fixed] @ y + g[fixed] + self.A[:, fixed].T @ lam + self.C[:, fixed].T @ z)
        if not np.all(np.isfinite(y)):
            return None
        return KKTPoint(y, lam, z, z_box, active)

    def certify(self, point: KKTPoint | None, l, u, g=None, b=None) -> bool:
        """True if `point` satisfies the KKT conditions within tolerance: primal feasibility of
        every constraint, the sign of every multiplier and, given g (and b), stationarity, the
        equality rows and complementarity (active bounds held), which the exact solve on the
        active set imposes up to its rounding: checked so that an ill-conditioned active set
        cannot pass a point its LU solve got wrong."""
        if point is None:
            return False
        y, a = point.y, point.active
        cy = self.C @ y
        tol_in = PRIMAL_TOL * (1.0 + np.abs(cy))
        if np.any(cy > u + tol_in) or np.any(cy < l - tol_in):
            return False
        if g is not None and not self._residuals_small(point, cy, g, b, l, u):
            return False
        tol_box = PRIMAL_TOL * (1.0 + np.abs(y))
        if np.any(y > self.u_box + tol_box) or np.any(y < self.l_box - tol_box):
            return False
        scale = 1.0 + max(np.max(np.abs(point.z), initial=0.0), np.max(np.abs(point.z_box), initial=0.0))
        tol_z = DUAL_SIGN_TOL * scale
        return bool(np.all(point.z[a.upper] >= -tol_z) and np.all(point.z[a.lower] <= tol_z)
                    and np.all(point.z_box[a.box_upper] >= -tol_z) and np.all(point.z_box[a.box_lower] <= tol_z))

    def _residuals_small(self, point: KKTPoint, cy, g, b, l, u) -> bool:
        y, a = point.y, point.active
        hy, a_lam, c_z = self.H @ y, self.A.T @ point.lam, self.C.T @ point.z
        scale = 1.0 + max(np.max(np.abs(t), initial=0.0) for t in (g, hy, a_lam, c_z, point.z_box))
        if np.max(np.abs(hy + g + a_lam + c_z + point.z_box), initial=0.0) > STATIONARITY_TOL * scale:
            return False
        if self.A.shape[0]:
            ay = self.A @ y
            b = np.asarray(b, float).reshape(-1)
            if np.any(np.abs(ay - b) > PRIMAL_TOL * (1.0 + np.abs(b))):
                return False
        held = np.concatenate([(cy - u)[a.upper], (cy - l)[a.lower],
                               (y - self.u_box)[a.box_upper], (y - self.l_box)[a.box_lower]])
        value = np.concatenate([cy[a.upper], cy[a.lower], y[a.box_upper], y[a.box_lower]])
        return bool(np.all(np.abs(held) <= PRIMAL_TOL * (1.0 + np.abs(value))))

    def guess_active_set(self, y, z, z_box, l, u, slack_tol: float = 1e-7) -> ActiveSet:
        """Active set read off an approximate primal-dual point: a bound is a candidate when the
        point is within slack_tol (relative) of it and its multiplier has the bound's sign;
        candidates are taken by decreasing |multiplier| while they stay linearly independent
        (near-parallel facets of a tube otherwise make the KKT matrix singular)."""
        cy = self.C @ y
        tol_in = slack_tol * (1.0 + np.abs(cy))
        up = (u - cy <= tol_in) & (z > 0)
        lo = (cy - l <= tol_in) & (z < 0) & ~up
        tol_box = slack_tol * (1.0 + np.abs(y))
        bup = (self.u_box - y <= tol_box) & (z_box > 0)
        blo = (y - self.l_box <= tol_box) & (z_box < 0) & ~bup
        box = bup | blo
        free = ~box
        rows = np.flatnonzero(up | lo)
        keep = np.zeros(self.C.shape[0], dtype=bool)
        basis = self.A[:, free]
        rank = np.linalg.matrix_rank(basis) if basis.size else 0
        for i in rows[np.argsort(-np.abs(z[rows]))]:
            trial = np.vstack([basis, self.C[i, free]])
            r = np.linalg.matrix_rank(trial, tol=1e-10 * max(1.0, np.abs(trial).max()))
            if r > rank:
                basis, rank = trial, r
                keep[i] = True
        return ActiveSet(up & keep, lo & keep, bup, blo)

    def solve_and_certify(self, g, b, l, u, active: ActiveSet, max_changes: int = 0) -> KKTPoint | None:
        """The certified optimum from `active`, changing the guess up to max_changes times: add
        the most violated bound, else drop the active bound with the most wrong-signed multiplier
        (a primal-dual active-set step); None if not certified by then."""
        for _ in range(max_changes + 1):
            point = self.solve_on_active_set(g, b, l, u, active)
            if point is None:
                return None
            if self.certify(point, l, u, g, b):
                return point
            active = self._next_guess(point, l, u)
            if active is None:
                return None
        return None

    def _next_guess(self, point: KKTPoint, l, u) -> ActiveSet | None:
        """A bound violated by `point` joins the active set (the most violated whose row keeps the
        active rows independent, or replaces one that makes them dependent); if none is
        violated, the most wrong-signed multiplier leaves."""
        a = point.active
        up, lo, bup, blo = a.upper.copy(), a.lower.copy(), a.box_upper.copy(), a.box_lower.copy()
        y = point.y
        cy = self.C @ y
        viol = np.concatenate([cy - u, l - cy, y - self.u_box, self.l_box - y])
        scale = np.concatenate([1.0 + np.abs(cy), 1.0 + np.abs(cy), 1.0 + np.abs(y), 1.0 + np.abs(y)])
        rel = viol / scale
        m = cy.size
        for k in np.argsort(-rel):
            if rel[k] <= PRIMAL_TOL:
                break
            trial = [up.copy(), lo.copy(), bup.copy(), blo.copy()]
            if k < m:
                trial[0][k] = True
            elif k < 2 * m:
                trial[1][k - m] = True
            elif k < 2 * m + self.n:
                trial[2][k - 2 * m] = True
            else:
                trial[3][k - 2 * m - self.n] = True
            candidate = ActiveSet(*trial)
            if self._factor(candidate) is not None:   # independent of the rows already active
                return candidate
            # Dependent on the active rows (nearly parallel tube facets): swap it for the active
            # row with the smallest multiplier that makes the rows independent again.
            if k < 2 * m:
                for j in np.flatnonzero(up | lo)[np.argsort(np.abs(point.z[up | lo]))]:
                    swapped = ActiveSet(candidate.upper.copy(), candidate.lower.copy(), bup, blo)
                    swapped.upper[j] = swapped.lower[j] = False
                    if self._factor(swapped) is not None:
                        return swapped
        wrong = np.concatenate([np.where(up, -point.z, 0.0), np.where(lo, point.z, 0.0),
                                np.where(bup, -point.z_box, 0.0), np.where(blo, point.z_box, 0.0)])
        k = int(np.argmax(wrong)) if wrong.size else -1
        if k < 0 or wrong[k] <= 0:
            return None
        if k < m:
            up[k] = False
        elif k < 2 * m:
            lo[k - m] = False
        elif k < 2 * m + self.n:
            bup[k - 2 * m] = False
        else:
            blo[k - 2 * m - self.n] = False
        return ActiveSet(up, lo, bup, blo)
