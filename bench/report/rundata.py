"""Everything a run directory holds, loaded once: scenario, metrics, trajectory, recording.

Missing pieces are normal (a run without CAN has no can.log, an old run no recording): each field
is None or empty then, and the report leaves the matching section out.

Nothing read here is trusted: a run directory holds whatever anyone on the bus published. Every
recorded message is decoded again as a bench message; one that does not decode is counted as
malformed, and one of a type other than its topic carries (a valid DeadlineEvent-shaped
ThrustCommand on event/deadline) is counted under `wrong_type` and left out, so the analyses only
ever see well-formed messages of the type they expect. Unreadable JSON files count as missing.
"""
from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import numpy as np
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader

from bench.bus import keys
from bench.bus.can.zenoh_interface import CAN_TOPIC
from bench.bus.schemas import (
    DeadlineEvent, DipoleCommand, GyroSample, MagnetometerSample, Message, MtqApplied, ProcessStats, RelativePosition,
    StarTrackerSample, StepDone, ThrustCommand, TranslationEstimate, TruthState,
)
from bench.recorder import COUNTS_FILE, MALFORMED_PREFIX, OFFSETS_FILE, RECORDING_FILE, UNAUTHENTIC_PREFIX, classify_any
from bench.scenario import Scenario, ScenarioError, load_scenario

CAN_LOG_FILE = "can.log"

# The message type(s) each topic of the loop carries; a topic not listed takes any bench message.
# command/applied is the plant's record of what it applied: thrust in the translation loop, the
# dipole in the attitude loop.
EXPECTED_TYPES: dict[str, type[Message] | tuple[type[Message], ...]] = {
    keys.SENSE_RELPOS: RelativePosition,
    keys.TRUTH: TruthState,
    keys.ESTIMATE_TRANSLATION: TranslationEstimate,
    keys.COMMAND_THRUST: ThrustCommand,
    keys.COMMAND_APPLIED: (ThrustCommand, DipoleCommand),
    keys.COMMAND_DIPOLE: DipoleCommand,
    keys.ACTUATOR_MTQ: MtqApplied,
    keys.EVENT_DEADLINE: DeadlineEvent,
    keys.STATUS_STEP: StepDone,
    keys.SENSE_GYRO: GyroSample,
    keys.SENSE_MAG: MagnetometerSample,
    keys.SENSE_STAR: StarTrackerSample,
}


def expected_type(topic: str) -> type[Message] | tuple[type[Message], ...] | None:
    if topic.startswith(keys.STATUS_STATS + "/"):
        return ProcessStats
    return EXPECTED_TYPES.get(topic)


@dataclass(frozen=True)
class Recorded:
    """One valid message of the recording: its topic, arrival time (the recorder's wall clock, the
    MCAP publish time; the log time is the simulated time) and JSON body."""

    topic: str
    received_ns: int
    body: dict

    @property
    def seq(self) -> int:
        return int(self.body["header"]["seq"])

    @property
    def stamps_ns(self) -> dict[str, int]:
        return self.body["header"].get("stamps_ns", {})


@dataclass
class RunData:
    run_dir: Path
    run_id: str
    scenario: Scenario | None = None
    metrics: dict = field(default_factory=dict)
    trajectory: dict[str, np.ndarray] = field(default_factory=dict)
    messages: list[Recorded] = field(default_factory=list)
    malformed_in_recording: int = 0
    wrong_type: dict[str, int] = field(default_factory=dict)   # topic -> messages of another type
    recording_truncated: bool = False
    recorder_counts: dict | None = None
    clock_offsets: dict = field(default_factory=dict)
    can_log: Path | None = None

    def on(self, topic: str) -> list[Recorded]:
        """Recorded messages of one topic, in arrival order."""
        return [m for m in self.messages if m.topic == topic]

    @property
    def has_recording(self) -> bool:
        return (self.run_dir / RECORDING_FILE).is_file()


class RunDirError(ValueError):
    """Not a run directory (or an unreadable one); the message says what is missing."""


