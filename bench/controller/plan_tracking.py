"""The "tvlqr_plan" attitude law: TVLQR tracking of the newest MILQR plan (issue 12), and the
controller's inbox of plans from `bench node planner`.

`PlanTrackingLaw` is an attitude law (`eval(AttitudeControlInput) -> (dipole_am2, info)`) that
holds the newest plan and tracks it with `bench.gnc.attitude_tracking.TvlqrAttitudeTracker` at the
control rate; each command's info carries the plan's feed-forward for the next cycles
(`info["u_plan"]`), which the deadline monitor's "shifted_plan" fallback replays on a miss. Before
the first plan it commands zero, or the configured fallback law, says so in info
(`waiting_for_plan`) and counts the cycles.

`PlanInbox` receives plan messages on the Zenoh thread. A message that does not decode is counted
by the node context; one that decodes but whose arrays do not fit together or are not finite
(`bench.bus.plan_message.from_message` raises) is counted here and ignored: neither stops the
controller. Lock-step: the controller runs the planner's own rule (`replan_reason`) on the same
estimate and the same current plan, and when a plan is due it waits for the plan made from this
step's estimate (the message's header.seq), so the run does not depend on planning time.
Real-time: it takes the newest plan whenever one has arrived and never waits.
"""
from __future__ import annotations

import threading
import time

import numpy as np

from bench.bus import keys
from bench.bus.plan_message import AttitudePlanMessage, from_message
from bench.controller.attitude_laws import dipole_limit_am2
from bench.config.controller import AttitudePlannerConfig
from bench.gnc import quaternion as qt
from bench.gnc.attitude_law import AttitudeControlInput, AttitudeLaw
from bench.gnc.attitude_tracking import AttitudePlan, TvlqrAttitudeTracker
from bench.scenario import Scenario



# The replan rule: the planner applies it to decide when to plan, and the controller in lock-step
# to know when a plan is due (it waits for the plan made from that step's estimate).
UNIT_NORM_TOLERANCE = 1e-6      # as the controller's cycle: a non-unit estimate is not flown on


def plan_tracking_error_rad(plan: AttitudePlan, time_s: float, q_wxyz) -> float:
    """Angle between the estimate and the plan's reference attitude at time_s."""
    q_ref = TvlqrAttitudeTracker(plan, 1.0).reference(time_s)[0]
    return qt.angle_between_rad(q_ref, np.asarray(q_wxyz, float))


def replan_reason(time_s: float, valid: bool, q_wxyz, plan: AttitudePlan | None,
                  settings: AttitudePlannerConfig) -> str | None:
    """"first_plan", "schedule", "tracking_error" or None (no plan due)."""
    q = np.asarray(q_wxyz, float)
    if not valid or not np.all(np.isfinite(q)) or abs(np.linalg.norm(q) - 1.0) > UNIT_NORM_TOLERANCE:
        return None
    if plan is None:
        return "first_plan" if time_s >= settings.first_plan_after_s else None
    since_s = time_s - plan.start_time_s
    if since_s >= settings.replan_period_s:
        return "schedule"
    if since_s >= settings.min_replan_interval_s and \
            plan_tracking_error_rad(plan, time_s, q) > np.deg2rad(settings.replan_error_deg):
        return "tracking_error"
    return None


class PlanTrackingLaw:
    def __init__(self, dipole_limit_am2: float, control_period_s: float, feedforward_cycles: int,
                 fallback: AttitudeLaw | None = None, fallback_name: str = "zero"):
        self.dipole_limit_am2 = dipole_limit_am2
        self.control_period_s = control_period_s
        self.feedforward_cycles = feedforward_cycles
        self.fallback, self.fallback_name = fallback, fallback_name
        self.tracker: TvlqrAttitudeTracker | None = None
        self.cycles_without_plan = 0
        self.plans_applied = 0

    @property
    def plan(self) -> AttitudePlan | None:
        return None if self.tracker is None else self.tracker.plan

    def set_plan(self, plan: AttitudePlan) -> None:
        self.tracker = TvlqrAttitudeTracker(plan, self.dipole_limit_am2, self.control_period_s, self.feedforward_cycles)
        self.plans_applied += 1

    def eval(self, x: AttitudeControlInput) -> tuple[np.ndarray, dict]:
        if self.tracker is not None:
            return self.tracker.eval(x)
        self.cycles_without_plan += 1
        if self.fallback is None:
            return np.zeros(3), {"saturated": False, "waiting_for_plan": True, "acting_law": "zero"}
        dipole, info = self.fallback.eval(x)
        return dipole, {**info, "waiting_for_plan": True, "acting_law": self.fallback_name}


