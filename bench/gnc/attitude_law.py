"""Attitude control laws for a magnetorquer-only spacecraft, behind one interface.

Every law is an object with `eval(x) -> (dipole_am2, info)` (the seed 003 convention): it reads an
`AttitudeControlInput` (what the flight side believes: attitude, rate, field in body axes) and
returns the magnetic dipole to command, in A m^2, body axes, already saturated per axis at the
board's limit. Torque laws (sliding mode, PD) go through `dipole_for_torque`, the least-norm dipole
whose torque m x B is the component of the desired torque perpendicular to B: a magnetorquer can
produce no torque along the field, so that component is lost (the under-actuation of seed 004).

Laws here:
- `BDotDetumble`: m = -k dB/dt (body frame), the classic magnetometer-only rate damper. It drives
  the body to follow the field direction, which turns at about 2n in a near-polar orbit, so it
  settles near 2n (~0.13 deg/s at 500 km), not at rest (Avanzini & Giulietti 2012, JGCD 35(4)).
- `RateDamping`: m = (k/|B|^2) (omega x B), gyro-based: damps the inertial rate itself, to zero.
- `DetumbleSequence`: B-dot, then rate damping once the believed rate is below a handover rate.
- `ResidualDipoleCompensation`: any law's dipole minus the spacecraft's calibrated residual dipole.
- `SlidingModeTracking`: seed 002's sliding-mode tracking law with sgn(q0) against unwinding.
- `PdTracking`: seed 002's model-agnostic PD law, -kp sgn(q0) q_v - kd omega_e.

Frames: q is body to inertial (scalar first), omega in body axes, the target's rate in the
target frame's own axes (`AttitudeTarget`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from bench.gnc import quaternion as qt

# Below this |B| the torque-to-dipole map divides by ~0; no board can act there (|B| in LEO is
# 2e-5..5e-5 T), so the law commands zero and says so instead of a huge or non-finite dipole.
MIN_FIELD_T = 1e-9


@dataclass(frozen=True)
class AttitudeControlInput:
    time_s: float
    q_wxyz: np.ndarray          # believed attitude, body to inertial
    omega_radps: np.ndarray     # believed body rate (gyro bias removed), body axes
    field_body_t: np.ndarray    # geomagnetic field in body axes (measured or modelled), T


class AttitudeLaw(Protocol):
    def eval(self, x: AttitudeControlInput) -> tuple[np.ndarray, dict]:
        """Dipole to command (A m^2, body axes, saturated) and an info dict."""


@dataclass(frozen=True)
class TargetState:
    q_wxyz: np.ndarray                  # desired attitude, target frame to inertial
    omega_radps: np.ndarray             # desired rate, target-frame axes
    omega_dot_radps2: np.ndarray        # desired angular acceleration, target-frame axes


# A target is a function of time: an inertial hold, a nadir-pointing frame, a planned slew.
AttitudeTarget = Callable[[float], TargetState]


def inertial_hold(q_wxyz) -> AttitudeTarget:
    """Hold a fixed inertial attitude."""
    state = TargetState(qt.normalize(np.asarray(q_wxyz, float)), np.zeros(3), np.zeros(3))
    return lambda time_s: state


def saturate_dipole(dipole_am2: np.ndarray, dipole_limit_am2: float) -> tuple[np.ndarray, bool]:
    """Per-axis clip at the board's limit (each coil saturates on its own); True when one clipped."""
    clipped = np.clip(dipole_am2, -dipole_limit_am2, dipole_limit_am2)
    return clipped, bool(np.any(clipped != dipole_am2))


def dipole_for_torque(torque_body_nm: np.ndarray, field_body_t: np.ndarray,
                      dipole_limit_am2: float) -> tuple[np.ndarray, dict]:
    """m = (B x tau) / |B|^2, saturated per axis; zero (and counted in info) where |B| ~ 0.

    (B x tau) x B / |B|^2 = tau - (tau . B) B / |B|^2: the torque it yields is tau minus its
    component along B, the most a magnetorquer can give.
    """
    torque = np.asarray(torque_body_nm, float)
    field_t = np.asarray(field_body_t, float)
    field_sq = float(field_t @ field_t)
    if not np.isfinite(field_sq) or field_sq < MIN_FIELD_T**2 or not np.all(np.isfinite(torque)):
        return np.zeros(3), {"weak_or_bad_field": True, "saturated": False}
    dipole, saturated = saturate_dipole(qt.cross3(field_t, torque) / field_sq, dipole_limit_am2)
    return dipole, {"weak_or_bad_field": False, "saturated": saturated}


