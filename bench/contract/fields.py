"""What every field of every published message means: its description, unit, frame and allowed values.

The message types (bench/bus/schemas.py, bench/bus/plan_message.py, bench/bus/can/sim_window.py)
say what a field is; this table says what it means, for the outside team that reads the exported
JSON Schemas (`bench contract export`) and contract.json. Kept here rather than as msgspec `Meta`
annotations beside each field: the types live in four modules that decode every message of a run,
the allowed values come from the code that emits them, and the frames depend on the run (the
rendezvous navigation frame), so the exporter composes them. tests/test_contract_export.py holds the
table to the types: a field of an exported message without an entry fails it, and each list of
allowed values is checked against the code that produces the values.

Nothing here is imported on a message's decode path.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import get_args

from bench.bus.schemas import SCHEMA_VERSION, STAGES
from bench.config.controller import ATTITUDE_LAWS, FallbackPolicy

# --- frames and conventions -------------------------------------------------------------------
LVLH = ("the target's LVLH frame in Hill (RSW) axes, Cartesian: origin at the target, which flies a circular "
        "orbit; x radially outward (from the Earth's centre through the target), y along track (the target's "
        "orbital velocity), z along the orbit normal (the target's orbital angular momentum), right-handed; the "
        "frame rotates with the target at its mean motion, and velocities are the time derivatives of these "
        "coordinates in the rotating frame (not the CCSDS nadir-pointing LVLH)")
CURVILINEAR = ("curvilinear coordinates about the target's circular orbit of radius R (bench/plant/curvilinear.py): "
               "[dr, s, w] = [|p| - R, R atan2(y, R + x), R asin(z / |p|)] for the chaser at p = (R + x, y, z) in "
               "LVLH axes, and their time derivatives in the rotating frame; thrust along the local radial, "
               "along-track and cross-track directions at the chaser")
NAVIGATION = ("the rendezvous loop's navigation frame, the run's [plant] navigation_frame (contract.json: "
              "frames.navigation_frame): \"cartesian\" is the target's LVLH frame (x radial out, y along track, "
              "z orbit normal, origin at the target), \"curvilinear\" the curvilinear [dr, s, w] about the "
              "target's orbit")
BODY = "the spacecraft's body axes (those of the gyro, the magnetometer and the magnetorquer coils)"
INERTIAL = ("the attitude loop's inertial frame: TEME, z along the Earth's spin axis (the SGP4 orbit's frame, "
            "taken as inertial; the circular orbit uses the same axes), origin at the Earth's centre")
QUATERNION = ("unit quaternion, scalar first [w, x, y, z], Hamilton product, body to inertial: it maps body-frame "
              "vectors to the inertial frame, r_I = q (x) [0, r_B] (x) q*")

FRAMES = {"navigation": NAVIGATION, "lvlh": LVLH, "body": BODY, "inertial": INERTIAL,
          "body_to_inertial": QUATERNION}
# As a field's description says it (the full text is in contract.json, frames).
FRAMES_SHORT = {
    "navigation": ("the run's navigation frame (contract.json frames.navigation_frame): by default the target's "
                   "LVLH frame, Hill axes, origin at the target, x radially out, y along track, z along the orbit "
                   "normal; curvilinear [dr, s, w] if the scenario says so"),
    "lvlh": "the target's LVLH frame, Hill axes, origin at the target, x radially out, y along track, z along the "
            "orbit normal",
    "body": "body axes",
    "inertial": "inertial (TEME, z along the Earth's spin axis)",
    "body_to_inertial": "scalar first [w, x, y, z], body to inertial (r_I = q (x) [0, r_B] (x) q*), Hamilton",
}

# --- allowed values that code emits (tests/test_contract_export.py checks each against the code) ---
FALLBACKS = get_args(FallbackPolicy)
# ThrustCommand.status as the bench's controllers set it: LQR and LQT "solved"; the MPCs the QP's
# outcome (bench/gnc/qp.py, bench/gnc/mpc.py: certified "SOLVED", "INFEASIBLE", "UNCERTIFIED", or
# proxsuite's own status when it failed from both starts); the deadline monitor and the control cycle.
THRUST_STATUSES = (
    "solved", "SOLVED", "INFEASIBLE", "UNCERTIFIED", "NON_FINITE_STATE", "INITIAL_STATE_VIOLATES_CONSTRAINTS",
    "PROXQP_MAX_ITER_REACHED", "PROXQP_PRIMAL_INFEASIBLE", "PROXQP_DUAL_INFEASIBLE", "PROXQP_NOT_RUN",
    "PROXQP_SOLVED_CLOSEST_PRIMAL_FEASIBLE", "NO_RESULT_BY_DEADLINE", "waiting_for_estimate",
)
# The tube MPC ([controller] type = "mpc_tube") solves the in-plane and out-of-plane problems apart.
_one = "(" + "|".join(THRUST_STATUSES) + ")"
THRUST_STATUS_PATTERN = f"^in-plane {_one}, out-of-plane {_one}$"
# AttitudePlanMessage.stop_reason: bench/gnc/milqr.py, and bench/planner/plan.py's hold plan.
PLAN_STOP_REASONS = ("feedforward_small", "cost_change_small", "max_iterations", "wall_time",
                     "regularisation_limit", "stalled", "hold")
UNAUTHENTIC_KINDS = ("forged", "replayed")      # bench/bus/data_auth.py FORGED, REPLAYED
STATS_PROCESSES = ("plant", "estimator", "controller", "planner", "mtq", "canbus", "recorder", "live")
DEADLINE_PROCESSES = ("plant", "controller")


@dataclass(frozen=True)
class Field:
    text: str
    unit: str | None = None                 # SI, as written in the field's name
    frame: str | None = None                # a key of FRAMES
    allowed: tuple | None = None            # the values the field may take (null added where it is optional)
    pattern: str | None = None              # further strings allowed besides `allowed`
    keys: tuple | None = None               # an object's allowed keys

    def description(self) -> str:
        parts = [self.text.rstrip(".") + "."]
        if self.unit:
            parts.append(f"Unit: {self.unit}.")
        if self.frame:
            parts.append(f"{'Quaternion' if self.frame == 'body_to_inertial' else 'Frame'}: {FRAMES_SHORT[self.frame]}.")
        if self.allowed:
            values = ", ".join(_literal(v) for v in self.allowed)
            parts.append(f"Allowed: {values}" + ("; or a string matching the schema's pattern" if self.pattern else "") + ".")
        if self.keys:
            parts.append(f"Keys: {', '.join(map(_literal, self.keys))}.")
        return " ".join(parts)

    def to_json(self) -> dict:
        out: dict = {"description": self.text}
        if self.unit:
            out["unit"] = self.unit
        if self.frame:
            out["frame"] = self.frame
        if self.allowed:
            out["allowed"] = list(self.allowed)
        if self.pattern:
            out["pattern"] = self.pattern
        if self.keys:
            out["keys"] = list(self.keys)
        return out


def _literal(value) -> str:
    return f'"{value}"' if isinstance(value, str) else str(value)


STATE = "m (x, y, z), m/s (vx, vy, vz)"
SEQ_OF_STEP = "of plant step k (header.seq = k)"

# Message types: what the message is, where the type has no docstring of its own.
MESSAGES: dict[str, str] = {
    "Header": "The common header of every message: which run, which plant sample it derives from, and the "
              "monotonic stamps of the stages it passed through.",
    "TranslationEstimate": "The estimator's state estimate of plant step k (estimator -> controller).",
    "ThrustCommand": "The controller's thrust command for plant step k (controller -> plant): exactly one per "
                     "estimate, with the estimate's header carried over and the controller's stamps added.",
    "DeadlineEvent": "A deadline miss of a process's cycle, or its recovery, as it happens (recorder, reports).",
}

# The `type` tag and the `header` of every message.
COMMON: dict[str, Field] = {
    "type": Field("The message's tag: which message this payload is (fixed per message type)."),
    "header": Field("The common header (see Header): the run, the plant step k the message derives from, its "
                    "simulated time and the stages' monotonic stamps; a message derived from another carries its "
                    "header over."),
}

FIELDS: dict[str, dict[str, Field]] = {
    "Header": {
        "schema_version": Field("Version of these schemas; a receiver refuses any other.", allowed=(SCHEMA_VERSION,)),
        "run_id": Field("The run's id: the second chunk of every key, bench/<run_id>/...; 1-64 letters, digits, "
                        "'_', '.', '-', starting with a letter or digit. A message of another run is refused."),
        "seq": Field("Index k of the plant sample this message derives from (the plant's step); a command for "
                     "step k carries k, one per step, none skipped or repeated."),
        "sim_time_s": Field("Simulated time of plant sample k (k times the step period time_step_s), carried "
                            "unchanged downstream.", unit="s"),
        "stamps_ns": Field("Stage name -> CLOCK_MONOTONIC of the host that handled the message at that stage, in "
                           "integer nanoseconds. Upstream stamps are carried unchanged and each node adds its own "
                           f"stages. Loop stages, in order: {', '.join(STAGES)}; the attitude planner adds "
                           "planner_received and planned on plan/attitude.", unit="ns"),
    },
    "TruthState": {
        "state_m_mps": Field("The true relative state [x, y, z, vx, vy, vz] of the chaser with respect to the "
                             "target at step k; read only by a truth-mode estimator and the recorder.", unit=STATE,
                             frame="navigation"),
        "thrust_applied_n": Field("The thrust the plant applied over the step that ended at step k (zero at "
                                  "step 0): the output stage's output, as commanded.", unit="N", frame="navigation"),
    },
    "RelativePosition": {
        "position_m": Field("Noisy relative position [x, y, z] of the chaser with respect to the target at step k.",
                            unit="m", frame="navigation"),
        "noise_std_m": Field("The sensor's true noise standard deviation per axis (the flight side's belief is its "
                             "own, the scenario's [onboard]; the bench's estimator never uses this field).", unit="m"),
    },
    "RangeBearing": {
        "range_m": Field("Noisy range |p| to the chaser, > 0; null (with azimuth_rad and elevation_rad) when the "
                         "sensor has no fix (measured range at or below its minimum range).", unit="m", frame="lvlh"),
        "azimuth_rad": Field("Noisy azimuth atan2(y, x) of the chaser; null without a fix.", unit="rad",
                             frame="lvlh"),
        "elevation_rad": Field("Noisy elevation asin(z / r) of the chaser; null without a fix.", unit="rad",
                               frame="lvlh"),
    },
    "TranslationEstimate": {
        "state_m_mps": Field("Estimated relative state [x, y, z, vx, vy, vz] of the chaser with respect to the "
                             "target at step k; zeros and meaningless while valid is false.", unit=STATE,
                             frame="navigation"),
        "covariance": Field("Covariance of state_m_mps, 6x6 row-major (36 numbers); null if the estimator gives none.",
                            unit="m^2, m^2/s, m^2/s^2 (products of the state's units)", frame="navigation"),
        "mean_motion_radps": Field("The target orbit's mean motion as the estimator estimates it; null unless it "
                                   "also estimates the orbit (the controller then updates its model).", unit="rad/s"),
        "nis": Field("Normalised innovation squared of this step's measurement against the prediction; null "
                     "without a measurement."),
        "nis_dof": Field("Degrees of freedom of nis (the measurement's dimension; 0 without one)."),
        "measurement_rejected": Field("True if the innovation gate rejected this step's measurement."),
        "valid": Field("False before the estimator's first fix: state_m_mps means nothing, and a controller "
                       "commands zero thrust for it (the bench's controller does, with status "
                       "\"waiting_for_estimate\")."),
    },
    "ThrustCommand": {
        "thrust_n": Field("Thrust per axis for step k, held constant over the step (zero-order hold). Each "
                          "|thrust_n[i]| must be within the thrusters' limit (contract.json: envelopes.thrust); the "
                          "plant refuses a command outside it (out_of_envelope) and applies its on_reject policy.",
                          unit="N", frame="navigation"),
        "ctrl_feasible": Field("True if the law produced this command as designed (LQR always; an MPC whose QP was "
                               "solved and certified); false if the law failed (a safe action after a failed "
                               "solve, or no result by the deadline). Informational: the plant applies any command "
                               "inside the envelope."),
        "status": Field("How the law ended this cycle: \"solved\" (LQR, LQT), \"SOLVED\" (MPC, optimum certified), "
                        "\"INFEASIBLE\", \"UNCERTIFIED\" (the solver said solved, the KKT certificate did not hold), "
                        "a PROXQP_* status (the QP solver failed), \"NO_RESULT_BY_DEADLINE\" (real time: no answer "
                        "by [controller.deadline] budget_s), \"waiting_for_estimate\" (the estimate was not valid; "
                        "zero thrust); the tube MPC reports both halves, \"in-plane S1, out-of-plane S2\". An "
                        "outside controller uses one of these (\"solved\" for a closed-form law)",
                        allowed=THRUST_STATUSES, pattern=THRUST_STATUS_PATTERN),
        "solve_time_s": Field("Wall-clock time the law took for this command, measured by the controller "
                              "(its own claim; the check measures the response at the recorder), >= 0.", unit="s"),
        "iterations": Field("Solver iterations this cycle (0 for a closed-form law such as LQR)."),
        "fallback": Field("Set when a deadline fallback produced this command instead of the law (real time, "
                          "the cycle overran [controller.deadline] budget_s): which one acted; null otherwise.",
                          allowed=FALLBACKS),
    },
    "DipoleCommand": {
        "dipole_am2": Field("The magnetic dipole the attitude law asked for at step k, per axis, within the "
                            "board's limit (contract.json: envelopes.dipole).", unit="A m^2", frame="body"),
        "alive_counter": Field("Alive counter of the first CAN command frame that carried this dipole, or -1 if no "
                               "frame was sent; the plant pairs the board's report with it."),
        "law": Field("The attitude law that produced the dipole ([attitude_control] law).",
                     allowed=tuple(ATTITUDE_LAWS)),
        "saturated": Field("True if the law's dipole was clipped to the limit on some axis."),
        "weak_field": Field("True if the field was too weak (or not finite) for the law to use."),
        "fallback": Field("Set when a deadline fallback produced this command (real time; the attitude loop holds "
                          "the last dipole); null otherwise.", allowed=FALLBACKS),
    },
    "MtqApplied": {
        "dipole_am2": Field("The dipole the coils put into the field, which the plant turns into torque m x B: the "
                            "command after quantisation and saturation (zero in the safe state, a magnetometer "
                            "window or without power), through the board's hardware faults (an open, stuck, "
                            "reversed or weak coil, [[can.faults]]).", unit="A m^2", frame="body"),
        "coil_current_a": Field("Coil currents now, as the current sensors in series with the coils measure them "
                                "(they lag the target by the coils' L/R time constant; a coil wired backwards or "
                                "weak after the sensor does not show).", unit="A", frame="body"),
        "safe_state": Field("True when the coils are off because no valid command came within the board's command "
                            "timeout."),
        "actuation_paused": Field("True when the coils are off for a magnetometer sampling window."),
        "alive_counter": Field("Alive counter of the command frame this report answers (joins it to the driver's "
                               "DipoleCommand)."),
        "target_dipole_am2": Field("The decoded command's dipole (quantised, saturated) that the coils take when not "
                                   "paused; null where the board does not say (an outside board's telemetry, "
                                   "lock-step reports).", unit="A m^2", frame="body"),
        "step": Field("Lock-step with the bus on simulated time: the plant step this report averages the coil "
                      "drivers' output over; null on the wall clock."),
        "command_applied": Field("Lock-step on simulated time: true if a command frame of the step was applied (its "
                                 "counter is alive_counter); null on the wall clock."),
    },
    "CanWindow": {
        "step": Field("The plant step whose CAN frames these are (negative: the board's boot, before step 0)."),
        "start_ns": Field("Start of the step on the bus's simulated clock (10^12 ns at mission time 0).", unit="ns"),
        "end_ns": Field("End of the step on the bus's simulated clock; every frame's t_ns is in [start_ns, end_ns).",
                        unit="ns"),
        "frames": Field("The frames of the step on this side of the bus, in time order (each a SimFrame array)."),
    },
    "SimFrame": {
        "t_ns": Field("When the frame's last bit passed, on the bus's simulated clock.", unit="ns"),
        "arbitration_id": Field("CAN identifier (mtq.dbc)."),
        "data": Field("The frame's payload bytes, base64 in JSON."),
        "is_fd": Field("True for a CAN FD frame."),
        "is_extended_id": Field("True for a 29-bit identifier."),
        "is_error_frame": Field("True for an error frame."),
        "bitrate_switch": Field("CAN FD: true if the data phase switched bit rate."),
    },
    "GyroSample": {
        "rate_radps": Field("Mean body rate over [t_k-1, t_k] plus the gyro's bias and white noise; sent last on "
                            "each tick (it closes the tick).", unit="rad/s", frame="body"),
    },
    "MagnetometerSample": {
        "field_body_t": Field("Measured geomagnetic field with the magnetometer's scale, bias and noise.", unit="T",
                              frame="body"),
        "field_model_inertial_t": Field("The on-board field model's prediction at the same time (held until the "
                                        "next sample).", unit="T", frame="inertial"),
    },
    "StarTrackerSample": {
        "q_wxyz": Field("Measured attitude, noisier about the boresight than across it; null when the tracker has "
                        "no fix (Sun or Earth in its field of view).", frame="body_to_inertial"),
    },
    "AttitudeTruth": {
        "q_wxyz": Field("True attitude at t_k.", frame="body_to_inertial"),
        "omega_radps": Field("True body rate.", unit="rad/s", frame="body"),
        "gyro_bias_radps": Field("True gyro bias.", unit="rad/s", frame="body"),
        "field_body_t": Field("True geomagnetic field.", unit="T", frame="body"),
        "position_m": Field("The spacecraft's position from the Earth's centre.", unit="m", frame="inertial"),
    },
    "AttitudeEstimate": {
        "valid": Field("False until the smoother has its first fix (then only laws that need no attitude, B-dot, "
                       "act; the others command zero)."),
        "q_wxyz": Field("Estimated attitude.", frame="body_to_inertial"),
        "omega_radps": Field("Body rate: the gyro with the estimated bias removed.", unit="rad/s", frame="body"),
        "gyro_bias_radps": Field("Estimated gyro bias.", unit="rad/s", frame="body"),
        "field_body_t": Field("The field the law should use: the magnetometer's, else the model's rotated into the "
                              "body.", unit="T", frame="body"),
        "attitude_covariance_rad2": Field("Covariance of the body-frame attitude error e (R_true = R_est Exp(e)), "
                                          "3x3 row-major; null if none.", unit="rad^2", frame="body"),
        "magnetometer_bias_t": Field("Estimated magnetometer bias (measured = scale * B_body + bias), when the "
                                     "estimator estimates the magnetometer's calibration; null (or left out) "
                                     "otherwise. Read by the report only, not by the controller.", unit="T",
                                     frame="body"),
        "magnetometer_scale": Field("Estimated magnetometer scale factor, dimensionless (1: none), with "
                                    "magnetometer_bias_t; null (or left out) otherwise."),
    },
    "AttitudePlanMessage": {
        "plan_id": Field("The plan's number (increasing)."),
        "start_time_s": Field("Simulated time of the plan's sample 0; sample k is at start_time_s + k dt_s.", unit="s"),
        "dt_s": Field("The plan's step, > 0.", unit="s"),
        "states": Field("N+1 states [q_wxyz (body to inertial, scalar first), omega_radps (body)].",
                        unit="1 (quaternion), rad/s (rate)"),
        "dipoles_am2": Field("N feed-forward dipoles.", unit="A m^2", frame="body"),
        "gains": Field("N TVLQR gains K, each 3x6 row-major: u = u_bar - K dx with dx = [Rodrigues phi; d_omega].",
                       unit="A m^2 per rad, A m^2 per rad/s"),
        "target_wxyz": Field("The attitude the plan arrives at.", frame="body_to_inertial"),
        "stop_reason": Field("Why the MILQR planner stopped iterating (\"hold\": a plan that only holds the target).",
                             allowed=PLAN_STOP_REASONS),
        "iterations": Field("MILQR iterations."),
        "cost": Field("The plan's cost."),
        "planning_time_s": Field("Wall-clock time the planner took.", unit="s"),
        "hold_steps": Field("The last steps that hold the target at rest after the arrival (0-N)."),
    },
    "DeadlineEvent": {
        "process": Field("The process whose cycle this is.", allowed=DEADLINE_PROCESSES),
        "cycle_time_s": Field("Wall-clock time of the cycle (controller: from the estimate's arrival to the command "
                              "leaving; plant: from sensing step k to integrating it).", unit="s"),
        "budget_s": Field("The budget it is judged against ([controller.deadline] budget_s; the plant: the "
                          "real-time period).", unit="s"),
        "missed": Field("True: the cycle overran its budget (plant: step k's command had not arrived when it "
                        "integrated the step); false: the first cycle on time after misses."),
        "consecutive_misses": Field("Misses in a row, this one included."),
        "fallback": Field("The fallback applied for this cycle (null: none).", allowed=FALLBACKS),
    },
    "StepDone": {
        "n_steps": Field("The run's number of plant steps."),
        "finished": Field("True on the last step: the run is over."),
        "mac": Field("HMAC-SHA256 in hex with the report key the launcher handed the plant (bench/runtime/"
                     "reports.py); \"\" unsigned (the launcher ignores it)."),
        "waiting": Field("Not a step done but a wait report: the topic the plant has been waiting on for step k "
                         "(\"\" for a step done)."),
        "waited_s": Field("How long the plant has waited, on the wall clock (wait reports only).", unit="s"),
    },
    "ProcessStats": {
        "process": Field("The reporting process's name.", allowed=STATS_PROCESSES),
        "published": Field("Topic (under bench/<run_id>/) -> messages published."),
        "malformed": Field("Topic -> messages received that did not decode (refused, counted, never fatal)."),
        "mac": Field("HMAC-SHA256 in hex with the report key the launcher handed that process; \"\" unsigned "
                     "(a node the launcher did not start)."),
        "unauthentic": Field("Messages dropped for their tag: kind -> topic -> count (\"forged\": no valid tag "
                             "under the run's key; \"replayed\": a counter already passed).", keys=UNAUTHENTIC_KINDS),
        "realtime_priority": Field("The SCHED_FIFO priority the process ran at (0: the default scheduler)."),
    },
    # Live operation (issue 48): event/can, event/fault (bench/bus/schemas.py, bench/bus/can/live_faults.py).
    "BusEvent": {
        "source": Field("Which monitor detected it: the flight-side driver, or the FDIR actuator monitor.",
                        allowed=("driver", "FDIR")),
        "kind": Field("What was detected (bench/bus/can/driver.py KINDS; the FDIR monitor's \"fdir_<class>\"), as "
                      "metrics.json's can_bus.driver.events counts it."),
        "latency_s": Field("The detection's latency: from the fault's evidence on the bus to this detection "
                           "(the FDIR monitor's: the span of evidence it took).", unit="s"),
        "detected_ns": Field("When it was detected on the driver's event clock: CLOCK_MONOTONIC ns, or in lock-step "
                             "with the bus on simulated time the bus's simulated ns.", unit="ns"),
        "frame": Field("The frame it concerns (a DBC name), \"FDIR\" for the actuator monitor's, \"\" for none."),
        "detail": Field("What the detector says of it (free text, at most 400 characters)."),
    },
    "FaultWindow": {
        "label": Field("\"<index>:<name>\": the fault's place in the injector's list (the scenario's faults first, "
                       "then those injected live) and its kind, as in can/injections.jsonl and busmodel.json."),
        "fault": Field("The fault as a [[can.faults]] entry (see FaultSpec); start_s is its start on simulated time."),
        "live": Field("True for a fault injected while the run ran (`bench inject`, the live view's service)."),
        "end_sim_s": Field("Its end in simulated seconds from the first command frame; null: no end (a count of "
                           "frames, or a hardware fault to the run's end).", unit="s"),
        "requested_by": Field("A live fault: the sender of the signed request (\"inject\", \"live\"); \"\" for a "
                              "scripted one."),
    },
    "FaultSpec": {
        "name": Field("The fault's kind (`bench faults` lists them with their parameters)."),
        "frames": Field("DBC frame names it acts on (frame faults; empty: the kind's default frames)."),
        "start_s": Field("When it starts: simulated seconds from the driver's first command frame.", unit="s"),
        "duration_s": Field("How long it acts, simulated seconds (null: to the end, or its count).", unit="s"),
        "count": Field("Frames it affects at most (0: no limit)."),
        "every": Field("It acts on every n-th matching frame."),
        "params": Field("The kind's own parameters (name -> value; `bench faults`)."),
    },
}


def field(struct: str, name: str) -> Field | None:
    """The table's entry for one field (the tag and the header of any message included)."""
    return FIELDS.get(struct, {}).get(name) or (COMMON.get(name) if struct != "Header" else None)
