"""The key-expression table: each topic under `bench/<run_id>/`, the message it carries, who
publishes it and who reads it.

Publishers and readers are what the nodes do (their "reads:/writes:" docstrings); the
access-control table (bench/bus/acl.py, which every secure run enforces) allows each of them, and
tests/test_contract.py checks that it does. The recorder reads every topic and is left out. Message types are the bench's schemas (bench/bus/schemas.py,
bench/bus/plan_message.py).
"""
from __future__ import annotations

from dataclasses import dataclass

from bench.bus import keys
from bench.bus.can.sim_window import CanWindow
from bench.bus.plan_message import AttitudePlanMessage
from bench.bus.schemas import (
    AttitudeEstimate, AttitudeTruth, BusEvent, DeadlineEvent, DipoleCommand, FaultWindow, GyroSample, MagnetometerSample,
    Message, MtqApplied, ProcessStats, RangeBearing, RelativePosition, StarTrackerSample, StepDone, ThrustCommand,
    TranslationEstimate, TruthState,
)

RENDEZVOUS, ATTITUDE, BOTH = "rendezvous", "attitude", "both"


@dataclass(frozen=True)
class Topic:
    topic: str                                 # under bench/<run_id>/; `<process>` is a node's name
    messages: tuple[type[Message], ...]
    loop: str
    publishers: tuple[str, ...]
    readers: tuple[str, ...]                   # besides the recorder, which reads every topic
    what: str

    def to_json(self) -> dict:
        return {"key": keys.key("<run_id>", self.topic), "topic": self.topic, "loop": self.loop,
                "messages": [m.__name__ for m in self.messages], "publishers": list(self.publishers),
                "readers": list(self.readers), "what": self.what}


