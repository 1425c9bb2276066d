"""Unit-quaternion toolkit for attitude planning and tracking (seed 004 section 5, seed 000).

Convention, the same as `bench.plant.attitude`: scalar first, q = [s, v] = [w, x, y, z], Hamilton
product, q maps body vectors to inertial ones (r_N = q (x) [0, r_B] (x) q*). Products are matrices so
that Jacobians can be written with them:

    q2 (x) q1 = L(q2) q1 = R(q1) q2

Seed 004 errata fixed here:
- its Cayley map divides by sqrt(1 + |phi|); a unit quaternion needs sqrt(1 + |phi|^2).
"""
from __future__ import annotations

import numpy as np

IDENTITY_WXYZ = np.array([1.0, 0.0, 0.0, 0.0])
# H maps a 3-vector to a pure quaternion: [0; r].
H = np.vstack([np.zeros((1, 3)), np.eye(3)])
# T = diag(1, -1, -1, -1): conjugate(q) = T q.
T = np.diag([1.0, -1.0, -1.0, -1.0])


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for 3-vectors, the same arithmetic as np.cross, which costs ~10x more per call
    (argument handling): the attitude plant and laws call it several times per step."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def skew(v: np.ndarray) -> np.ndarray:
    """[v]x such that skew(a) @ b = a x b."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def left_matrix(q: np.ndarray) -> np.ndarray:
    """L(q): q (x) p = L(q) p."""
    s, v = q[0], q[1:]
    out = np.empty((4, 4))
    out[0, 0] = s
    out[0, 1:] = -v
    out[1:, 0] = v
    out[1:, 1:] = s * np.eye(3) + skew(v)
    return out


def right_matrix(q: np.ndarray) -> np.ndarray:
    """R(q): p (x) q = R(q) p."""
    s, v = q[0], q[1:]
    out = np.empty((4, 4))
    out[0, 0] = s
    out[0, 1:] = -v
    out[1:, 0] = v
    out[1:, 1:] = s * np.eye(3) - skew(v)
    return out


def multiply(q2: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """Hamilton product q2 (x) q1."""
    return left_matrix(q2) @ q1


def conjugate(q: np.ndarray) -> np.ndarray:
    return T @ q


def normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternion; raises on a zero or non-finite input rather than returning NaN."""
    q = np.asarray(q, dtype=float)
    norm = np.linalg.norm(q)
    if not np.isfinite(norm) or norm < 1e-12:
        raise ValueError(f"quaternion {q} cannot be normalised (norm {norm})")
    return q / norm


def rotation_matrix(q: np.ndarray) -> np.ndarray:
    """Q(q) = H^T L(q) R(q)^T H: body-to-inertial direction cosine matrix of q.

    Written out (the product expanded for a unit q): the matrix product cost ~80 us a call, and the
    attitude plant asks several times a step. tests/test_quaternion.py checks it against H^T L R^T H.
    """
    w, x, y, z = (float(c) for c in q)
    return np.array([
        [w * w + x * x - y * y - z * z, 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), w * w - x * x + y * y - z * z, 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), w * w - x * x - y * y + z * z],
    ])


def rotate(q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """q (x) [0, r] (x) q*: r rotated by q (body to inertial for the bench's q)."""
    return rotation_matrix(q) @ r


def attitude_jacobian(q: np.ndarray) -> np.ndarray:
    """G(q) = L(q) H (4x3): dq = G(q) dphi for a small body-frame rotation q (x) cayley(dphi)."""
    return left_matrix(q) @ H


def cayley(phi: np.ndarray) -> np.ndarray:
    """Rodrigues parameters -> unit quaternion: [1; phi] / sqrt(1 + |phi|^2) (seed: erratum, see top)."""
    phi = np.asarray(phi, dtype=float)
    return np.concatenate([[1.0], phi]) / np.sqrt(1.0 + phi @ phi)


def inverse_cayley(q: np.ndarray) -> np.ndarray:
    """Unit quaternion -> Rodrigues parameters v/s = axis tan(theta/2); singular at theta = pi."""
    if abs(q[0]) < 1e-12:
        raise ValueError("inverse Cayley map is singular at a 180-degree rotation (scalar part 0)")
    return q[1:] / q[0]


def exp(rotation_vector_rad: np.ndarray) -> np.ndarray:
    """Rotation vector (axis x angle, rad) -> unit quaternion [cos(theta/2), axis sin(theta/2)]."""
    r = np.asarray(rotation_vector_rad, dtype=float)
    theta = np.linalg.norm(r)
    if theta < 1e-8:
        # Second-order series keeps the result unit-length to machine precision near zero.
        return normalize(np.concatenate([[1.0 - theta**2 / 8.0], 0.5 * r]))
    return np.concatenate([[np.cos(theta / 2.0)], np.sin(theta / 2.0) * r / theta])


def log(q: np.ndarray) -> np.ndarray:
    """Unit quaternion -> rotation vector (rad) of the shortest rotation: q and -q give the same."""
    q = np.asarray(q, dtype=float)
    if q[0] < 0.0:  # q and -q are one attitude; take the representative with angle <= pi
        q = -q
    v_norm = np.linalg.norm(q[1:])
    if v_norm < 1e-12:
        return 2.0 * q[1:] / max(q[0], 1e-300)
    return 2.0 * np.arctan2(v_norm, q[0]) * q[1:] / v_norm


def angle_between_rad(q_a: np.ndarray, q_b: np.ndarray) -> float:
    """Rotation angle of q_a* (x) q_b, in [0, pi]: the pointing error between two attitudes."""
    # atan2 of the error quaternion's parts, not arccos(q_a . q_b): arccos loses half the digits
    # near zero angle (1e-8 rad of noise at identical inputs).
    dq = multiply(conjugate(q_a), q_b)
    return float(2.0 * np.arctan2(np.linalg.norm(dq[1:]), abs(dq[0])))


def error_state(q: np.ndarray, omega_radps: np.ndarray, q_ref: np.ndarray,
                omega_ref_radps: np.ndarray) -> np.ndarray:
    """6-vector [phi; omega - omega_ref] with phi = inverse_cayley(q_ref* (x) q) (body-frame error).

    The sign of the error quaternion is chosen with a non-negative scalar part so that the error is
    the short way round.
    """
    dq = multiply(conjugate(q_ref), q)
    if dq[0] < 0.0:
        dq = -dq
    return np.concatenate([inverse_cayley(dq), np.asarray(omega_radps) - np.asarray(omega_ref_radps)])


def state_error_jacobian(q: np.ndarray) -> np.ndarray:
    """E(x) (7x6): maps the 6-vector error state to a 7-vector state perturbation [dq; domega]."""
    out = np.zeros((7, 6))
    out[:4, :3] = attitude_jacobian(q)
    out[4:, 3:] = np.eye(3)
    return out
