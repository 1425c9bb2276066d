"""Deadline misses, cycle times and solve times of a run, from the recording and the plant.

Two views of the same deadline, in both loops:
- the controller's: DeadlineEvents on `event/deadline` (process "controller"), one per miss,
  and its cycle time per step = commanded - controller_received of the command's header (the
  loop's command topic: command/thrust or command/dipole);
- the plant's (real-time mode): a step whose command was not in when the step was integrated has
  no `plant_received` stamp in trajectory.npz.
A plant-side miss in a step the controller met its budget was lost to transport (or to the
estimator), not to the controller: the report counts both kinds separately.
The attitude loop's planner (planner.json) plans outside the control deadline: each plan's wall
time is set against its own cap (real time: max_planning_wall_s; lock-step has none).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from bench.bus import keys
from bench.report.rundata import RunData


@dataclass
class DeadlineResult:
    budget_s: float | None
    cycle_seq: np.ndarray                   # steps with a controller cycle time
    cycle_time_s: np.ndarray
    solve_time_s: np.ndarray
    controller_miss_seq: list[int]
    fallbacks: dict[str, int]               # fallback name -> commands it produced
    plant_miss_seq: list[int] = field(default_factory=list)
    events_by_process: dict[str, int] = field(default_factory=dict)
    # the controller's own summary (deadline_controller.json): how late the OS woke it after a
    # worker timeout, the host's share of an overrun that the recording cannot show
    host_wake_late_max_s: float | None = None
    cycle_time_less_host_p99_s: float | None = None
    # real time: estimates the controller passed over for a newer one queued behind them (its
    # count, and the steps of the recorded estimates that got no command)
    stale_estimates_skipped: int | None = None
    passed_over_seq: list[int] = field(default_factory=list)
    # the attitude planner: per plan, the simulated time it started from and its wall time
    plan_time_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    plan_wall_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    plan_budget_s: float | None = None
    # Parts provided from outside the bench ([run] external): their cycle time and stamps are
    # their own claims, not measured here, so no cycle time is taken from them.
    external: list[str] = field(default_factory=list)

    @property
    def plant_misses_controller_slow(self) -> int:
        """Plant-side misses whose cycle was over budget or never ran (its estimate passed over)."""
        return len(set(self.plant_miss_seq) & (set(self.controller_miss_seq) | set(self.passed_over_seq)))

    @property
    def plant_misses_transport_slow(self) -> int:
        return len(self.plant_miss_seq) - self.plant_misses_controller_slow

    def to_metrics(self) -> dict:
        return {
            "budget_s": self.budget_s,
            "controller_cycles": int(self.cycle_time_s.size),
            "controller_misses": len(self.controller_miss_seq),
            "worst_cycle_time_s": float(self.cycle_time_s.max()) if self.cycle_time_s.size else None,
            "fallbacks_applied": self.fallbacks,
            "plant_missed_steps": len(self.plant_miss_seq),
            "plant_misses_controller_slow": self.plant_misses_controller_slow,
            "plant_misses_transport_slow": self.plant_misses_transport_slow,
            "events_by_process": self.events_by_process,
            "solve_time_p50_ms": _p(self.solve_time_s, 50),
            "solve_time_p99_ms": _p(self.solve_time_s, 99),
            "host_wake_late_max_s": self.host_wake_late_max_s,
            "cycle_time_less_host_p99_s": self.cycle_time_less_host_p99_s,
            "stale_estimates_skipped": self.stale_estimates_skipped,
            "external": self.external,
            **({"planner": {"plans": int(self.plan_wall_s.size), "budget_s": self.plan_budget_s,
                            "wall_time_p50_s": float(np.median(self.plan_wall_s)),
                            "worst_wall_time_s": float(self.plan_wall_s.max()),
                            "over_budget": int(np.sum(self.plan_wall_s > self.plan_budget_s))
                            if self.plan_budget_s is not None else 0}}
               if self.plan_wall_s.size else {}),
        }


def _p(values_s: np.ndarray, q: float) -> float | None:
    return float(np.percentile(values_s, q) * 1e3) if values_s.size else None


def plant_missed_steps(run: RunData) -> list[int]:
    """Real-time steps that ran on a held command: step k's command was not in when the plant
    integrated it. The attitude plant records that time itself (its plant_received stamp is the
    board's report of the command's frame, which may come a step later); the translation plant's
    plant_received is the command's arrival."""
    if run.scenario is None or run.scenario.run.mode != "real-time":
        return []
    received = run.trajectory.get("att_command_received_ns", run.trajectory.get("stamp_plant_received_ns"))
    return [] if received is None else [int(k) for k in np.flatnonzero(np.asarray(received) < 0)]


