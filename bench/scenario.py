"""Scenario files (TOML), validated on load.

A scenario is composed of one section per part of the loop; each part owns its section's schema
(`bench/config/<part>.py`). A bad file raises `ScenarioError` with one line naming the field.

Nothing a file holds may get past here and fail later: the file's size is bounded before it is
parsed and its nesting by the parser itself (tomllib's recursion, then a depth check of what it
returned); values are converted strictly (a string is never a number; an integer is a float);
every number must be finite, and every number has an upper bound (times, counts, rates, sizes,
list lengths) so no value makes a process allocate, loop or overflow without limit. The ranges
are listed in docs/run_safety.md. A key given twice is refused (JSON would keep the last one
silently), and so is an integer longer than Python converts, naming the field. A field that names
a device or an endpoint names only that: channels are devices, never URLs or files
(bench/bus/can/config.py, channel_problem).
"""
from __future__ import annotations

import json
import math
import re
import sys
import tomllib
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal, get_args

import msgspec

from bench.bus import toml_input
from bench.bus.can.config import CanConfig
from bench.config.controller import ATTITUDE_LAWS, PLANNED_LAWS, AttitudeControlConfig, ControllerConfig
from bench.config.estimator import EstimatorConfig
from bench.config.plant import (
    AttitudeConfigError, AttitudePlantConfig, check_attitude_plant, check_unit_quaternion, inertia_matrix,
)
from bench.config.plant import PlantConfig
from bench.criteria import Criteria
from bench.gnc.cwh import RendezvousParams

BUILTIN_PACKAGE = "bench.scenarios"


MAX_MESSAGE_CHARS = 1000


def one_line(text: str, limit: int = MAX_MESSAGE_CHARS) -> str:
    """`text` as one printable line: what a file put in a key or a value (a newline, an escape
    sequence, a line separator) shown escaped, and at most `limit` characters."""
    text = "".join(c if c.isprintable() else repr(c)[1:-1] for c in str(text))
    return text if len(text) <= limit else text[: limit - 3] + "..."


class ScenarioError(ValueError):
    """A scenario that cannot be run, with the field and the problem in the message (one line)."""

    def __init__(self, message: str):
        super().__init__(one_line(message))


# A scenario file larger than this is refused before it is read; one nested deeper than
# MAX_NESTING levels of tables and arrays is refused after parsing (or when tomllib runs out of
# recursion on it: a 50 000-deep array).
MAX_SCENARIO_BYTES = 1 << 20
MAX_NESTING = 32
TOML_STACK_FRAMES = 400     # see parse_toml_text
# Every step keeps a state, a command and nine stamps in the plant's memory (~200 B): 1e5 steps
# is 20 MB, and at 600 s per step 694 days of simulated time.
MAX_STEPS = 100_000
# The IGRF field is tabulated along the orbit every attitude.field.grid_s over the run (and the
# planner's horizon): at most this many points (6 floats each, one IGRF evaluation per point).
MAX_FIELD_GRID_POINTS = 1_000_000
# Rendezvous: orbit angle per plant step (mean motion x time_step_s), at most a quarter orbit.
MAX_ORBIT_ANGLE_PER_STEP_RAD = math.pi / 2
# MILQR plans max_horizon_s / plan_step_s steps (a 3x3 Riccati recursion and a rollout each).
MAX_PLAN_STEPS = 10_000
# Real-time: the wall-clock step period (time_step_s / time_factor) must be between these.
MIN_WALL_PERIOD_S = 1e-3
MAX_WALL_PERIOD_S = 60.0
# Scenario names start run ids and directory names: plain characters, no leading '.' or '-'.
NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,39}$"


# Parts a user may provide from outside the bench ([run] external, `bench run --external`).
ExternalPart = Literal["controller", "estimator", "board"]
EXTERNAL_PARTS: tuple[str, ...] = get_args(ExternalPart)


