"""Typed messages of the bench, in the manner of Basilisk's message structs.

Every payload is a msgspec Struct encoded as JSON (so Foxglove and any JSON tool can read a
recording), with the common `Header`. Decoding validates types, lengths and unknown fields; a bad
payload raises `MalformedMessage`, which the receiving process counts and logs, never dies on.
What each field means for an outside node (description, unit, frame, allowed values) is in
bench/contract/fields.py, which the exported JSON Schemas carry; a test fails on a field it misses.
"""
from __future__ import annotations

from typing import Annotated, TypeVar

import msgspec

SCHEMA_VERSION = 1

# Monotonic-clock stages a sample passes through, in loop order. Each process that handles a
# sample stamps `time.monotonic_ns()` under its stage name; latencies are differences of these.
STAGES = (
    "sensed",               # plant produced the measurement
    "estimator_received",
    "estimated",            # estimator published its estimate
    "controller_received",
    "commanded",            # controller published its command
    "can_sent",             # flight-side driver put the command frame on the bus
    "board_received",       # magnetorquer board decoded it
    "plant_received",       # plant received the command
    "applied",              # plant (or board) applied it
)

Vec3 = Annotated[list[float], msgspec.Meta(min_length=3, max_length=3)]
Vec6 = Annotated[list[float], msgspec.Meta(min_length=6, max_length=6)]
Cov6 = Annotated[list[float], msgspec.Meta(min_length=36, max_length=36)]
NonNegInt = Annotated[int, msgspec.Meta(ge=0)]
# HMAC-SHA256 in hex of a report to the launcher (bench/runtime/reports.py); "" unsigned.
ReportMac = Annotated[str, msgspec.Meta(max_length=64, pattern="^[0-9a-f]*$")]


class MalformedMessage(ValueError):
    """A payload that is not a valid message of the expected type."""


class Header(msgspec.Struct, forbid_unknown_fields=True):
    schema_version: int
    run_id: str
    seq: NonNegInt                 # index k of the plant sample this message derives from
    sim_time_s: float
    stamps_ns: dict[str, int] = {}

    def stamped(self, stage: str, monotonic_ns: int) -> "Header":
        """A copy of this header with one more stage stamp (headers flow downstream)."""
        stamps = dict(self.stamps_ns)
        stamps[stage] = monotonic_ns
        return Header(self.schema_version, self.run_id, self.seq, self.sim_time_s, stamps)


class Message(msgspec.Struct, forbid_unknown_fields=True, tag_field="type"):
    header: Header


class RelativePosition(Message, tag="relpos"):
    """Noisy relative position of the chaser in the target's LVLH frame."""
    position_m: Vec3
    noise_std_m: float


class RangeBearing(Message, tag="range_bearing"):
    """Noisy range, azimuth atan2(y, x) and elevation asin(z / r) of the chaser in LVLH; all three
    None when the sensor has no fix (its measured range at or below its minimum range: near the
    target, where noise can take the range to zero or below)."""
    range_m: Annotated[float, msgspec.Meta(gt=0)] | None = None
    azimuth_rad: float | None = None
    elevation_rad: float | None = None

    def __post_init__(self):
        if (self.range_m is None) != (self.azimuth_rad is None) or (self.range_m is None) != (self.elevation_rad is None):
            raise ValueError("range_m, azimuth_rad and elevation_rad are given together or not at all (no fix)")

    @property
    def fix(self) -> list[float] | None:
        """[range m, azimuth rad, elevation rad], or None without a fix."""
        return None if self.range_m is None else [self.range_m, self.azimuth_rad, self.elevation_rad]


class TruthState(Message, tag="truth"):
    """Ground truth; read by the truth-mode estimator, the recorder and reports only."""
    state_m_mps: Vec6
    thrust_applied_n: Vec3


class TranslationEstimate(Message, tag="estimate_translation"):
    state_m_mps: Vec6
    covariance: Cov6 | None = None          # row-major 6x6, SI units
    mean_motion_radps: float | None = None  # set when the estimator also estimates the orbit
    # Normalised innovation squared of this step's measurement against the prediction (None
    # without one), its degrees of freedom, and whether the innovation gate rejected it.
    nis: float | None = None
    nis_dof: NonNegInt = 0
    measurement_rejected: bool = False
    # False before the estimator's first fix (no position known yet: a range/bearing sensor
    # closer than its minimum range, say): state_m_mps is zeros and means nothing, and the
    # controller commands zero thrust until an estimate is valid.
    valid: bool = True


class ThrustCommand(Message, tag="thrust"):
    thrust_n: Vec3
    ctrl_feasible: bool
    status: str
    solve_time_s: float
    iterations: NonNegInt = 0
    fallback: str | None = None          # set when a deadline fallback produced this command


