"""TVLQR tracking of a planned magnetorquer attitude manoeuvre (seed 000 applied to seed 004's plans).

A plan is a time base (start, step), the planned states x_0..x_N, the planned dipoles u_0..u_{N-1}
(held over each step) and one gain per step. The law, evaluated at the control rate:

    dx = [phi; omega - omega_ref],  phi = Rodrigues parameters of q_ref* (x) q   (body-frame error)
    m  = clamp(u_bar_k - K_k dx, +-limit per axis)

The attitude error uses the inverse Cayley map, not the log map of seed 000's slide: the gains are
computed on Jacobians in Rodrigues coordinates (`bench.gnc.attitude_planning`), and the log map's
rotation vector is twice as large for small errors (log = 2 phi + O(phi^3)), which would double the
attitude gain. Between plan samples the reference attitude is slerped and the reference rate
interpolated linearly; the feed-forward and the gain are those of the step (zero-order hold, as
planned). Past the plan's end the law holds the final planned state with zero feed-forward and the
last step's gain: a stop-gap until the next plan arrives (that gain was designed for the field at
the plan's end; as the field turns it is not a designed regulator any more).

Given the control period, `eval` also returns the plan's feed-forward for this and the next
`feedforward_cycles - 1` control cycles as `info["u_plan"]` (zero past the plan's end, as the law
itself): the deadline monitor's "shifted_plan" fallback (`bench.controller.deadline`) replays it
when a later cycle misses its deadline.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.gnc import quaternion as qt
from bench.gnc.attitude_law import AttitudeControlInput, saturate_dipole
from bench.gnc.tvlqr import tvlqr_gains, tracking_control


@dataclass(frozen=True)
class AttitudePlan:
    start_time_s: float
    dt_s: float
    states: np.ndarray           # (N+1, 7) [q_wxyz, omega_radps]
    dipoles_am2: np.ndarray      # (N, 3) body axes
    gains: np.ndarray            # (N, 3, 6) u = u_bar - K dx, dx = [Rodrigues phi; d_omega]
    plan_id: int = 0
    # The last hold_steps steps hold the target at rest after the arrival (zero feed-forward, TVLQR
    # gains designed along the field of those steps): the manoeuvre arrives at arrival_time_s. All
    # of them: a plan that only holds (bench.planner.plan.hold_plan), arrived at its start.
    hold_steps: int = 0

    def __post_init__(self):
        states, dipoles, gains = (np.asarray(a, dtype=float) for a in (self.states, self.dipoles_am2, self.gains))
        N = dipoles.shape[0]
        if states.shape != (N + 1, 7) or dipoles.shape != (N, 3) or gains.shape != (N, 3, 6) or N == 0:
            raise ValueError(f"plan shapes must be states (N+1, 7), dipoles (N, 3), gains (N, 3, 6) with N > 0; "
                             f"got {states.shape}, {dipoles.shape}, {gains.shape}")
        for name, a in (("states", states), ("dipoles_am2", dipoles), ("gains", gains)):
            if not np.all(np.isfinite(a)):
                raise ValueError(f"plan {name} contains non-finite values")
        if not 0 <= self.hold_steps <= N:
            raise ValueError(f"plan hold_steps must be 0..{N} (at most its {N} steps), got {self.hold_steps}")
        if not (np.isfinite(self.dt_s) and self.dt_s > 0 and np.isfinite(self.start_time_s)):
            raise ValueError(f"plan time base must be finite with dt_s > 0, got start {self.start_time_s}, dt {self.dt_s}")
        object.__setattr__(self, "states", states)
        object.__setattr__(self, "dipoles_am2", dipoles)
        object.__setattr__(self, "gains", gains)

    @property
    def steps(self) -> int:
        return self.dipoles_am2.shape[0]

    @property
    def end_time_s(self) -> float:
        return self.start_time_s + self.steps * self.dt_s

    @property
    def arrival_time_s(self) -> float:
        """End of the manoeuvre (the hold after it excluded)."""
        return self.start_time_s + (self.steps - self.hold_steps) * self.dt_s


def tvlqr_gains_along(model, states: np.ndarray, dipoles_am2: np.ndarray, Q, R, Q_final) -> np.ndarray:
    """TVLQR gains (N, 3, 6) on the reduced Jacobians of `model` along a planned trajectory (seed 000)."""
    A, B = model.linearise(states, dipoles_am2)
    K, _ = tvlqr_gains(A, B, Q, R, Q_final)
    return K


def _slerp(q0: np.ndarray, q1: np.ndarray, fraction: float) -> np.ndarray:
    delta = qt.multiply(qt.conjugate(q0), q1)
    return qt.multiply(q0, qt.exp(fraction * qt.log(delta)))


class TvlqrAttitudeTracker:
    """Attitude law (`bench.gnc.attitude_law.AttitudeLaw`): tracks an `AttitudePlan`; `eval(x)`
    returns the body dipole (A m^2, saturated per axis) and info. The measured field is not used by
    the law (the plan's gains carry the field model); it is only checked like the other inputs."""

    def __init__(self, plan: AttitudePlan, dipole_limit_am2: float, control_period_s: float | None = None,
                 feedforward_cycles: int = 100):
        if not (np.isfinite(dipole_limit_am2) and dipole_limit_am2 > 0):
            raise ValueError(f"dipole_limit_am2 must be positive, got {dipole_limit_am2}")
        if control_period_s is not None and not (np.isfinite(control_period_s) and control_period_s > 0):
            raise ValueError(f"control_period_s must be positive, got {control_period_s}")
        if feedforward_cycles < 1:
            raise ValueError(f"feedforward_cycles must be at least 1, got {feedforward_cycles}")
        self.plan = plan
        self.dipole_limit_am2 = float(dipole_limit_am2)
        self.control_period_s = control_period_s
        self.feedforward_cycles = int(feedforward_cycles)

    def feedforward_ahead(self, time_s: float) -> np.ndarray:
        """(feedforward_cycles, 3): the planned dipole at time_s + i * control_period_s (zero-order
        hold per plan step, as planned; the first step's before the plan's start and zero after its
        end, as `reference` does)."""
        plan = self.plan
        times = time_s + self.control_period_s * np.arange(self.feedforward_cycles)
        index = np.maximum(np.floor((times - plan.start_time_s) / plan.dt_s).astype(int), 0)
        inside = index < plan.steps
        ahead = np.zeros((self.feedforward_cycles, 3))
        ahead[inside] = plan.dipoles_am2[index[inside]]
        return ahead

    def reference(self, time_s: float):
        """(q_ref, omega_ref, u_bar, K, step index, phase) at time_s."""
        plan = self.plan
        elapsed = (time_s - plan.start_time_s) / plan.dt_s
        if elapsed >= plan.steps:
            x_end = plan.states[-1]
            return x_end[:4], x_end[4:], np.zeros(3), plan.gains[-1], plan.steps, "after_plan"
        phase = "in_plan"
        if elapsed < 0:
            elapsed, phase = 0.0, "before_plan"
        k = int(np.floor(elapsed))
        fraction = elapsed - k
        x0, x1 = plan.states[k], plan.states[k + 1]
        q_ref = _slerp(x0[:4], x1[:4], fraction)
        omega_ref = (1.0 - fraction) * x0[4:] + fraction * x1[4:]
        return q_ref, omega_ref, plan.dipoles_am2[k], plan.gains[k], k, phase

    def eval(self, x: AttitudeControlInput) -> tuple[np.ndarray, dict]:
        q = np.asarray(x.q_wxyz, dtype=float)
        omega = np.asarray(x.omega_radps, dtype=float)
        for name, value in (("time_s", np.asarray(x.time_s, dtype=float)), ("q_wxyz", q), ("omega_radps", omega),
                            ("field_body_t", np.asarray(x.field_body_t, dtype=float))):
            if not np.all(np.isfinite(value)) or (name == "q_wxyz" and np.linalg.norm(value) < 1e-12):
                # as the other laws of bench.gnc.attitude_law: command nothing and say why
                return np.zeros(3), {"bad_input": name, "saturated": False, "plan_id": self.plan.plan_id}
        q_ref, omega_ref, u_bar, K, k, phase = self.reference(float(x.time_s))
        dx = qt.error_state(qt.normalize(q), omega, q_ref, omega_ref)
        dipole, saturated = saturate_dipole(tracking_control(u_bar, K, dx), self.dipole_limit_am2)
        info = {
            "bad_input": None,
            "saturated": saturated,
            "plan_id": self.plan.plan_id,
            "plan_step": k,
            "phase": phase,
            "attitude_error_rad": qt.angle_between_rad(q_ref, q),
            "rate_error_radps": float(np.linalg.norm(omega - omega_ref)),
            "feedforward_am2": u_bar,
        }
        if self.control_period_s is not None:
            info["u_plan"] = self.feedforward_ahead(float(x.time_s))
        return dipole, info
