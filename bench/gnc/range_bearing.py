"""Range, azimuth and elevation of a relative position, and their Jacobian (pure geometry).

Shared by the plant's range/bearing sensor and the estimator's measurement model, so both use
the same angles: azimuth = atan2(y, x) in (-pi, pi], elevation = asin(z / range).
"""
from __future__ import annotations

import numpy as np


def range_bearing(position_m: np.ndarray) -> np.ndarray:
    """[range m, azimuth rad (atan2(y, x)), elevation rad (asin(z / range))] of a relative position."""
    x, y, z = position_m
    rng = float(np.linalg.norm(position_m))
    return np.array([rng, np.arctan2(y, x), np.arcsin(z / rng)])


def range_bearing_jacobian(position_m: np.ndarray) -> np.ndarray:
    """d[range, azimuth, elevation]/d position, 3x3."""
    x, y, z = position_m
    rho2 = x * x + y * y
    rho = np.sqrt(rho2)
    r2 = rho2 + z * z
    r = np.sqrt(r2)
    return np.array([
        [x / r, y / r, z / r],
        [-y / rho2, x / rho2, 0.0],
        [-x * z / (r2 * rho), -y * z / (r2 * rho), rho / r2],
    ])


def position_from_range_bearing(rb: np.ndarray) -> np.ndarray:
    """The relative position at this range, azimuth and elevation (the inverse of range_bearing)."""
    rng, azimuth, elevation = rb
    return rng * np.array([np.cos(elevation) * np.cos(azimuth),
                           np.cos(elevation) * np.sin(azimuth),
                           np.sin(elevation)])


def wrap_angle_rad(angle_rad):
    """An angle (difference) in [-pi, pi)."""
    return (angle_rad + np.pi) % (2.0 * np.pi) - np.pi