class DeadlineEvent(Message, tag="deadline"):
    process: str
    cycle_time_s: float
    budget_s: float
    missed: bool
    consecutive_misses: NonNegInt
    fallback: str | None = None


class StepDone(Message, tag="step_done"):
    """Plant's progress beacon: step k is integrated (drives the launcher's progress bar).
    mac: signed with the key the launcher handed the plant; the launcher ignores one without it.
    waiting: not a step done but a wait report: the plant has been waiting `waited_s` (wall clock)
    for a message on this topic, the one it needs for step k (lock-step: the command, the board's
    report; real time: a command at all). Sent once a wait lasts a second (bench/plant/stepping.py),
    so that the launcher's progress watchdog names the stage of a run that stalls."""
    n_steps: NonNegInt
    finished: bool = False
    mac: ReportMac = ""
    waiting: Annotated[str, msgspec.Meta(max_length=64)] = ""
    waited_s: Annotated[float, msgspec.Meta(ge=0.0)] = 0.0


class ProcessStats(Message, tag="process_stats"):
    """Counts a process reports at shutdown: what it published and what it had to reject.
    mac: signed with the key the launcher handed that process; the launcher takes the counts of a
    process it started only with a valid one."""
    process: str
    published: dict[str, NonNegInt]
    malformed: dict[str, NonNegInt]
    mac: ReportMac = ""
    # Messages it dropped for their data-topic MAC (bench/bus/data_auth.py): "forged" or
    # "replayed" -> topic -> count.
    unauthentic: dict[str, dict[str, NonNegInt]] = {}
    # The SCHED_FIFO priority its process ran at (0: the default scheduler; bench/runtime/priority.py).
    realtime_priority: NonNegInt = 0


M = TypeVar("M", bound=Message)

_encoder = msgspec.json.Encoder()
_decoders: dict[type, msgspec.json.Decoder] = {}


def header(run_id: str, seq: int, sim_time_s: float, **stamps_ns: int) -> Header:
    return Header(SCHEMA_VERSION, run_id, seq, sim_time_s, dict(stamps_ns))


def encode(message: Message) -> bytes:
    return _encoder.encode(message)


def decode(payload: bytes, kind: type[M]) -> M:
    """Decode and validate; raise MalformedMessage naming what is wrong."""
    decoder = _decoders.get(kind)
    if decoder is None:
        decoder = _decoders[kind] = msgspec.json.Decoder(kind)
    try:
        message = decoder.decode(payload)
    except (msgspec.ValidationError, msgspec.DecodeError) as exc:
        raise MalformedMessage(f"{kind.__name__}: {exc}") from None
    if message.header.schema_version != SCHEMA_VERSION:
        raise MalformedMessage(
            f"{kind.__name__}: schema version {message.header.schema_version}, expected {SCHEMA_VERSION}"
        )
    return message


def json_schema(kind: type[Message]) -> dict:
    """JSON Schema of a message type, for the MCAP recording (Foxglove reads it)."""
    return msgspec.json.schema(kind)


class MtqApplied(Message, tag="mtq_applied"):
    """Dipole the magnetorquer board applies (board -> plant, which turns it into torque m x B).

    Header stamps: board_received (command frame decoded), applied (coil targets set). The CAN
    command carries no sample index, so `alive_counter` joins this to the driver's command.
    """
    # What the coils put into the field (the plant's m x B): the coil driver target after quantisation
    # and saturation, through the board's hardware faults (bench/bus/can/coils.py); zero without power.
    dipole_am2: Vec3
    coil_current_a: Vec3             # coil currents now, as measured (they lag the target by the coil L/R)
    safe_state: bool                 # coils off: no valid command within the command timeout
    actuation_paused: bool = False   # coils off for a magnetometer sampling window
    alive_counter: NonNegInt = 0
    # The decoded command's dipole (quantised, saturated) that the coils take when not paused: in a
    # magnetometer window dipole_am2 is zero while this is the command the frame carried. None where
    # the board does not say (an external board's telemetry, lock-step reports).
    target_dipole_am2: Vec3 | None = None
    # Lock-step on simulated time (bench/bus/can/lockstep_bus.py): one report per plant step, of the
    # coil drivers' output averaged over step `step`; command_applied: a command frame of the
    # step was applied (its counter is alive_counter). None on the wall clock.
    step: NonNegInt | None = None
    command_applied: bool | None = None


# --- the attitude loop (issue 11) ---------------------------------------------------------------
Quat = Annotated[list[float], msgspec.Meta(min_length=4, max_length=4)]
Cov3 = Annotated[list[float], msgspec.Meta(min_length=9, max_length=9)]