def _tracking_errors(x: AttitudeControlInput, target: TargetState):
    """q_e = q_d* (x) q, the target rate in body axes omega_r = C(q_e)^T omega_d, omega_e = omega - omega_r.

    C(q_e)^T takes target-frame vectors to body axes (seed 002: q_e* (x) omega_d (x) q_e).
    """
    q_e = qt.multiply(qt.conjugate(target.q_wxyz), x.q_wxyz)
    c_body_from_target = qt.rotation_matrix(q_e).T
    omega_r = c_body_from_target @ target.omega_radps
    omega_e = x.omega_radps - omega_r
    return q_e, c_body_from_target, omega_r, omega_e


def _dipole_from_torque_law(law, x: AttitudeControlInput) -> tuple[np.ndarray, dict]:
    """A torque law's eval: its torque through the magnetorquer map, with both infos."""
    torque, info = law.torque_nm(x)
    dipole, map_info = dipole_for_torque(torque, x.field_body_t, law.dipole_limit_am2)
    return dipole, {**info, **map_info, "torque_nm": torque}


def _sign(q0: float) -> float:
    # sgn(0) taken as +1: at exactly 180 degrees either way is the short way.
    return 1.0 if q0 >= 0.0 else -1.0


@dataclass
class SlidingModeTracking:
    """Seed 002: s = omega_e + lambda sgn(q_e0) q_ev, torque
    M = omega x J omega + J omega_r_dot - lambda J sgn(q_e0) q_ev_dot - k J s.

    With the full torque, V = s'Js decays as exp(-2kt) and q_e goes to (+-1, 0), whichever is nearer
    (sgn(q_e0) picks it: no unwinding). With magnetorquers only the part of M along B is lost.
    """
    target: AttitudeTarget
    inertia_kgm2: np.ndarray
    dipole_limit_am2: float
    sliding_gain_radps: float = 0.05      # lambda
    convergence_gain_radps: float = 0.02  # k

    def torque_nm(self, x: AttitudeControlInput) -> tuple[np.ndarray, dict]:
        target = self.target(x.time_s)
        q_e, c_bt, omega_r, omega_e = _tracking_errors(x, target)
        sign = _sign(q_e[0])
        q_ev = q_e[1:]
        # q_e_dot = 1/2 q_e (x) [0, omega_e]  =>  vector part 1/2 (q0 omega_e + q_v x omega_e)
        q_ev_dot = 0.5 * (q_e[0] * omega_e + qt.cross3(q_ev, omega_e))
        # d/dt (C omega_d) = C omega_d_dot - omega_e x C omega_d (C = body-from-target rotation)
        omega_r_dot = c_bt @ target.omega_dot_radps2 - qt.cross3(omega_e, omega_r)
        s = omega_e + self.sliding_gain_radps * sign * q_ev
        j = self.inertia_kgm2
        w = x.omega_radps
        torque = (qt.cross3(w, j @ w) + j @ omega_r_dot
                  - self.sliding_gain_radps * sign * (j @ q_ev_dot) - self.convergence_gain_radps * (j @ s))
        return torque, {"sliding_variable": s, "error_angle_rad": qt.angle_between_rad(target.q_wxyz, x.q_wxyz)}

    def eval(self, x: AttitudeControlInput) -> tuple[np.ndarray, dict]:
        return _dipole_from_torque_law(self, x)


@dataclass
class PdTracking:
    """Seed 002's model-agnostic law: M = -kp sgn(q_e0) q_ev - kd omega_e (needs no inertia)."""
    target: AttitudeTarget
    dipole_limit_am2: float
    kp_nm: float = 1e-4
    kd_nms: float = 5e-3

    def torque_nm(self, x: AttitudeControlInput) -> tuple[np.ndarray, dict]:
        target = self.target(x.time_s)
        q_e, _, _, omega_e = _tracking_errors(x, target)
        torque = -self.kp_nm * _sign(q_e[0]) * q_e[1:] - self.kd_nms * omega_e
        return torque, {"error_angle_rad": qt.angle_between_rad(target.q_wxyz, x.q_wxyz)}

    def eval(self, x: AttitudeControlInput) -> tuple[np.ndarray, dict]:
        return _dipole_from_torque_law(self, x)