class LivelinessConfig(msgspec.Struct, forbid_unknown_fields=True):
    """[run.liveliness]: how a hung process is told from a slow one (launcher and plant).

    A process whose liveliness token vanished is hung if it is stopped (state T in /proc, e.g.
    SIGSTOP) for stopped_grace_s, or if its token stays gone for hang_timeout_s whatever it does;
    a token that comes back (a starved process whose lease lapsed) clears the suspicion. So a
    stopped node is named lease_s + stopped_grace_s after it stopped (3 s with the defaults; the
    token lapses only when Zenoh's lease expires), plus up to one 0.1 s poll of the launcher.
    """

    lease_s: Annotated[float, msgspec.Meta(ge=0.1, le=60.0)] = 2.0
    # How long the launcher waits for every node to come alive, and a node for its peers to be
    # ready. Sixteen Python processes importing numpy, gtsam and Zenoh on two cores at load 30
    # took over 60 s (benchmarks/bench_concurrent_runs.py); the launcher waits up to three times
    # this for a node whose CPU time still advances (slow, not stuck).
    startup_timeout_s: Annotated[float, msgspec.Meta(ge=5.0, le=3600.0)] = 120.0
    stopped_grace_s: Annotated[float, msgspec.Meta(ge=0.0, le=60.0)] = 1.0
    hang_timeout_s: Annotated[float, msgspec.Meta(ge=1.0, le=600.0)] = 15.0
    # Real time: the launcher's progress watchdog ends a run in which no step is done, or no
    # command comes, for this many plant periods (at the time factor), at least 5 s; lock-step runs
    # are bound by command_timeout_s instead (bench/runtime/progress_watchdog.py, docs/run_safety.md).
    stall_periods: Annotated[int, msgspec.Meta(ge=1, le=100_000)] = 50


class RunConfig(msgspec.Struct, forbid_unknown_fields=True):
    # lock-step: plant waits for each command (deterministic); real-time: plant steps on the
    # wall clock at time_factor simulated seconds per wall second and never waits.
    mode: Literal["lock-step", "real-time"] = "lock-step"
    steps: Annotated[int, msgspec.Meta(ge=1, le=MAX_STEPS)] | None = None   # default: the reference's 288
    time_factor: Annotated[float, msgspec.Meta(ge=1e-2, le=1e6)] = 6000.0   # real-time: 600 s steps at 10 Hz
    seed: Annotated[int, msgspec.Meta(ge=0, le=2**63 - 1)] = 1
    # real-time: SCHED_FIFO priority of the loop's processes, the plant, the estimator and the
    # controller, every thread of them (0: the default scheduler); bench/runtime/priority.py.
    # They stand for the spacecraft and its flight computer, which no other program holds up.
    realtime_priority: Annotated[int, msgspec.Meta(ge=0, le=99)] = 20
    # lock-step: how long the plant waits for a command before it declares the loop broken.
    command_timeout_s: Annotated[float, msgspec.Meta(gt=0, le=3600.0)] = 10.0
    liveliness: LivelinessConfig = msgspec.field(default_factory=LivelinessConfig)
    # Parts provided from outside the bench (docs/contract.md). "controller": the controller process,
    # which in the attitude loop over [can] is the flight software (the law and the magnetorquer
    # driver on the bus); the launcher starts no such node and waits for one to join under its name.
    # "estimator": the navigation filter, the same way. "board": a magnetorquer board on the CAN bus
    # (no simulated board, no bus model; the plant reads the board's telemetry frames); rules in
    # bench.launcher.external_parts.
    external: Annotated[list[ExternalPart], msgspec.Meta(max_length=len(EXTERNAL_PARTS))] = msgspec.field(
        default_factory=list)


