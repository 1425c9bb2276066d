"""The attitude plan message, planner -> controller on `plan/attitude` (seed 004 plans, seed 000 gains).

Both ends speak it, so it lives on the bus: the planner process encodes an `AttitudePlan` with
`to_message`; the controller decodes with `bench.bus.schemas.decode(payload, AttitudePlanMessage)`
and rebuilds the plan with `from_message`, which rejects arrays that do not fit together.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Annotated

import msgspec
import numpy as np

from bench.bus.schemas import Header, Message

if TYPE_CHECKING:
    from bench.gnc.attitude_tracking import AttitudePlan

Vec3 = Annotated[list[float], msgspec.Meta(min_length=3, max_length=3)]
State7 = Annotated[list[float], msgspec.Meta(min_length=7, max_length=7)]
Gain18 = Annotated[list[float], msgspec.Meta(min_length=18, max_length=18)]   # 3x6 row-major


class AttitudePlanMessage(Message, tag="attitude_plan"):
    """A MILQR plan: N+1 states, N dipoles (body, A m^2) and N TVLQR gains (u = u_bar - K dx,
    dx = [Rodrigues phi; d_omega]), sample k at start_time_s + k dt_s."""
    plan_id: Annotated[int, msgspec.Meta(ge=0)]
    start_time_s: float
    dt_s: Annotated[float, msgspec.Meta(gt=0)]
    states: list[State7]
    dipoles_am2: list[Vec3]
    gains: list[Gain18]
    target_wxyz: Annotated[list[float], msgspec.Meta(min_length=4, max_length=4)]
    stop_reason: str
    iterations: Annotated[int, msgspec.Meta(ge=0)]
    cost: float
    planning_time_s: float
    hold_steps: Annotated[int, msgspec.Meta(ge=0)] = 0     # the last steps: a hold at the target after arrival


def to_message(plan: AttitudePlan, header: Header, target_wxyz, info: dict) -> AttitudePlanMessage:
    return AttitudePlanMessage(
        header=header, plan_id=plan.plan_id, start_time_s=plan.start_time_s, dt_s=plan.dt_s,
        states=plan.states.tolist(), dipoles_am2=plan.dipoles_am2.tolist(),
        gains=plan.gains.reshape(plan.steps, 18).tolist(), target_wxyz=list(map(float, target_wxyz)),
        stop_reason=info["stop_reason"], iterations=info["iterations"], cost=float(info["cost"]),
        planning_time_s=float(info["wall_time_s"]), hold_steps=plan.hold_steps)


def from_message(message: AttitudePlanMessage) -> AttitudePlan:
    """The plan carried by a decoded message; ValueError if its arrays do not fit together."""
    # Imported here, not with the schema: the schema is read where no plan is built (the launcher's
    # summary, `bench report`), and bench.gnc brings scipy.linalg (0.3 s of CPU at every start).
    from bench.gnc.attitude_tracking import AttitudePlan

    n = len(message.dipoles_am2)
    if len(message.states) != n + 1 or len(message.gains) != n:
        raise ValueError(f"AttitudePlanMessage: {len(message.states)} states, {n} dipoles and "
                         f"{len(message.gains)} gains (need N+1, N, N)")
    return AttitudePlan(message.start_time_s, message.dt_s, np.array(message.states), np.array(message.dipoles_am2),
                        np.array(message.gains).reshape(n, 3, 6), message.plan_id, message.hold_steps)
