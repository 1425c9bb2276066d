"""Curvilinear relative coordinates about a circular target orbit, and conversions to and from
Cartesian LVLH, for the plant boundary (seed 001: CWH controllers on the nonlinear plant).

Cartesian LVLH: x radial out, y along track, z along the orbit normal, origin at the target; the
chaser's position from the Earth's centre is p = (R + x, y, z) in LVLH axes.

Curvilinear (spherical about the Earth's centre, in the rotating LVLH frame):
    radial difference     dr = |p| - R
    arc length            s  = R theta,  theta = atan2(y, R + x)  (in-plane angle ahead of the target)
    cross-track           w  = R phi,    phi = asin(z / |p|)        (angle out of the orbit plane)
and their time derivatives in the rotating frame. State [dr, s, w, dr', s', w'].

Why: the CWH equations are the linearisation of the relative motion in either set, but in
Cartesian LVLH a chaser 400 km behind on the target's own orbit sits about y^2 / (2R) = 11 km
*below* x = 0, which CWH reads as an 11 km radial error to be corrected; in curvilinear
coordinates that chaser is at dr = 0, s = -400 km, as CWH assumes. The thrust a controller asks
for in curvilinear coordinates is along the local radial, along-track and cross-track directions
at the chaser, (e_r, e_theta, e_phi); `thrust_to_lvlh` turns it into LVLH components.
"""
from __future__ import annotations

import numpy as np


def _check_state(state: np.ndarray, name: str) -> np.ndarray:
    state = np.asarray(state, dtype=float)
    if state.shape != (6,):
        raise ValueError(f"{name} must have 6 entries [position m, velocity m/s], got shape {state.shape}")
    return state


def _check_radius(target_radius_m: float) -> float:
    if not (np.isfinite(target_radius_m) and target_radius_m > 0):
        raise ValueError(f"target_radius_m must be positive and finite, got {target_radius_m}")
    return float(target_radius_m)


def position_to_curvilinear_m(position_m: np.ndarray, target_radius_m: float) -> np.ndarray:
    """[dr, s, w] of an LVLH position (no velocity needed: what a position sensor converts)."""
    radius = _check_radius(target_radius_m)
    x, y, z = np.asarray(position_m, dtype=float).reshape(3)
    r = np.sqrt((radius + x) ** 2 + y**2 + z**2)
    return np.array([r - radius, radius * np.arctan2(y, radius + x), radius * np.arcsin(z / r)])


def cartesian_to_curvilinear(state_m_mps: np.ndarray, target_radius_m: float) -> np.ndarray:
    """LVLH [x, y, z, vx, vy, vz] -> curvilinear [dr, s, w, dr', s', w'] (SI)."""
    radius = _check_radius(target_radius_m)
    x, y, z, vx, vy, vz = _check_state(state_m_mps, "state_m_mps")
    px = radius + x
    rho2 = px**2 + y**2                      # squared distance from the orbit normal axis
    r = np.sqrt(rho2 + z**2)
    r_dot = (px * vx + y * vy + z * vz) / r
    theta_dot = (px * vy - y * vx) / rho2
    phi_dot = (vz * r - z * r_dot) / (r * np.sqrt(rho2))
    return np.array([r - radius, radius * np.arctan2(y, px), radius * np.arcsin(z / r),
                     r_dot, radius * theta_dot, radius * phi_dot])


def _unit_vectors(theta: float, phi: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(e_r, e_theta, e_phi) at the angles, LVLH components."""
    ct, st, cp, sp = np.cos(theta), np.sin(theta), np.cos(phi), np.sin(phi)
    return (np.array([cp * ct, cp * st, sp]), np.array([-st, ct, 0.0]), np.array([-sp * ct, -sp * st, cp]))


def curvilinear_to_cartesian(state_curv: np.ndarray, target_radius_m: float) -> np.ndarray:
    """Curvilinear [dr, s, w, dr', s', w'] -> LVLH [x, y, z, vx, vy, vz] (SI)."""
    radius = _check_radius(target_radius_m)
    dr, s, w, dr_dot, s_dot, w_dot = _check_state(state_curv, "state_curv")
    r, theta, phi = radius + dr, s / radius, w / radius
    e_r, e_theta, e_phi = _unit_vectors(theta, phi)
    position = r * e_r
    # d(r e_r)/dt = r' e_r + r theta' cos(phi) e_theta + r phi' e_phi
    velocity = dr_dot * e_r + r * (s_dot / radius) * np.cos(phi) * e_theta + r * (w_dot / radius) * e_phi
    return np.concatenate([position - np.array([radius, 0.0, 0.0]), velocity])


def thrust_to_lvlh(thrust_curv_n: np.ndarray, position_m: np.ndarray, target_radius_m: float) -> np.ndarray:
    """Thrust along (e_r, e_theta, e_phi) at the chaser's LVLH position -> LVLH components."""
    radius = _check_radius(target_radius_m)
    x, y, z = np.asarray(position_m, dtype=float).reshape(3)
    theta = np.arctan2(y, radius + x)
    phi = np.arcsin(z / np.sqrt((radius + x) ** 2 + y**2 + z**2))
    e_r, e_theta, e_phi = _unit_vectors(theta, phi)
    u = np.asarray(thrust_curv_n, dtype=float).reshape(3)
    return u[0] * e_r + u[1] * e_theta + u[2] * e_phi