class OnboardConfig(msgspec.Struct, forbid_unknown_fields=True):
    """What the flight side (estimator and controller alike) believes about the world.

    The defaults believe the plant's truth ([plant]); a belief that differs is a scenario.
    """

    # The target orbit radius believed on board is the plant's R (1 + believed_radius_error)
    # (seed 001, third case). Off by 50 % or more is a different orbit, not an estimation problem.
    believed_radius_error: Annotated[float, msgspec.Meta(gt=-0.5, lt=0.5)] = 0.0
    # Sensor noise believed on board; None: the plant's ([plant.relpos_sensor],
    # [plant.range_bearing_sensor]). A measurement message's own noise field is never used.
    # Bounded like the plant's sensor noise ([plant], 1e9) and the estimator's beliefs (1e15).
    relpos_noise_std_m: Annotated[float, msgspec.Meta(gt=0, le=1e9)] | None = None
    range_noise_std_m: Annotated[float, msgspec.Meta(gt=0, le=1e9)] | None = None
    bearing_noise_std_rad: Annotated[float, msgspec.Meta(gt=0, le=1e9)] | None = None
    # White acceleration believed to act on the chaser (m^2/s^3). The linear CWH plant has none,
    # so neither does the default belief; set it for the nonlinear plant or a mistuned case.
    process_noise_psd_m2ps3: Annotated[float, msgspec.Meta(ge=0, le=1e15)] = 0.0


class Scenario(msgspec.Struct, forbid_unknown_fields=True):
    name: Annotated[str, msgspec.Meta(pattern=NAME_PATTERN)]
    description: Annotated[str, msgspec.Meta(max_length=4096)] = ""
    # "rendezvous": the translational loop (600 s steps). "attitude": the magnetorquer loop at the
    # gyro rate ([attitude], [attitude_control]; issue 11).
    kind: Literal["rendezvous", "attitude"] = "rendezvous"
    run: RunConfig = msgspec.field(default_factory=RunConfig)
    plant: PlantConfig = msgspec.field(default_factory=PlantConfig)
    estimator: EstimatorConfig = msgspec.field(default_factory=EstimatorConfig)
    controller: ControllerConfig = msgspec.field(default_factory=ControllerConfig)
    onboard: OnboardConfig = msgspec.field(default_factory=OnboardConfig)
    can: CanConfig | None = None
    attitude: AttitudePlantConfig = msgspec.field(default_factory=AttitudePlantConfig)
    attitude_control: AttitudeControlConfig = msgspec.field(default_factory=AttitudeControlConfig)
    # What a run of this scenario is judged on ([[criteria]]: bench/criteria.py)
    criteria: Criteria = msgspec.field(default_factory=list)

    def params(self) -> RendezvousParams:
        """The seed's params struct for this scenario (reference numbers, scenario overrides)."""
        p = self.plant
        overrides = dict(
            mass_kg=p.mass_kg,
            gravitational_parameter_m3ps2=p.gravitational_parameter_m3ps2,
            target_radius_m=p.target_radius_m,
            time_step_s=p.time_step_s,
        )
        if self.run.steps is not None:
            overrides["n_steps"] = self.run.steps
        return RendezvousParams.from_reference(**overrides)

    def onboard_params(self) -> RendezvousParams:
        """The params as the flight side believes them ([onboard]): what estimator and controller
        build their models on. The plant flies `params()`."""
        return self.params().with_radius_error(self.onboard.believed_radius_error)

    @property
    def n_steps(self) -> int:
        if self.kind == "attitude":
            if self.run.steps is not None:
                return self.run.steps
            return max(1, round(self.attitude.duration_s * self.attitude.sensors.gyro_rate_hz))
        return self.params().n_steps

    @property
    def step_s(self) -> float:
        """Simulated time per plant step."""
        return 1.0 / self.attitude.sensors.gyro_rate_hz if self.kind == "attitude" else self.plant.time_step_s

    def initial_state_m_mps(self):
        import numpy as np

        if self.plant.initial_state_m_mps is not None:
            return np.array(self.plant.initial_state_m_mps, dtype=float)
        return self.params().initial_state_m_mps(self.plant.initial_condition)


