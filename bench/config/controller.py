"""Scenario sections [controller] (which translational controller and its weights, seed 003) and
[attitude_control] (which attitude law, its gains and target, and what the flight side believes).
"""
from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from bench.data import load_reference

SEED_WEIGHTS = load_reference()["weights"]     # Q*, horizons and tube poles of seed 003
Seconds = Annotated[float, msgspec.Meta(ge=0, le=60.0)]
PositiveSeconds = Annotated[float, msgspec.Meta(gt=0, le=60.0)]
FallbackPolicy = Literal["hold", "shifted_plan", "lqr"]
# Processes that apply a StressConfig (call StressInjector(config, name).apply(cycle) in their
# loop): the controller per cycle, the planner per plan (its "cycle" is the plan's number: a slow
# planner, to show lock-step runs do not depend on planning time). Another name is refused.
StressedProcess = Literal["controller", "planner"]
PositiveWeights = Annotated[list[Annotated[float, msgspec.Meta(gt=0, le=1e12)]], msgspec.Meta(min_length=1, max_length=64)]
# The QP grows with N (3N inputs, 6N states); 1000 steps is already a 9000-variable QP per cycle.
Horizon = Annotated[int, msgspec.Meta(ge=1, le=1000)]


class StressConfig(msgspec.Struct, forbid_unknown_fields=True):
    """Extra time added to chosen cycles of one process, to make deadline misses on purpose.

    A cycle i (0-based) is stressed if i is in `cycles`, or if `every_nth_cycle` = N > 0 and
    (i + 1) is a multiple of N (the Nth, 2Nth, ... cycle). Over n cycles that is exactly
    len({i in cycles, i < n} | {N-1, 2N-1, ...}) stressed cycles: tests can count them.
    """

    process: StressedProcess = "controller"
    extra_cycle_time_s: Seconds = 0.0
    cycles: Annotated[list[Annotated[int, msgspec.Meta(ge=0, le=100_000)]], msgspec.Meta(max_length=10_000)] = []
    every_nth_cycle: Annotated[int, msgspec.Meta(ge=0, le=100_000)] = 0
    # "busy": burn CPU (load, as a slow solver would); "sleep": a pure delay (as a pre-empted one).
    kind: Literal["busy", "sleep"] = "busy"

    def is_stressed(self, cycle_index: int) -> bool:
        if self.extra_cycle_time_s <= 0:
            return False
        if cycle_index in self.cycles:
            return True
        return self.every_nth_cycle > 0 and (cycle_index + 1) % self.every_nth_cycle == 0

    def stressed_count(self, n_cycles: int) -> int:
        """How many of cycles 0..n_cycles-1 get the extra time."""
        return sum(self.is_stressed(i) for i in range(n_cycles))


class DeadlineConfig(msgspec.Struct, forbid_unknown_fields=True):
    """Scenario [controller.deadline]."""

    # Wall-clock budget from the estimate's arrival to the command being ready. The default is
    # half the step period of real-time mode at its default rate (10 steps per wall second).
    budget_s: PositiveSeconds = 0.05
    # "shifted_plan" replays the last on-time plan shifted by the cycles missed, then falls back
    # to LQR (to "hold" if no LQR law is given).
    fallback: FallbackPolicy = "hold"
    # Real-time mode runs the law in a worker process (bench/runtime/solver_worker.py); a request
    # outstanding this long gets its worker killed and restarted.
    hard_limit_s: PositiveSeconds = 2.0
    # Real-time mode: SCHED_FIFO priority of the controller's cycle thread (0: default scheduler).
    # Without it the fallback left up to 8 ms late on the loaded bench machine (solver_worker.py).
    realtime_priority: Annotated[int, msgspec.Meta(ge=0, le=99)] = 10
    stress: StressConfig = msgspec.field(default_factory=StressConfig)