# From each node's "reads:/writes:" docstring (bench/plant/node.py, bench/estimator/node.py, ...);
# tests/test_contract.py checks every publisher and reader against the access-control table.
TOPICS: tuple[Topic, ...] = (
    Topic(keys.TRUTH, (TruthState,), RENDEZVOUS, ("plant",), ("estimator",),
          "ground truth of step k (read by the truth-mode estimator; recorder and reports)"),
    Topic(keys.SENSE_RELPOS, (RelativePosition,), RENDEZVOUS, ("plant",), ("estimator",), "relative-position fix of step k"),
    Topic(keys.SENSE_RANGE_BEARING, (RangeBearing,), RENDEZVOUS, ("plant",), ("estimator",), "range and bearing of step k"),
    Topic(keys.ESTIMATE_TRANSLATION, (TranslationEstimate,), RENDEZVOUS, ("estimator",), ("controller",),
          "the state estimate of step k"),
    Topic(keys.COMMAND_THRUST, (ThrustCommand,), RENDEZVOUS, ("controller",), ("plant", "estimator"),
          "the thrust command for step k: header.seq = k"),
    Topic(keys.COMMAND_APPLIED, (ThrustCommand, DipoleCommand), BOTH, ("plant",), (),
          "the command the plant applied, with every stamp (recorder, reports)"),
    Topic(keys.ACTUATOR_MTQ, (MtqApplied,), BOTH, ("mtq", "canbus"), ("plant",),
          "the dipole the magnetorquer board applies (canbus: per step, bus on simulated time)"),
    Topic(keys.CAN_STEP_FLIGHT, (CanWindow,), ATTITUDE, ("controller",), ("canbus",),
          "lock-step, bus on simulated time: the driver's CAN frames of step k at their simulated times"),
    Topic(keys.CAN_STEP_BUS, (CanWindow,), ATTITUDE, ("canbus",), ("controller",),
          "lock-step, bus on simulated time: the CAN frames the driver heard during step k"),
    Topic(keys.SENSE_GYRO, (GyroSample,), ATTITUDE, ("plant",), ("estimator",), "gyro rate of step k; closes the tick"),
    Topic(keys.SENSE_MAG, (MagnetometerSample,), ATTITUDE, ("plant",), ("estimator",), "magnetometer sample, on its ticks"),
    Topic(keys.SENSE_STAR, (StarTrackerSample,), ATTITUDE, ("plant",), ("estimator",), "star-tracker attitude, on its ticks"),
    Topic(keys.TRUTH_ATTITUDE, (AttitudeTruth,), ATTITUDE, ("plant",), ("estimator",), "attitude ground truth of step k"),
    Topic(keys.ESTIMATE_ATTITUDE, (AttitudeEstimate,), ATTITUDE, ("estimator",), ("controller", "planner"),
          "the attitude estimate of step k"),
    Topic(keys.COMMAND_DIPOLE, (DipoleCommand,), ATTITUDE, ("controller",), ("plant",), "the dipole asked for at step k"),
    Topic(keys.PLAN_ATTITUDE, (AttitudePlanMessage,), ATTITUDE, ("planner",), ("controller",), "a MILQR plan for the tracker"),
    Topic(keys.EVENT_DEADLINE, (DeadlineEvent,), BOTH, ("plant", "controller"), ("live",), "a deadline miss, as it happens"),
    Topic(keys.EVENT_CAN, (BusEvent,), ATTITUDE, ("controller",), ("live",),
          "what the flight side detected on the magnetorquer bus (driver, FDIR), as it detects it"),
    Topic(keys.EVENT_FAULT, (FaultWindow,), ATTITUDE, ("canbus",), ("mtq", "live"),
          "each fault of the bus model as it is armed: scripted, or injected live (the board takes live hardware faults)"),
    Topic(keys.STATUS_STEP, (StepDone,), BOTH, ("plant",), ("launcher",), "step k integrated (`finished` on the last)"),
    Topic(f"{keys.STATUS_STATS}/<process>", (ProcessStats,), BOTH,
          ("plant", "estimator", "controller", "planner", "mtq", "canbus", "recorder", "live"), ("launcher",),
          "a node's counts, once, as it stops (under its own name)"),
)
# The control plane (not data): what the launcher and the plant wait for (bench/bus/presence.py).
TOKENS = {
    "presence/<process>": "each node's queryable: it answers a presence query (payload: a nonce) with its "
                          "name, host, readiness and monotonic clock, signed under the run's key; the launcher "
                          "waits for every node's answer and watches them, the plant waits for every peer's "
                          "ready answer, the recorder takes its clock offsets from them",
    "presence/launcher": "the launcher's answer: a node not started by the launcher stops when it no longer answers",
    f"{keys.ALIVE}/launcher": "the launcher's liveliness token, a hint only: its delete at the end of a run makes "
                              "the nodes not started by the launcher ask presence/launcher at once",
    keys.CONTROL_FAULT: "canbus's queryable for live fault injection (bench/bus/fault_command.py): a FaultRequest "
                        "signed under the run's key (the data-topic tag, sender `inject` or `live`), answered with a "
                        "FaultReply signed by canbus; taken only in a run started with --allow-live-faults",
}


def chunks_match(pattern: str, topic: str) -> bool:
    """Zenoh key matching on chunks: `*` is one chunk, a final `**` any number."""
    p, t = pattern.split("/"), topic.split("/")
    if p[-1] == "**":
        return len(t) >= len(p) - 1 and all(a in ("*", b) for a, b in zip(p[:-1], t))
    return len(p) == len(t) and all(a in ("*", b) for a, b in zip(p, t))


def topic_of(topic: str) -> Topic | None:
    """The table's entry for a concrete topic (status/stats/plant -> status/stats/<process>)."""
    for entry in TOPICS:
        if chunks_match(entry.topic.replace("<process>", "*"), topic):
            return entry
    return None


def publications_of(node: str, loop: str) -> list[Topic]:
    """The topics `node` publishes in `loop` (its own stats included)."""
    return [t for t in TOPICS if t.loop in (loop, BOTH) and node in t.publishers]