def deadlines(run: RunData) -> DeadlineResult:
    events = [m.body for m in run.on(keys.EVENT_DEADLINE)]
    events_by_process: dict[str, int] = {}
    for e in events:
        events_by_process[e["process"]] = events_by_process.get(e["process"], 0) + 1
    controller_misses = sorted({e["header"]["seq"] for e in events if e["process"] == "controller" and e["missed"]})

    attitude = run.scenario is not None and run.scenario.kind == "attitude"
    external = list(run.scenario.run.external) if run.scenario is not None else []
    seqs, cycle_s, solve_s, fallbacks = [], [], [], {}
    commanded: set[int] = set()
    for m in run.on(keys.COMMAND_DIPOLE if attitude else keys.COMMAND_THRUST):
        commanded.add(m.seq)
        stamps, body = m.stamps_ns, m.body
        if "controller" in external:
            continue     # its stamps and solve times are its own claims: not a measured cycle
        if "controller_received" in stamps and "commanded" in stamps:
            seqs.append(m.seq)
            cycle_s.append((stamps["commanded"] - stamps["controller_received"]) / 1e9)
        if body.get("fallback"):
            fallbacks[body["fallback"]] = fallbacks.get(body["fallback"], 0) + 1
        elif "solve_time_s" in body:
            solve_s.append(float(body["solve_time_s"]))   # a fallback's solve time is not a solve
    summary = _json_dict(run.run_dir / "deadline_controller.json")
    budget = summary.get("budget_s")
    if budget is None and run.scenario is not None:
        budget = run.scenario.controller.deadline.budget_s
    plan_time_s, plan_wall_s, plan_budget_s = _planner(run)
    passed_over = []
    if run.scenario is not None and run.scenario.run.mode == "real-time":
        estimated = {m.seq for m in run.on(keys.ESTIMATE_ATTITUDE if attitude else keys.ESTIMATE_TRANSLATION)}
        passed_over = sorted(estimated - commanded)
    return DeadlineResult(
        budget_s=budget,
        cycle_seq=np.asarray(seqs, dtype=int),
        cycle_time_s=np.asarray(cycle_s, dtype=float),
        solve_time_s=np.asarray(solve_s, dtype=float),
        controller_miss_seq=controller_misses,
        fallbacks=fallbacks,
        plant_miss_seq=plant_missed_steps(run),
        events_by_process=events_by_process,
        host_wake_late_max_s=summary.get("host_wake_late_max_s"),
        cycle_time_less_host_p99_s=summary.get("cycle_time_less_host_p99_s"),
        stale_estimates_skipped=summary.get("stale_estimates_skipped"), passed_over_seq=passed_over,
        plan_time_s=plan_time_s, plan_wall_s=plan_wall_s, plan_budget_s=plan_budget_s, external=external,
    )


def _json_dict(path) -> dict:
    try:
        value = json.loads(path.read_text()) if path.is_file() else {}
    except (OSError, ValueError):
        return {}
    return value if isinstance(value, dict) else {}


def _planner(run: RunData) -> tuple[np.ndarray, np.ndarray, float | None]:
    """(start time of each plan [simulated s], its planning wall time [s], the wall-time cap)."""
    plans = [p for p in _json_dict(run.run_dir / "planner.json").get("plans", [])
             if isinstance(p, dict) and "wall_time_s" in p and "time_s" in p]
    budget = None
    if run.scenario is not None and run.scenario.kind == "attitude" and run.scenario.run.mode == "real-time":
        budget = float(run.scenario.attitude_control.planner.max_planning_wall_s)
    return (np.asarray([p["time_s"] for p in plans], float), np.asarray([p["wall_time_s"] for p in plans], float),
            budget)