class ControllerConfig(msgspec.Struct, forbid_unknown_fields=True):
    # lqr: u = K x (task 6). mpc: LQR terminal cost (17). mpc_te: terminal equality (18).
    # mpc_ts: terminal set X_LQR (19). mpc_ts_sc: mpc_ts with soft state constraints (20).
    # mpc_tube: tube MPC (23) on the out-of-plane axis [z, vz], mpc with LQR terminal cost in plane.
    # lqt: finite-horizon LQ tracking of a glide slope over the run (seed 001, bench/gnc/lqt.py).
    type: Literal["lqr", "lqt", "mpc", "mpc_te", "mpc_ts", "mpc_ts_sc", "mpc_tube"] = "lqr"
    # Q = diag(q_diag), R = diag(r_diag), on the scaled state (seed 003); defaults are Q*, R*.
    q_diag: PositiveWeights = msgspec.field(default_factory=lambda: list(SEED_WEIGHTS["q_star"]))
    r_diag: PositiveWeights = msgspec.field(default_factory=lambda: [1.0, 1.0, 1.0])
    horizon: Horizon = SEED_WEIGHTS["mpc_horizon"]      # N, prediction steps
    # mpc_ts_sc: slack penalty eps'S eps + v ||eps||_inf with S = soft_quadratic_weight * I (task 23).
    soft_quadratic_weight: Annotated[float, msgspec.Meta(gt=0, le=1e12)] = 1.0e3
    soft_linf_weight: Annotated[float, msgspec.Meta(ge=0, le=1e12)] = 1.0e5
    # mpc_tube: poles of A + B K_tube (task 31) and the out-of-plane horizon.
    tube_poles: Annotated[list[Annotated[float, msgspec.Meta(gt=-1, lt=1)]], msgspec.Meta(min_length=2, max_length=2)] = \
        msgspec.field(default_factory=lambda: list(SEED_WEIGHTS["tube_poles"]))
    tube_horizon: Horizon = SEED_WEIGHTS["tube_horizon"]
    # lqt: the glide slope reaches the target after this fraction of the run (then the LQR terminal law).
    # 0.35: from A with the tuned weights, 82 m on CWH and 36 m on the nonlinear plant; 0.75 ends 430 m off.
    lqt_glide_fraction: Annotated[float, msgspec.Meta(gt=0, le=1)] = 0.35
    # Wall-clock budget per cycle, fallback on a miss, optional stress (used by bench/controller/deadline.py).
    deadline: DeadlineConfig = msgspec.field(default_factory=DeadlineConfig)


# ---- [attitude_control] (issue 11) ------------------------------------------------------------
# A unit quaternion's components are within [-1, 1]; the unit-norm check names a wrong one.
Vec4 = Annotated[list[Annotated[float, msgspec.Meta(ge=-1.5, le=1.5)]], msgspec.Meta(min_length=4, max_length=4)]
# Gains span decades (kp 1e-5 N m, B-dot 1e4 A m^2 s/T); 1e12 is far above any that flies.
PositiveGain = Annotated[float, msgspec.Meta(gt=0, le=1e12)]
Angle180 = Annotated[float, msgspec.Meta(gt=0, le=180.0)]

# Attitude laws by the scenario's name: "module:builder", the builder taking the scenario and
# returning an object with eval(AttitudeControlInput) -> (dipole_am2, info). Strings, so the
# scenario checks names without importing the flight software; a new law is one line here.
ATTITUDE_LAWS: dict[str, str] = {
    "bdot": "bench.controller.attitude_laws:bdot",
    "sliding_mode": "bench.controller.attitude_laws:sliding_mode",
    "pd": "bench.controller.attitude_laws:pd",
    "rate_damping": "bench.controller.attitude_laws:rate_damping",
    # B-dot, then gyro rate damping below [attitude_control] handover_rate_dps
    "bdot_then_rate_damping": "bench.controller.attitude_laws:bdot_then_rate_damping",
    # issue 12: TVLQR tracking of the planner process's MILQR plans ([attitude_control.planner])
    "tvlqr_plan": "bench.controller.plan_tracking:tvlqr_plan",
}
# Laws whose plans come from `bench node planner` (the launcher starts it for them).
PLANNED_LAWS = {"tvlqr_plan"}
# Laws that need no attitude estimate (they fly before the smoother's first fix).
ATTITUDE_FREE_LAWS = {"bdot"}
# Laws with no attitude target (rate laws): no pointing error to report.
TARGET_FREE_LAWS = {"bdot", "rate_damping", "bdot_then_rate_damping"}


class AttitudeTargetConfig(msgspec.Struct, forbid_unknown_fields=True):
    # "inertial": hold q_wxyz (target to inertial). "nadir": body z to nadir, body x along the
    # velocity (the orbit of [attitude.orbit], which the flight side knows).
    kind: Literal["inertial", "nadir"] = "inertial"
    q_wxyz: Vec4 = msgspec.field(default_factory=lambda: [1.0, 0.0, 0.0, 0.0])