class GyroSample(Message, tag="gyro"):
    """Plant -> estimator on `sense/gyro`, every plant step k (the gyro rate is the step rate): the
    mean body rate over [t_k-1, t_k] plus the gyro's bias and white noise. On each tick the plant
    publishes the magnetometer and star-tracker samples of that tick first, the gyro last: the
    gyro closes the tick for the estimator."""
    rate_radps: Vec3


class MagnetometerSample(Message, tag="magnetometer"):
    """Plant -> estimator on `sense/mag`, on the magnetometer's ticks: the body-frame field with the
    magnetometer's scale, bias and noise. `field_model_inertial_t` is the on-board field model's
    prediction at the same time (the bench computes it for the flight side, which carries the
    same model); the estimator holds it until the next sample."""
    field_body_t: Vec3
    field_model_inertial_t: Vec3


class StarTrackerSample(Message, tag="star_tracker"):
    """Plant -> estimator on `sense/star`, on every star-tracker tick: the measured attitude (body
    to inertial, scalar first), noisier about the boresight than across it; `q_wxyz` is None
    when the tracker has no fix (an outage: Sun or Earth in its field of view)."""
    q_wxyz: Quat | None = None


class AttitudeTruth(Message, tag="attitude_truth"):
    """Ground truth at t_k (recorder, reports and the truth-mode estimator only)."""
    q_wxyz: Quat
    omega_radps: Vec3
    gyro_bias_radps: Vec3
    field_body_t: Vec3
    position_m: Vec3


class AttitudeEstimate(Message, tag="estimate_attitude"):
    """Estimator -> controller, every tick. valid = False until the smoother has its first fix
    (the controller then runs only laws that need no attitude, B-dot)."""
    valid: bool
    q_wxyz: Quat
    omega_radps: Vec3                 # gyro with the estimated bias removed, body axes
    gyro_bias_radps: Vec3
    field_body_t: Vec3                # the field the law should use: magnetometer, else model rotated
    attitude_covariance_rad2: Cov3 | None = None
    # The magnetometer calibration the smoother estimates ([estimator.attitude]
    # estimate_magnetometer_calibration; measured = scale * B_body + bias): None when it is not
    # estimated or before the first fix, and an outside estimator may leave both out. Carried here
    # because the report compares it with the plant's, and the estimate lives only in this process.
    magnetometer_bias_t: Vec3 | None = None     # body axes, T
    magnetometer_scale: float | None = None     # dimensionless, 1 = no scale error


class DipoleCommand(Message, tag="dipole_command"):
    """Controller -> plant (lock-step pairing) and recorder: the dipole the law asked for at step k
    and the alive counter of the first CAN command frame that carried it (-1: not sent)."""
    dipole_am2: Vec3
    alive_counter: int
    law: str
    saturated: bool = False
    weak_field: bool = False
    fallback: str | None = None


# --- live operation (issue 48) -------------------------------------------------------------------
from bench.bus.can.faults import FaultSpec  # noqa: E402  (the fault schema of [[can.faults]], no cycle)


class BusEvent(Message, tag="bus_event"):
    """Controller -> recorder and live view on `event/can`: what the flight side detected on the
    magnetorquer bus, as it detects it: the driver's own events and the FDIR actuator monitor's
    (the same events can/driver.json lists at the end). The driver's thread sees frames, not steps:
    the header carries sim_time_s 0.0, as the board's MtqApplied does, and the recorder and the
    live view place it at the newest step."""
    source: str                      # "driver" or "FDIR"
    kind: str                        # e.g. heartbeat_timeout, command_rejected, fdir_reversed
    latency_s: float                 # from the fault's evidence on the bus to this detection
    detected_ns: int                 # the driver's event clock (monotonic ns; the bus's simulated ns in lock-step)
    frame: str = ""
    detail: str = ""


class FaultWindow(Message, tag="fault_window"):
    """canbus -> recorder, live view and board on `event/fault`: one fault of the bus model as it is
    armed, scripted ([[can.faults]], when the first command frame arms the injector) or injected
    live (`bench inject`, the live view's service; bench/bus/fault_command.py). header.sim_time_s is
    the fault's start on the run's simulated time, as `fault.start_s` (simulated seconds from the
    first command frame)."""
    label: str                       # "<index>:<name>", as in can/injections.jsonl and busmodel.json
    fault: FaultSpec                 # the fault, as a scripted one is written
    live: bool                       # injected while the run ran
    end_sim_s: float | None = None   # None: no end (a count of frames, or a hardware fault to the run's end)
    requested_by: str = ""           # live: who signed the request ("inject", "live")
