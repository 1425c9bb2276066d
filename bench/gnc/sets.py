"""Polytopic sets for the MPC family (seed 003 tasks 13, 28, 29), all as H x <= h.

Geometry goes through scipy: linear programs on HiGHS (`scipy.optimize.linprog`) for support
functions and redundancy, qhull (`scipy.spatial.ConvexHull`) for Minkowski sums in vertex form.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linprog
from scipy.spatial import ConvexHull

# A constraint row counts as implied when its LP maximum is within this of its bound (scaled units).
REDUNDANCY_TOL = 1e-9


@dataclass(frozen=True)
class Polytope:
    """{x | H x <= h}."""

    H: np.ndarray
    h: np.ndarray

    def __post_init__(self):
        if self.H.ndim != 2 or self.h.shape != (self.H.shape[0],):
            raise ValueError(f"Polytope needs H (m x n) and h (m,), got {self.H.shape} and {self.h.shape}")

    @property
    def dim(self) -> int:
        return self.H.shape[1]

    def contains(self, x: np.ndarray, tol: float = 1e-9) -> np.ndarray | bool:
        """Membership of one point (n,) or of many points (k, n)."""
        x = np.asarray(x, dtype=float)
        slack = x @ self.H.T - self.h
        return np.all(slack <= tol, axis=-1)


def support(poly: Polytope, directions: np.ndarray) -> np.ndarray:
    """max_{x in poly} d' x for each row d of `directions` (one HiGHS LP per direction)."""
    directions = np.atleast_2d(directions)
    values = np.empty(directions.shape[0])
    free = [(None, None)] * poly.dim
    for i, d in enumerate(directions):
        res = linprog(-d, A_ub=poly.H, b_ub=poly.h, bounds=free, method="highs")
        if res.status == 3:
            raise ValueError(f"polytope is unbounded in direction {d}")
        if res.status != 0:
            raise ValueError(f"support LP failed ({res.message}); is the polytope empty?")
        values[i] = -res.fun
    return values


def remove_redundant_rows(poly: Polytope, tol: float = REDUNDANCY_TOL) -> Polytope:
    """Drop rows implied by the others (minimal H-representation, as MPT's minHRep).

    Row i is redundant if max H_i x over the remaining rows, with row i relaxed by 1, stays <= h_i.
    Zero rows and exact duplicates go first, since they would make every LP degenerate.
    """
    H, h = _normalise_rows(poly.H, poly.h)
    keep = np.ones(H.shape[0], dtype=bool)
    free = [(None, None)] * H.shape[1]
    for i in range(H.shape[0]):
        keep[i] = False
        b = np.concatenate([h[keep], [h[i] + 1.0]])
        a = np.vstack([H[keep], H[i]])
        res = linprog(-H[i], A_ub=a, b_ub=b, bounds=free, method="highs")
        keep[i] = res.status != 0 or -res.fun > h[i] + tol
    return Polytope(H[keep], h[keep])