class AttitudePlannerConfig(msgspec.Struct, forbid_unknown_fields=True):
    """[attitude_control.planner] (issue 12): MILQR planning in `bench node planner`, TVLQR tracking
    in the controller (law "tvlqr_plan"). The target is [attitude_control.target] (inertial only:
    MILQR's goal is one attitude at rest)."""
    # MILQR step; the dipole is held over it. max_horizon_s / plan_step_s is at most 1e4 steps (bench.scenario).
    plan_step_s: Annotated[float, msgspec.Meta(gt=0, le=3600.0)] = 20.0
    # cond(W) tolerance of the Gramian horizon (bench.gnc.attitude_planning: 3 is its reasoned
    # default, ~27 min on the bench's orbits); a larger one gives a shorter horizon.
    gramian_condition_tolerance: Annotated[float, msgspec.Meta(gt=1, le=1e12)] = 3.0
    max_horizon_s: Annotated[float, msgspec.Meta(gt=0, le=86400.0)] = 5400.0   # the horizon if the tolerance is never met
    max_iterations: Annotated[int, msgspec.Meta(ge=1, le=10_000)] = 200
    # Real-time only: MILQR's wall-time cap (returns its best iterate). Lock-step ignores it so that
    # a run does not depend on how busy the machine was (the iteration cap still holds).
    max_planning_wall_s: Annotated[float, msgspec.Meta(gt=0, le=3600.0)] = 60.0
    # No first plan before this (s of simulated time): the smoother's gyro-bias estimate converges
    # first. A plan flown on a rate still off by the initial bias (1.8e-3 rad/s at t = 0, 5e-5 rad/s
    # at 30 s on attitude_slew_milqr) left the plan by 10 deg within 75 s; the replans that follow
    # keep the arrival time on ever shorter horizons the body cannot follow.
    first_plan_after_s: Annotated[float, msgspec.Meta(ge=0, le=86400.0)] = 0.0
    replan_period_s: Annotated[float, msgspec.Meta(gt=0, le=1e6)] = 600.0   # replan this long after the current plan's start
    replan_error_deg: Angle180 = 10.0                # ... or when the estimate is this far off the plan
    min_replan_interval_s: Seconds = 30.0            # no error-triggered replan sooner than this
    # Until the first plan arrives (real-time: planning takes seconds) the controller commands
    # zero, or this law of the registry, and counts the cycles.
    fallback_law: Literal["zero", "pd", "sliding_mode"] = "zero"
    # Control cycles of planned feed-forward each command carries for the "shifted_plan" fallback.
    # At most 1000: each cycle is three floats in every command message (the recorder keeps 256 kB a message).
    feedforward_cycles: Annotated[int, msgspec.Meta(ge=1, le=1000)] = 100
    # Lock-step: how long the controller waits for the plan it knows is due before going on without.
    plan_wait_timeout_s: Annotated[float, msgspec.Meta(gt=0, le=3600.0)] = 300.0
    # Tracker weights (Bryson's rule): tolerated attitude and rate deviation, and terminal factor.
    tracking_attitude_deviation_deg: Angle180 = 1.0
    tracking_rate_deviation_radps: Annotated[float, msgspec.Meta(gt=0, le=100.0)] = 5e-4
    # Every plan ends with a hold of the target at rest this long after the arrival, tracked with
    # TVLQR gains designed along the field of the hold (without it the tracker held the arrival
    # with the last step's gain: 1.04 deg drifted to 3.8 deg in 220 s on attitude_slew_milqr).
    hold_after_arrival_s: Annotated[float, msgspec.Meta(ge=0, le=86400.0)] = 600.0