@dataclass
class BDotDetumble:
    """m = -k dB/dt, dB/dt from successive field samples in body axes (no rate or attitude needed).

    In body axes dB/dt ~ -omega x B when the body turns faster than the orbit, so the torque
    (-k dB/dt) x B = k (omega x B) x B has omega . torque = -k |omega x B|^2 <= 0: it only removes
    kinetic energy. The first call has no previous sample and commands zero.
    """
    gain_am2_s_per_t: float
    dipole_limit_am2: float
    _previous: tuple[float, np.ndarray] | None = field(default=None, repr=False)

    def eval(self, x: AttitudeControlInput) -> tuple[np.ndarray, dict]:
        field_t = np.asarray(x.field_body_t, float)
        if not np.all(np.isfinite(field_t)):
            self._previous = None      # never difference across a bad sample
            return np.zeros(3), {"weak_or_bad_field": True, "saturated": False}
        previous, self._previous = self._previous, (x.time_s, field_t)
        if previous is None or x.time_s <= previous[0]:
            return np.zeros(3), {"weak_or_bad_field": False, "saturated": False, "first_sample": True}
        field_rate_tps = (field_t - previous[1]) / (x.time_s - previous[0])
        dipole, saturated = saturate_dipole(-self.gain_am2_s_per_t * field_rate_tps, self.dipole_limit_am2)
        return dipole, {"weak_or_bad_field": False, "saturated": saturated, "field_rate_tps": field_rate_tps}


@dataclass
class RateDamping:
    """Gyro-based rate damping: m = (k/|B|^2) (omega x B), so the torque is

        tau = m x B = k (omega x b) x b = -k (omega - (omega . b) b)        (b = B/|B|)

    i.e. -k times the rate component perpendicular to the field (the part a magnetorquer can
    touch), with k in N m s whatever |B| is. With V = 1/2 omega' J omega (omega the inertial rate in
    body axes), dV/dt = omega . tau (the gyroscopic term omega x J omega does no work), so

        dV/dt = omega . (m_sat x B) = m_sat . (B x omega) = -(|B|^2/k) m_sat . m <= 0,

    because per-axis saturation (and the board's rounding) keeps each component's sign or zeroes
    it: m_sat,i m_i >= 0. Unlike B-dot it damps the inertial rate, not the rate relative to the
    field, so it goes to rest instead of following the field at ~2n. The rate along B is not
    damped at any instant; it is as the field turns (about 2n in a near-polar orbit), so the
    slowest mode decays in about an orbit, the rest at k/J. Needs a bias-free rate: a raw gyro
    with a 1e-3 rad/s bias would park the body at minus the bias (0.06 deg/s per axis).
    """
    gain_nms: float
    dipole_limit_am2: float

    def eval(self, x: AttitudeControlInput) -> tuple[np.ndarray, dict]:
        field_t = np.asarray(x.field_body_t, float)
        omega = np.asarray(x.omega_radps, float)
        field_sq = float(field_t @ field_t)
        if not np.isfinite(field_sq) or field_sq < MIN_FIELD_T**2 or not np.all(np.isfinite(omega)):
            return np.zeros(3), {"weak_or_bad_field": True, "saturated": False}
        dipole, saturated = saturate_dipole(self.gain_nms * qt.cross3(omega, field_t) / field_sq, self.dipole_limit_am2)
        return dipole, {"weak_or_bad_field": False, "saturated": saturated}