# Real-time attitude runs keep simulated and wall time close: the board's command timeout (0.1 s)
# and the driver's command period are wall-clock, so at a factor of 10 one 0.1 s plant step would
# be shorter than the driver's 20 ms command period and the loop would sample stale commands.
MAX_ATTITUDE_TIME_FACTOR = 2.0


def _check_attitude(s: Scenario) -> None:
    if s.controller.deadline.fallback == "lqr":
        raise ScenarioError("controller.deadline.fallback: 'lqr' is a translational law; the attitude loop has none")
    try:
        check_attitude_plant(s.attitude)
    except AttitudeConfigError as exc:
        raise ScenarioError(str(exc)) from None
    control = s.attitude_control
    if control.law not in ATTITUDE_LAWS:
        raise ScenarioError(f"attitude_control.law: unknown law {control.law!r} (known: {', '.join(sorted(ATTITUDE_LAWS))})")
    if control.dipole_limit_am2 is not None:
        limit = control.dipole_limit_am2
        if not limit > 0:   # also NaN
            raise ScenarioError(f"attitude_control.dipole_limit_am2: must be positive, got {limit}")
        if s.can is not None and limit > s.can.board.max_dipole_am2:
            raise ScenarioError(f"attitude_control.dipole_limit_am2: {limit} exceeds the board's "
                                f"can.board.max_dipole_am2 = {s.can.board.max_dipole_am2}")
    try:
        check_unit_quaternion(control.target.q_wxyz, "attitude_control.target.q_wxyz")
        if control.inertia_kgm2 is not None:
            inertia_matrix(control.inertia_kgm2, "attitude_control.inertia_kgm2")
    except AttitudeConfigError as exc:
        raise ScenarioError(str(exc)) from None
    if s.attitude.sensors.magnetometer_sampling == "coil_blanking":
        board = None if s.can is None else s.can.board
        if board is None or not (board.mag_window_period_s > 0 and board.mag_window_s > 0):
            raise ScenarioError("attitude.sensors.magnetometer_sampling: \"coil_blanking\" samples in the board's coil-"
                                "blanking windows; set can.board.mag_window_period_s and mag_window_s (real time over CAN)")
        tick_wall_s = s.step_s / s.run.time_factor
        if board.mag_window_s < tick_wall_s:
            raise ScenarioError(f"can.board.mag_window_s: {board.mag_window_s} s is shorter than one gyro tick "
                                f"({tick_wall_s:.3g} s of wall time): a coil-blanking window could fall between two ticks")
    if s.run.mode == "lock-step" and s.can is not None and s.can.board.mag_window_period_s > 0:
        raise ScenarioError("can.board.mag_window_period_s: the board's magnetometer windows run on the wall "
                            "clock, which a lock-step attitude run does not follow; use run.mode = \"real-time\"")
    if s.run.mode == "lock-step" and s.can is not None and s.can.faults:
        # bench.bus.can.sim_window.bus_on_simulated_time: a fault's start_s is simulated time, which
        # a bus on the wall clock beside a lock-step loop has no measure of.
        wall = (s.can.lock_step_clock == "wall" or "board" in s.run.external or s.can.transport != "zenoh"
                or s.can.driver_bus is not None or s.can.board_bus is not None)
        if wall:
            raise ScenarioError("can.faults: their times are simulated seconds, and this lock-step run puts the bus "
                                "on the wall clock (lock_step_clock \"wall\", a kernel bus, a bus of its own or an "
                                "external board); use lock_step_clock \"auto\" on the zenoh transport, or real time")
    if s.run.mode == "real-time" and s.run.time_factor > MAX_ATTITUDE_TIME_FACTOR:
        raise ScenarioError(f"run.time_factor: the attitude loop runs real-time near 1x (board timeout and "
                            f"bus on the wall clock); got {s.run.time_factor}, at most {MAX_ATTITUDE_TIME_FACTOR}")