class FdirConfig(msgspec.Struct, forbid_unknown_fields=True):
    """[attitude_control.fdir]: the FDIR actuator monitor (bench.gnc.actuator_monitor; docs/fdir.md
    gives the calibration behind the defaults: 0 alarms on every fault-free built-in scenario)."""
    enabled: bool = True
    # Reaction on a detected coil fault: a reversed coil's command sign-flipped, an open or stuck
    # coil's torque asked of the two coils left (bench.gnc.actuator_monitor.accommodate).
    accommodate: bool = False
    window_s: Annotated[float, msgspec.Meta(gt=0, le=3600.0)] = 60.0
    min_window_s: Annotated[float, msgspec.Meta(gt=0, le=3600.0)] = 20.0
    evaluate_every_s: Annotated[float, msgspec.Meta(gt=0, le=3600.0)] = 1.0
    gain_tolerance: Annotated[float, msgspec.Meta(gt=0, le=10.0)] = 0.3
    offset_tolerance_am2: Annotated[float, msgspec.Meta(gt=0, le=100.0)] = 0.01
    threshold: Annotated[float, msgspec.Meta(gt=0, le=1e9)] = 40.0
    persistence: Annotated[int, msgspec.Meta(ge=1, le=1000)] = 3
    max_gain_std: Annotated[float, msgspec.Meta(gt=0, le=10.0)] = 0.08
    # The system-level check (bench.gnc.pointing_envelope): an event when the law's pointing error
    # stays above this many degrees for pointing_persistence_s (a hold's pointing requirement);
    # None: not watched (a slew's error to its final target is large by design, a detumble has none).
    pointing_error_limit_deg: Annotated[float, msgspec.Meta(gt=0, le=180.0)] | None = None
    pointing_persistence_s: Annotated[float, msgspec.Meta(ge=0, le=3600.0)] = 10.0


class AttitudeControlConfig(msgspec.Struct, forbid_unknown_fields=True):
    law: Annotated[str, msgspec.Meta(max_length=64)] = "bdot"   # a key of ATTITUDE_LAWS above
    # No lower bound here so that a zero or negative limit gets the scenario's own message; at most
    # 100 A m^2 (the board's own limit, 3.2 in the DBC, applies when there is a [can] section).
    dipole_limit_am2: Annotated[float, msgspec.Meta(le=100.0)] | None = None   # default: [can.board] max_dipole_am2
    # Believed; default: [attitude] inertia_kgm2 (kg m^2, 3 moments or 9 entries).
    inertia_kgm2: Annotated[list[Annotated[float, msgspec.Meta(ge=-1e9, le=1e9)]],
                            msgspec.Meta(min_length=3, max_length=9)] | None = None
    target: AttitudeTargetConfig = msgspec.field(default_factory=AttitudeTargetConfig)
    # B-dot: m = -k dB/dt. Avanzini & Giulietti (2012) give k = 2 n (1 + sin xi) J_min / |B|^2,
    # ~1e4 A m^2 s / T for the default body at 500 km. Measured here: 5e5 (too high) locks the spin
    # to the field and stalls at ~2.7 deg/s for two orbits; 1e4 reaches 0.3 deg/s in 3200 s.
    bdot_gain_am2_s_per_t: PositiveGain = 1.0e4
    # Rate damping: tau = -k omega_perp (N m s). k/J is the damping rate of the rate across B;
    # 2e-5 on the 1U body (J ~ 2e-3) is 1/100 s, and saturates (0.2 A m^2) only above ~0.3 rad/s.
    rate_damping_gain_nms: PositiveGain = 2.0e-5
    handover_rate_dps: PositiveGain = 0.5    # bdot_then_rate_damping: B-dot above, rate damping below
    # The spacecraft's residual dipole as calibrated (A m^2, body axes); every law's command is
    # offset by minus this (bench.gnc.attitude_law.ResidualDipoleCompensation). Zero: none.
    residual_dipole_compensation_am2: Annotated[list[Annotated[float, msgspec.Meta(ge=-100.0, le=100.0)]],
                                                msgspec.Meta(min_length=3, max_length=3)] = \
        msgspec.field(default_factory=lambda: [0.0, 0.0, 0.0])
    # Round the law's dipole to the board's step in the law and carry the rounding error to the next
    # cycle (bench.gnc.attitude_law.QuantisationErrorFeedback): without it the board's rounding
    # zeroes every torque under ~1.5e-8 N m, which is all a converging low-gain law asks for.
    quantisation_error_feedback: bool = False
    # Seed 002 sliding mode (lambda, k) and PD (kp, kd).
    sliding_gain_radps: PositiveGain = 0.05
    convergence_gain_radps: PositiveGain = 0.02
    kp_nm: PositiveGain = 1.0e-5
    kd_nms: PositiveGain = 5.0e-4
    planner: AttitudePlannerConfig = msgspec.field(default_factory=AttitudePlannerConfig)
    # FDIR actuator monitor: coil faults from the dynamics (bench.gnc.actuator_monitor)
    fdir: FdirConfig = msgspec.field(default_factory=FdirConfig)