@dataclass
class DetumbleSequence:
    """What a detumble mode flies: B-dot (magnetometer only: robust to a gyro that is saturated,
    biased or not yet calibrated) takes the body from tumbling down to a few times the orbit rate;
    once the believed rate is below `handover_rate_radps` (latched: no chattering back), gyro rate
    damping takes it to rest, which B-dot cannot (it follows the field at ~2n)."""
    bdot: BDotDetumble
    rate_damping: RateDamping
    handover_rate_radps: float
    handover_time_s: float | None = None

    def eval(self, x: AttitudeControlInput) -> tuple[np.ndarray, dict]:
        if self.handover_time_s is None and np.linalg.norm(x.omega_radps) < self.handover_rate_radps:
            self.handover_time_s = float(x.time_s)
        law = self.bdot if self.handover_time_s is None else self.rate_damping
        dipole, info = law.eval(x)
        return dipole, {**info, "phase": "bdot" if law is self.bdot else "rate_damping"}


class LawWrapper:
    """Base of the wrappers below: a law around a law (`self.law`), whose own interface (set_plan,
    torque_nm, ...) stays reachable through the wrapper."""

    def __getattr__(self, name):
        # Dunder names and `law` itself are not forwarded (unpickling asks before `law` exists).
        if name == "law" or name.startswith("__"):
            raise AttributeError(name)
        return getattr(self.law, name)


@dataclass
class ResidualDipoleCompensation(LawWrapper):
    """The law's dipole minus the spacecraft's believed (calibrated) residual dipole, re-saturated.

    The residual dipole m_r (harness currents, magnetised parts) adds m_r x B to every torque. On
    the bench's 1U body (J ~ 2e-3 kg m^2) 1e-3 A m^2 in 30 uT is 3e-8 N m, which turns in body axes
    at ~2n once the body is near rest; undamped that is a rate of 3e-8/(J 2n) ~ 0.4 deg/s, and
    against a rate damper of gain k a floor of 3e-8/k (0.09 deg/s at k = 2e-5 N m s, measured).
    Commanding -m_r cancels it up to the calibration error. (In flight m_r comes from a ground
    magnetic test or an in-flight fit.)
    """
    law: AttitudeLaw
    residual_dipole_am2: np.ndarray
    dipole_limit_am2: float

    def eval(self, x: AttitudeControlInput) -> tuple[np.ndarray, dict]:
        dipole, info = self.law.eval(x)
        if info.get("weak_or_bad_field"):
            return dipole, info
        compensated, saturated = saturate_dipole(dipole - self.residual_dipole_am2, self.dipole_limit_am2)
        return compensated, {**info, "saturated": bool(info.get("saturated")) or saturated}


@dataclass
class QuantisationErrorFeedback(LawWrapper):
    """The law's dipole rounded to the board's step here, with each cycle's rounding error carried
    to the next (first-order sigma-delta), so that the coils' dipole *averaged over a few cycles* is
    the law's, not the law's rounded.

    Why: the board rounds every command to `dipole_resolution_am2` (1e-3 A m^2 on the bench), so a
    law asking for less than half a step gets nothing: 1.5e-8 N m in 30 uT. The gains that let a
    magnetorquer-only loop converge are the low ones (control slower than the field turns, ~2n),
    whose torques near the target are 1e-9..1e-8 N m: all inside that dead zone without this
    (docs/attitude.md). The carried error stays within half a step per axis (|e| <= step/2), so the
    torque error averages out over seconds while the attitude moves over hundreds of seconds.
    A command the law saturated is not carried (the coil cannot give more anyway).
    """
    law: AttitudeLaw
    dipole_resolution_am2: float
    dipole_limit_am2: float
    _carried_am2: np.ndarray = field(default_factory=lambda: np.zeros(3), repr=False)

    def eval(self, x: AttitudeControlInput) -> tuple[np.ndarray, dict]:
        dipole, info = self.law.eval(x)
        if info.get("weak_or_bad_field") or not np.all(np.isfinite(dipole)):
            self._carried_am2 = np.zeros(3)      # never carry across a cycle that commanded nothing
            return dipole, info
        wanted = np.asarray(dipole, float) + self._carried_am2
        step = self.dipole_resolution_am2
        unclipped = np.round(wanted / step) * step
        rounded, saturated = saturate_dipole(unclipped, self.dipole_limit_am2)
        self._carried_am2 = np.where(rounded == unclipped, wanted - rounded, 0.0)
        return rounded, {**info, "saturated": bool(info.get("saturated")) or saturated}
