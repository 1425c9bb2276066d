"""Zenoh key expressions: `bench/<run_id>/<topic>`; the run id keeps parallel runs apart."""
from __future__ import annotations

import re

PREFIX = "bench"

SENSE_RELPOS = "sense/relpos"
SENSE_RANGE_BEARING = "sense/range_bearing"
TRUTH = "truth"
ESTIMATE_TRANSLATION = "estimate/translation"
COMMAND_THRUST = "command/thrust"
COMMAND_APPLIED = "command/applied"   # the command the plant applied, with its full stamp chain
ACTUATOR_MTQ = "actuator/mtq"
# Lock-step on simulated time (bench/bus/can/sim_window.py): a step's CAN frames, driver -> bus
# and bus -> driver, one CanWindow each way per step.
CAN_STEP_FLIGHT = "canstep/flight"
CAN_STEP_BUS = "canstep/bus"
# The attitude loop (issue 11).
SENSE_GYRO = "sense/gyro"            # every plant step (the gyro rate)
SENSE_MAG = "sense/mag"              # on the magnetometer's ticks
SENSE_STAR = "sense/star"            # on the star tracker's ticks (no fix in an outage)
SENSE_ATTITUDE_TOPICS = (SENSE_GYRO, SENSE_MAG, SENSE_STAR)
TRUTH_ATTITUDE = "truth/attitude"
ESTIMATE_ATTITUDE = "estimate/attitude"
COMMAND_DIPOLE = "command/dipole"
PLAN_ATTITUDE = "plan/attitude"       # MILQR plans, planner -> controller (issue 12)
EVENT_DEADLINE = "event/deadline"
# Live operation (issue 48): what the flight side detects on the magnetorquer bus, as it detects it
# (controller), and each fault of the bus model as it is armed, scripted or injected live (canbus).
EVENT_CAN = "event/can"
EVENT_FAULT = "event/fault"
# The command channel of live fault injection: queries to the canbus process, signed under the run's
# key like the data topics (bench/bus/fault_command.py).
CONTROL_FAULT = "control/fault"
STATUS_STEP = "status/step"
STATUS_STATS = "status/stats"
ALIVE = "alive"      # the launcher's liveliness token alive/launcher, a hint that it left (presence.py decides)

# First character a letter or digit: no ".", ".." (a run written into the parent folder) and
# no "-x" (read as an option by every tool handed the directory name).
_RUN_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}\Z")


def check_run_id(run_id: str) -> str:
    """Run ids become one key-expression chunk and a directory name: keep them plain."""
    if not isinstance(run_id, str) or not _RUN_ID.match(run_id):
        raise ValueError(f"run id {run_id!r} must be 1-64 characters of letters, digits, '_', '.', '-', "
                         f"starting with a letter or digit")
    return run_id


def key(run_id: str, topic: str) -> str:
    return f"{PREFIX}/{run_id}/{topic}"


def all_topics(run_id: str) -> str:
    return f"{PREFIX}/{run_id}/**"