def _check_attitude_sizes(s: Scenario) -> None:
    """The attitude loop's counts that come from products of fields (each bounded alone)."""
    rate_hz = s.attitude.sensors.gyro_rate_hz
    if s.run.steps is None and s.attitude.duration_s * rate_hz > MAX_STEPS + 0.5:
        raise ScenarioError(f"attitude.duration_s: {s.attitude.duration_s:g} s at {rate_hz:g} Hz is "
                            f"{s.attitude.duration_s * rate_hz:.3g} steps; at most {MAX_STEPS}")
    planner = s.attitude_control.planner
    planned = s.attitude_control.law in PLANNED_LAWS
    if planned and planner.max_horizon_s / planner.plan_step_s > MAX_PLAN_STEPS:
        raise ScenarioError(f"attitude_control.planner.plan_step_s: {planner.max_horizon_s:g} s of horizon in "
                            f"{planner.plan_step_s:g} s steps is more than {MAX_PLAN_STEPS} MILQR steps")
    if s.attitude.field.model == "igrf":
        duration_s = s.n_steps * s.step_s + 1.0
        if planned:   # the planner tabulates its horizon and hold beyond the run (bench/planner/planner.py)
            duration_s += planner.max_horizon_s + planner.hold_after_arrival_s + 2 * planner.plan_step_s
        points = duration_s / s.attitude.field.grid_s
        if points > MAX_FIELD_GRID_POINTS:
            raise ScenarioError(f"attitude.field.grid_s: {s.attitude.field.grid_s:g} s over {duration_s:.3g} s is "
                                f"{points:.3g} IGRF points; at most {MAX_FIELD_GRID_POINTS}")


def _check_semantics(s: Scenario) -> None:
    if s.kind == "attitude":
        _check_attitude_sizes(s)
        _check_attitude(s)
    if s.run.mode == "real-time":
        period_s = s.step_s / s.run.time_factor
        if not MIN_WALL_PERIOD_S <= period_s <= MAX_WALL_PERIOD_S:
            raise ScenarioError(
                f"run.time_factor: {s.run.time_factor:g} makes a {s.step_s:g} s step last {period_s:.3g} s "
                f"of wall time; it must be {MIN_WALL_PERIOD_S:g}-{MAX_WALL_PERIOD_S:g} s"
            )
    if s.kind == "attitude":
        return  # the translational checks below are for the rendezvous loop
    # The CWH discretisation and the LQR/MPC designs need a step that is a fraction of the orbit:
    # the reference flies 600 s steps at n = 1.1e-3 rad/s (0.68 rad); a step of a whole orbit or
    # more aliases the motion the controller is meant to follow.
    step_rad = s.params().mean_motion * s.plant.time_step_s
    if not step_rad <= MAX_ORBIT_ANGLE_PER_STEP_RAD:
        raise ScenarioError(f"plant.time_step_s: {s.plant.time_step_s:g} s is {step_rad:.3g} rad of the target's orbit "
                            f"(mean motion from plant.gravitational_parameter_m3ps2 and target_radius_m); at most "
                            f"{MAX_ORBIT_ANGLE_PER_STEP_RAD} rad per step")
    if s.plant.initial_state_m_mps is None:
        known = RendezvousParams.from_reference().initial_conditions_m_mps
        if s.plant.initial_condition not in known:
            raise ScenarioError(
                f"plant.initial_condition: unknown initial condition {s.plant.initial_condition!r} "
                f"(known: {', '.join(sorted(known))}; or give plant.initial_state_m_mps)"
            )
    if len(s.controller.q_diag) != 6:
        raise ScenarioError(f"controller.q_diag: needs 6 weights, got {len(s.controller.q_diag)}")
    if len(s.controller.r_diag) != 3:
        raise ScenarioError(f"controller.r_diag: needs 3 weights, got {len(s.controller.r_diag)}")
    _check_lqr_design(s)


