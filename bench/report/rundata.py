"""Everything a run directory holds, loaded once: scenario, metrics, trajectory, recording.

Missing pieces are normal (a run without CAN has no can.log, an old run no recording): each field
is None or empty then, and the report leaves the matching section out.
"""
from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader

from bench.recorder import COUNTS_FILE, MALFORMED_PREFIX, OFFSETS_FILE, RECORDING_FILE
from bench.scenario import Scenario, ScenarioError, load_scenario

CAN_LOG_FILE = "can.log"


@dataclass(frozen=True)
class Recorded:
    """One valid message of the recording: its topic, arrival time and JSON body."""

    topic: str
    log_time_ns: int
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


def read_recording(path: Path) -> tuple[list[Recorded], int, bool]:
    """Valid messages of an MCAP recording (in arrival order), how many malformed payloads it
    holds, and whether it ended early (a recorder killed before it finished the file: what it
    wrote until then is still read, with a non-seeking reader that does not need the summary)."""
    messages, malformed, truncated = [], 0, False
    with open(path, "rb") as f:
        try:
            for _schema, channel, message in NonSeekingReader(f).iter_messages(log_time_order=False):
                if channel.topic.startswith(MALFORMED_PREFIX):
                    malformed += 1
                    continue
                messages.append(Recorded(channel.topic, message.log_time, json.loads(message.data)))
        except (McapError, struct.error, EOFError, ValueError):
            truncated = True
    messages.sort(key=lambda m: m.log_time_ns)
    return messages, malformed, truncated


def _json_or(path: Path, default):
    return json.loads(path.read_text()) if path.is_file() else default


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
    if (run_dir / "trajectory.npz").is_file():
        with np.load(run_dir / "trajectory.npz") as npz:
            data.trajectory = {k: npz[k] for k in npz.files}
    if (run_dir / RECORDING_FILE).is_file():
        data.messages, data.malformed_in_recording, data.recording_truncated = read_recording(run_dir / RECORDING_FILE)
        if data.messages:
            data.run_id = data.messages[0].body["header"]["run_id"]
    data.recorder_counts = _json_or(run_dir / COUNTS_FILE, None)
    data.clock_offsets = _json_or(run_dir / OFFSETS_FILE, {})
    data.can_log = run_dir / CAN_LOG_FILE if (run_dir / CAN_LOG_FILE).is_file() else None
    return data