def tvlqr_plan(s: Scenario) -> AttitudeLaw:
    """Registry builder (bench.config.controller.ATTITUDE_LAWS)."""
    from bench.controller.attitude_laws import pd, sliding_mode

    settings = s.attitude_control.planner
    fallback = {"zero": None, "pd": pd, "sliding_mode": sliding_mode}[settings.fallback_law]
    return PlanTrackingLaw(dipole_limit_am2(s), s.step_s, settings.feedforward_cycles,
                           None if fallback is None else fallback(s), settings.fallback_law)


class PlanInbox:
    """Valid plans as they arrive, by the estimate seq they were planned from."""

    def __init__(self):
        self._cond = threading.Condition()
        self._plans: dict[int, AttitudePlan] = {}
        self._newest: AttitudePlan | None = None
        self.received = 0
        self.rejected = 0
        self.last_rejection: str | None = None

    def add(self, message: AttitudePlanMessage) -> str | None:
        """Take a decoded message; the reason it was refused, or None."""
        try:
            plan = from_message(message)
        except ValueError as exc:
            with self._cond:
                self.rejected += 1
                self.last_rejection = str(exc)
            return str(exc)
        with self._cond:
            self.received += 1
            self._plans[message.header.seq] = plan
            for seq in sorted(self._plans)[:-8]:     # keep the last few
                del self._plans[seq]
            if self._newest is None or plan.plan_id > self._newest.plan_id:
                self._newest = plan
            self._cond.notify_all()
        return None

    def newest(self) -> AttitudePlan | None:
        with self._cond:
            return self._newest

    def wait_for(self, seq: int, timeout_s: float, stop: threading.Event | None = None) -> AttitudePlan | None:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while seq not in self._plans:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or (stop is not None and stop.is_set()):
                    return None
                self._cond.wait(min(remaining, 0.2))
            return self._plans[seq]


class PlanFollower:
    """The controller's side of planning: which plan the law tracks at each estimate."""

    def __init__(self, ctx, law: PlanTrackingLaw):
        self.ctx, self.law = ctx, law
        self.settings = ctx.scenario.attitude_control.planner
        # Lock-step waits for a plan that is due (the planner takes every estimate: it is on its
        # way); real time tracks the newest plan in (bench/runtime/time_model.py).
        self.waits_for_due_plan = ctx.time_model.takes_every_message
        self.inbox = PlanInbox()
        self.waits_timed_out = 0
        self._said_waiting = False
        ctx.subscribe(keys.PLAN_ATTITUDE, AttitudePlanMessage, self._on_plan)

    def _on_plan(self, message: AttitudePlanMessage) -> None:
        refused = self.inbox.add(message)
        if refused is not None:
            self.ctx.malformed[keys.PLAN_ATTITUDE] += 1
            self.ctx.log.warning("plan message %d ignored: %s", message.header.seq, refused)

    def before_cycle(self, seq: int, time_s: float, valid: bool, q_wxyz) -> None:
        if self.waits_for_due_plan:
            if replan_reason(time_s, valid, q_wxyz, self.law.plan, self.settings) is not None:
                plan = self.inbox.wait_for(seq, self.settings.plan_wait_timeout_s, self.ctx.stop)
                if plan is None:
                    self.waits_timed_out += 1
                    self.ctx.log.error("no plan for step %d after %.0f s; tracking the previous one", seq,
                                       self.settings.plan_wait_timeout_s)
                else:
                    self.law.set_plan(plan)
        else:
            newest = self.inbox.newest()
            if newest is not None and (self.law.plan is None or newest.plan_id > self.law.plan.plan_id):
                self.law.set_plan(newest)
        if self.law.plan is None and not self._said_waiting:
            self._said_waiting = True
            self.ctx.log.info("no plan yet: commanding %s until the planner's first plan arrives",
                              self.law.fallback_name)

    def summary(self) -> dict:
        return {"plans_received": self.inbox.received, "plans_rejected": self.inbox.rejected,
                "plans_applied": self.law.plans_applied, "cycles_without_plan": self.law.cycles_without_plan,
                "plan_waits_timed_out": self.waits_timed_out, "last_plan_rejection": self.inbox.last_rejection}