def _check_lqr_design(s: Scenario) -> None:
    """Every translational controller designs an LQR (the law, MPC's terminal cost, the fallback)
    on the believed model: weights or a plant it has no solution for (3e7 kg with 1 s steps and the
    seed's weights: the scaled input is too weak) are refused here, not in the controller process."""
    import numpy as np

    from bench.gnc.lqr import dlqr

    model = s.onboard_params().scaled
    # the controller's weights (bench.controller.factory.weights_from_config), read here without
    # importing the controller: the scenario sits below every process
    q, r = np.diag(np.asarray(s.controller.q_diag, float)), np.diag(np.asarray(s.controller.r_diag, float))
    try:
        with np.errstate(all="ignore"):
            gain, cost = dlqr(model.A, model.B, q, r)
        solved = bool(np.all(np.isfinite(gain)) and np.all(np.isfinite(cost)))
    except (np.linalg.LinAlgError, ValueError) as exc:
        solved, reason = False, str(exc)
    else:
        reason = "non-finite gain"
    if not solved:
        raise ScenarioError(f"controller.q_diag: no LQR solution for controller.q_diag and r_diag on this plant "
                            f"(plant.mass_kg = {s.plant.mass_kg:g}, plant.time_step_s = {s.plant.time_step_s:g}): {reason}")