def read_recording(path: Path, wrong_type: dict[str, int] | None = None) -> tuple[list[Recorded], int, bool]:
    """Valid messages of an MCAP recording (in arrival order), how many malformed payloads it
    holds, and whether it ended early (a recorder killed before it finished the file: what it
    wrote until then is still read, with a non-seeking reader that does not need the summary).
    Messages of a type their topic does not carry are counted into `wrong_type` and left out."""
    messages, malformed, truncated = [], 0, False
    wrong_type = {} if wrong_type is None else wrong_type
    with open(path, "rb") as f:
        try:
            for _schema, channel, message in NonSeekingReader(f).iter_messages(log_time_order=False):
                topic = channel.topic
                if topic.startswith(UNAUTHENTIC_PREFIX):
                    continue        # failed the data-topic MAC: not the run's (recorder_counts.json counts it)
                if topic.startswith(MALFORMED_PREFIX) or topic.startswith(CAN_TOPIC + "/"):
                    malformed += topic.startswith(MALFORMED_PREFIX)
                    continue
                decoded = classify_any(message.data)
                if decoded is None:
                    malformed += 1
                    continue
                kind = expected_type(topic)
                if kind is not None and not isinstance(decoded, kind):
                    wrong_type[topic] = wrong_type.get(topic, 0) + 1
                    continue
                messages.append(Recorded(topic, message.publish_time, msgspec.to_builtins(decoded)))
        except (McapError, struct.error, EOFError, ValueError):
            truncated = True
    messages.sort(key=lambda m: m.received_ns)
    return messages, malformed, truncated


def _json_or(path: Path, default):
    """A JSON file's content; the default if it is missing, unreadable or not JSON."""
    try:
        return json.loads(path.read_text()) if path.is_file() else default
    except (OSError, ValueError):
        return default


def load_run(run_dir: str | Path) -> RunData:
    run_dir = Path(run_dir)
    if not (run_dir / "scenario.json").is_file():
        raise RunDirError(f"{run_dir} is not a run directory (no scenario.json)")
    data = RunData(run_dir=run_dir, run_id=run_dir.name)
    try:
        data.scenario = load_scenario(run_dir / "scenario.json")
    except ScenarioError as exc:
        raise RunDirError(str(exc)) from None
    data.metrics = _json_or(run_dir / "metrics.json", {})
    if not isinstance(data.metrics, dict):
        data.metrics = {}
    if (run_dir / "trajectory.npz").is_file():
        with np.load(run_dir / "trajectory.npz") as npz:
            data.trajectory = {k: npz[k] for k in npz.files}
    if (run_dir / RECORDING_FILE).is_file():
        data.messages, data.malformed_in_recording, data.recording_truncated = read_recording(
            run_dir / RECORDING_FILE, data.wrong_type)
        if data.messages:
            data.run_id = data.messages[0].body["header"]["run_id"]
    data.recorder_counts = _json_or(run_dir / COUNTS_FILE, None)
    data.clock_offsets = _json_or(run_dir / OFFSETS_FILE, {})
    data.can_log = run_dir / CAN_LOG_FILE if (run_dir / CAN_LOG_FILE).is_file() else None
    return data


# Topics whose sequence number is the plant's step index (the board's actuator/mtq counts its own).
STEP_TOPICS = (keys.SENSE_RELPOS, keys.TRUTH, keys.ESTIMATE_TRANSLATION, keys.COMMAND_THRUST, keys.COMMAND_APPLIED,
               keys.EVENT_DEADLINE, keys.STATUS_STEP)


def ahead_of_plant(run: RunData) -> dict[str, int] | None:
    """Per topic, recorded messages whose step is one the plant never published (a forged or
    corrupted sequence); None without the plant's trajectory to compare with."""
    thrust = run.trajectory.get("thrust_n")
    if thrust is None:
        return None
    # The plant integrated len(thrust) steps and may have published one more sample before it stopped.
    last_published = len(thrust)
    ahead: dict[str, int] = {}
    for m in run.messages:
        if m.topic in STEP_TOPICS and m.seq > last_published:
            ahead[m.topic] = ahead.get(m.topic, 0) + 1
    return ahead