def _normalise_rows(H: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows scaled to unit norm, zero rows (0 <= h, h >= 0) dropped, duplicates merged (tightest)."""
    norms = np.linalg.norm(H, axis=1)
    if np.any((norms == 0) & (h < 0)):
        raise ValueError("polytope is empty: a zero row has a negative bound")
    nz = norms > 0
    H, h = H[nz] / norms[nz, None], h[nz] / norms[nz]
    rounded = np.round(H, 12)
    _, first, inverse = np.unique(rounded, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    tightest = np.full(first.size, np.inf)
    np.minimum.at(tightest, inverse, h)
    return H[first], tightest


def max_positively_invariant(a_cl: np.ndarray, constraints: Polytope, max_iter: int = 1000) -> tuple[Polytope, int]:
    """Maximal positively invariant set of x+ = a_cl x inside `constraints` (Gilbert and Tan).

    O_k = {x | G a_cl^j x <= g, j = 0..k}; stop at the first k where every row of step k+1 is
    implied by O_k. Returns the set with redundant rows removed and k.
    """
    G, g = constraints.H, constraints.h
    rows, rhs = [G], [g]
    power = np.eye(a_cl.shape[0])
    free = [(None, None)] * a_cl.shape[0]
    for k in range(max_iter):
        power = a_cl @ power
        candidate = G @ power
        H_k, h_k = np.vstack(rows), np.concatenate(rhs)
        implied = True
        for row, bound in zip(candidate, g):
            res = linprog(-row, A_ub=H_k, b_ub=h_k, bounds=free, method="highs")
            if res.status != 0 or -res.fun > bound + REDUNDANCY_TOL:
                implied = False
                break
        if implied:
            return remove_redundant_rows(Polytope(H_k, h_k)), k
        rows.append(candidate)
        rhs.append(g)
    raise RuntimeError(f"maximal positively invariant set not finitely determined within {max_iter} steps")


def lqr_max_pi(k_lqr: np.ndarray, a: np.ndarray, b: np.ndarray, H_x, h_x, H_u, h_u) -> Polytope:
    """X_LQR of seed 003 eq. (16): states whose LQR closed loop u = K x keeps H_x x <= h_x and
    H_u u <= h_u for all time."""
    constraints = Polytope(np.vstack([H_x, H_u @ k_lqr]), np.concatenate([h_x, h_u]))
    return max_positively_invariant(a + b @ k_lqr, constraints)[0]


def vertices(poly: Polytope) -> np.ndarray:
    """Vertices of a bounded, full-dimensional polytope (qhull half-space intersection)."""
    from scipy.spatial import HalfspaceIntersection

    interior = chebyshev_centre(poly)
    hs = HalfspaceIntersection(np.hstack([poly.H, -poly.h[:, None]]), interior)
    return ConvexHull(hs.intersections).points[ConvexHull(hs.intersections).vertices]


def chebyshev_centre(poly: Polytope) -> np.ndarray:
    """Centre of the largest ball inside the polytope; raises if the polytope has no interior."""
    norms = np.linalg.norm(poly.H, axis=1)
    c = np.zeros(poly.dim + 1)
    c[-1] = -1.0
    res = linprog(c, A_ub=np.hstack([poly.H, norms[:, None]]), b_ub=poly.h,
                  bounds=[(None, None)] * poly.dim + [(0, None)], method="highs")
    if res.status != 0 or res.x[-1] <= 0:
        raise ValueError("polytope has no interior")
    return res.x[:-1]


def hull_polytope(points: np.ndarray) -> Polytope:
    """H-representation of the convex hull of points (qhull facets: normal . x + offset <= 0)."""
    hull = ConvexHull(points)
    return remove_redundant_rows(Polytope(hull.equations[:, :-1], -hull.equations[:, -1]))


def min_robust_positively_invariant(a_cl: np.ndarray, disturbance: Polytope, rel_tol: float = 1e-6,
                                    max_iter: int = 200) -> tuple[Polytope, int]:
    """Minimal RPI set of x+ = a_cl x + w, w in W (seed 003 task 28, lecture 9 algorithm).

    E_i = W + a_cl W + ... + a_cl^(i-1) W, Minkowski sums in vertex form. The sequence converges
    only asymptotically, so "E_{i+1} = E_i" means: the next term a_cl^i W moves no facet of E_i by
    more than rel_tol of that facet's offset. Returns E_i and i.
    """
    w_vertices = vertices(disturbance)
    acc = w_vertices
    power = np.eye(a_cl.shape[0])
    for i in range(1, max_iter + 1):
        poly = hull_polytope(acc)
        power = a_cl @ power
        term = w_vertices @ power.T
        growth = np.max(term @ poly.H.T, axis=0)       # support of a_cl^i W along each facet normal
        if np.all(growth <= rel_tol * np.abs(poly.h)):
            return poly, i
        acc = (acc[:, None, :] + term[None, :, :]).reshape(-1, a_cl.shape[0])
        acc = acc[ConvexHull(acc).vertices]
    raise RuntimeError(f"minimal RPI set did not converge within {max_iter} iterations; choose faster poles")


def pontryagin_difference(poly: Polytope, subtrahend: Polytope, linear_map: np.ndarray | None = None) -> Polytope:
    """poly - M S = {x | x + M s in poly for all s in S}: h_i - max_{s in S} H_i M s."""
    m = np.eye(subtrahend.dim) if linear_map is None else np.atleast_2d(linear_map)
    shift = support(subtrahend, poly.H @ m)
    tightened = poly.h - shift
    return Polytope(poly.H.copy(), tightened)