def _msgspec_message(exc: msgspec.ValidationError) -> str:
    # msgspec says "Expected `float` >= 0 - at `$.plant.time_step_s`"; lead with the field.
    text = str(exc)
    problem, at, where = text.rpartition(" - at `$")
    if not at:
        problem, where = text, ""
    where = where.rstrip("`").lstrip(".")
    unknown = re.fullmatch(r"Object contains unknown field `(.*)`", problem, re.DOTALL)
    if unknown:   # the unknown key is the field to name: "run.stesp: unknown field"
        return f"{where + '.' if where else ''}{_key(unknown.group(1))}: unknown field"
    missing = re.fullmatch(r"Object missing required field `(.*)`", problem, re.DOTALL)
    if missing:
        return f"{where + '.' if where else ''}{_key(missing.group(1))}: required field missing"
    if where and re.match(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*: ", problem):
        # a section's own check naming one of its fields ("flight_channel: ..." at `$.can`)
        return f"{where}.{problem}"
    return f"{where}: {problem}" if where else f"<root>: {problem}"


def _key(key) -> str:
    """A key as a message shows it: bare if plain, else quoted (a key may hold ':', '.' or spaces)."""
    key = str(key)
    return key if re.fullmatch(r"[A-Za-z0-9_-]+", key) else json.dumps(key, ensure_ascii=False)


def _first_non_finite(value, path: str = "") -> str | None:
    """Path of the first float that is inf or NaN in plain data (dicts, lists), else None."""
    stack = [(path, value)]
    while stack:
        where, item = stack.pop()
        if isinstance(item, float) and not math.isfinite(item):
            return f"{where.lstrip('.') or '<root>'}: must be a finite number, got {item!r}"
        if isinstance(item, dict):
            stack.extend((f"{where}.{_key(k)}", v) for k, v in reversed(list(item.items())))
        elif isinstance(item, (list, tuple)):
            stack.extend((f"{where}[{i}]", v) for i, v in reversed(list(enumerate(item))))
    return None


def _deeper_than(value, limit: int) -> str | None:
    """Path of the first value nested deeper than `limit` tables and arrays, else None (iterative:
    whatever the parser returned, this check cannot run out of stack)."""
    stack = [("", value, 0)]
    while stack:
        where, item, depth = stack.pop()
        if isinstance(item, (dict, list, tuple)):
            if depth >= limit:
                return where.lstrip(".") or "<root>"
            items = item.items() if isinstance(item, dict) else enumerate(item)
            stack.extend((f"{where}.{_key(k)}" if isinstance(item, dict) else f"{where}[{k}]", v, depth + 1)
                         for k, v in items)
    return None


def _toml_field(exc: BaseException, text: str) -> str:
    """Which key tomllib was parsing when it raised `exc`, else the line (bench/bus/toml_input.py)."""
    return toml_input.field(exc, text, quote=_key)


def _check_nesting(data, source: str) -> None:
    where = _deeper_than(data, MAX_NESTING)
    if where is not None:
        raise ScenarioError(f"{source}: {where}: nested deeper than {MAX_NESTING} levels of tables and arrays")


def _stack_depth() -> int:
    frame, depth = sys._getframe(), 0
    while frame is not None:
        frame, depth = frame.f_back, depth + 1
    return depth


def parse_toml_text(text: str, source: str) -> dict:
    """tomllib's parse of a scenario's text, its limits turned into one-line ScenarioErrors naming
    the key: a syntax error or a key given twice, an integer of more digits than Python converts
    (sys.get_int_max_str_digits), a nesting deep enough to exhaust the parser's recursion, or
    deeper than MAX_NESTING.

    tomllib recurses two to four frames per level of nesting. It runs with TOML_STACK_FRAMES frames
    above this one (never more than the interpreter's limit), so a file nested beyond ~100 levels
    runs out of recursion and is named by its key whatever limit the interpreter was given (a test
    runner raises it), and one within MAX_NESTING always parses. The limit is the interpreter's, so
    it is lowered only for the parse."""
    limit = sys.getrecursionlimit()
    try:
        sys.setrecursionlimit(min(limit, _stack_depth() + TOML_STACK_FRAMES))
        data = tomllib.loads(text)
    except ValueError as exc:     # TOMLDecodeError, or an integer too long to convert
        raise ScenarioError(f"{source}: {_toml_field(exc, text)}: {toml_input.problem(exc)}") from None
    except RecursionError as exc:
        where = _toml_field(exc, text)
        raise ScenarioError(f"{source}: {where}: nested deeper than {MAX_NESTING} levels of tables and arrays "
                            "(too deep for the TOML parser)") from None
    finally:
        sys.setrecursionlimit(limit)
    _check_nesting(data, source)
    return data


class _Refused:
    """What the JSON parser's hooks put in place of what they refuse (an object with a key given
    twice, an integer too long to convert); the hooks see no path, so _first_refused finds it
    after parsing and names its field."""

    def __init__(self, problem: str, key: str | None = None):
        self.problem, self.key = problem, key


def _json_object(pairs: list) -> dict | _Refused:
    # json keeps the last of a key given twice, silently: a reviewer reads `"profile": "secoc"`
    # while the run uses the `"e2e"` further down.
    seen: dict = {}
    for key, value in pairs:
        if key in seen:
            return _Refused("key given twice", key)
        seen[key] = value
    return seen


def _json_int(text: str) -> int | _Refused:
    # What tomllib and int() refuse too (sys.get_int_max_str_digits), refused naming the field.
    limit, digits = sys.get_int_max_str_digits(), len(text.lstrip("-"))
    if limit and digits > limit:
        return _Refused(f"an integer of {digits} digits; at most {limit} digits are read")
    return int(text)


def _first_refused(value) -> str | None:
    """"FIELD: problem" of the first value the JSON hooks refused in plain data, else None."""
    stack = [("", value)]
    while stack:
        where, item = stack.pop()
        if isinstance(item, _Refused):
            where = f"{where}.{_key(item.key)}" if item.key is not None else where
            return f"{where.lstrip('.') or '<root>'}: {item.problem}"
        if isinstance(item, dict):
            stack.extend((f"{where}.{_key(k)}", v) for k, v in reversed(list(item.items())))
        elif isinstance(item, list):
            stack.extend((f"{where}[{i}]", v) for i, v in reversed(list(enumerate(item))))
    return None


def parse_json_text(text: str, source: str) -> dict:
    """json's parse of a scenario's text (the scenario.json a launcher wrote into a run directory),
    its refusals one-line ScenarioErrors naming the field: a syntax error (its line), a key given
    twice, an integer of more digits than Python converts, a nesting too deep for the parser."""
    try:
        data = json.loads(text, object_pairs_hook=_json_object, parse_int=_json_int)
    except json.JSONDecodeError as exc:
        raise ScenarioError(f"{source}: line {exc.lineno}: not valid JSON: {exc}") from None
    except RecursionError:
        raise ScenarioError(f"{source}: <root>: nested deeper than {MAX_NESTING} levels (too deep for the JSON parser)") from None
    problem = _first_refused(data)
    if problem:
        raise ScenarioError(f"{source}: {problem}")
    return data


def _read_bounded(path: Path) -> str:
    """The file's text, refused before reading if it is too large to parse safely."""
    try:
        size = path.stat().st_size
        if size > MAX_SCENARIO_BYTES:
            raise ScenarioError(f"{path}: {size} bytes; a scenario file may hold at most {MAX_SCENARIO_BYTES}")
        return path.read_text(errors="replace")
    except OSError as exc:
        raise ScenarioError(f"{path}: cannot be read: {exc.strerror or exc}") from None


def parse_scenario(data: dict, source: str = "<scenario>") -> Scenario:
    if not isinstance(data, dict):
        raise ScenarioError(f"{source}: a scenario is a table of sections, not {type(data).__name__}")
    _check_nesting(data, source)
    problem = _first_non_finite(data)
    if problem:
        raise ScenarioError(f"{source}: {problem}")
    try:
        # strict: no string becomes a number ("20" is not 20) and no bool an integer; an integer
        # is accepted where a float is expected.
        scenario = msgspec.convert(data, Scenario, strict=True)
    except msgspec.ValidationError as exc:
        raise ScenarioError(f"{source}: {_msgspec_message(exc)}") from None
    try:
        _check_semantics(scenario)
    except ScenarioError as exc:
        raise ScenarioError(f"{source}: {exc}") from None
    return scenario


def builtin_names() -> list[str]:
    root = resources.files(BUILTIN_PACKAGE)
    return sorted(p.name[: -len(".toml")] for p in root.iterdir() if p.name.endswith(".toml"))


def fault_free_attitude_builtins() -> list[str]:
    """The built-in attitude scenarios without [[can.faults]] (where any alarm is a false one)."""
    names = []
    for name in builtin_names():
        s = load_scenario(name)
        if s.kind == "attitude" and not (s.can is not None and s.can.faults):
            names.append(name)
    return names


def load_scenario(name_or_path: str | Path | None = None) -> Scenario:
    """A built-in scenario by name, or a TOML file by path; the default is `rendezvous_lqr`."""
    name_or_path = str(name_or_path or "rendezvous_lqr")
    path = Path(name_or_path)
    try:
        exists = path.exists()
    except (OSError, ValueError) as exc:    # a name too long, a NUL byte
        raise ScenarioError(f"scenario file {name_or_path!r}: {exc}") from None
    if path.suffix == ".json":
        # The scenario a launcher wrote into a run directory, exactly as it ran.
        if not path.is_file():
            raise ScenarioError(f"scenario file {name_or_path!r} does not exist")
        return parse_scenario(parse_json_text(_read_bounded(path), str(path)), str(path))
    if path.suffix == ".toml" or exists:
        if not path.is_file():
            raise ScenarioError(f"scenario file {name_or_path!r} does not exist")
        text, source = _read_bounded(path), str(path)
    elif name_or_path in builtin_names():
        text = resources.files(BUILTIN_PACKAGE).joinpath(f"{name_or_path}.toml").read_text()
        source = f"built-in scenario {name_or_path!r}"
    else:
        raise ScenarioError(
            f"no scenario file or built-in named {name_or_path!r} (built-ins: {', '.join(builtin_names())})"
        )
    return parse_scenario(parse_toml_text(text, source), source)


def scenario_to_toml_dict(s: Scenario) -> dict:
    """Plain data of a scenario (written into the run directory as what actually ran)."""
    return msgspec.to_builtins(s)
