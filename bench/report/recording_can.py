"""CAN frames of recording.mcap on the run's simulated time, decoded, in every mode.

While a run runs, the recorder gives a CAN frame the simulated time of the newest step it has seen
(bench/recorder.py: a frame has no simulated time of its own there), and a lock-step run whose bus
runs on simulated time has no frames on Zenoh at all: the flight side and the bus trade each step's
frames in one `canstep/*` batch. After the run, the bus model's capture (can.log) and the run's
clock place every frame; `place_can_frames` rewrites the recording once the run is over:

- a frame the recorder took from a Zenoh CAN channel (`can/flight`, `can/board`) gets the simulated
  time of its sender's timestamp (wall clock, mapped by the run's clock) as its log time and its
  `sim_time_s`;
- a run without such frames (the lock-step bus on simulated time) gets them from can.log, decoded
  with the run's DBC: `can/flight` for the flight side's frames (DBC sender OBC), `can/board` for the
  board's (MTQ), `can/bus` for the rest (error frames, identifiers not in the DBC), each on the
  simulated time of its capture stamp; their channels' metadata say `source` = "can.log".

Log times are clipped to the run's span [first step, last step + one step]: the board boots before
step 0 and reaches its safe state after the last one. Everything else is copied as it is. A
recording that does not read to its end (a recorder killed mid-run) is left alone.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import can
import numpy as np
from mcap.reader import make_reader
from mcap.writer import Writer

from bench.recorder import CAN_FRAME_SCHEMA, CAN_FRAME_SCHEMA_NAME, RECORDING_FILE, can_frame_json
from bench.report import canbus
from bench.report.timebase import RunClock, wall_to_mono_ns

CAPTURE_SOURCE = "can.log"
MARK = "can_frames"          # the MCAP metadata record saying the frames were placed


def _span(trajectory: dict) -> tuple[float, float] | None:
    times = trajectory.get("att_time_s", trajectory.get("t_s"))
    if times is None or len(times) == 0:
        return None
    times = np.asarray(times, dtype=float)
    return float(times[0]), float(times[-1] + (times[-1] - times[-2] if len(times) > 1 else 0.0))


def _topic_of(direction: str | None) -> str:
    sender = (direction or "").split("->", 1)[0]
    return {"OBC": "can/flight", "MTQ": "can/board"}.get(sender, "can/bus")


def place_can_frames(run) -> dict | None:
    """Rewrite run_dir/recording.mcap with its CAN frames on simulated time (module docstring);
    returns what it did ({"retimed": n, "from_capture": n}) or None when it left the file alone."""
    path = Path(run.run_dir) / RECORDING_FILE
    span = _span(run.trajectory)
    if not path.is_file() or span is None or run.scenario is None or getattr(run.scenario, "can", None) is None:
        return None
    clock = RunClock.from_run(run.trajectory, run.scenario)
    model = canbus._bus_model_report(run.run_dir)
    lo, hi = span
    sim_bus = model.get("clock") == "simulated"
    wall_offset_s = model.get("wall_offset_s")

    def log_ns(sim_s: float) -> int:
        return int(round(min(max(sim_s, lo), hi) * 1e9))

    # What the file holds, from its summary (not its messages: a long run's recording is large; it
    # is read once more below, streamed, to copy it).
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            metadata = [(m.name, dict(m.metadata)) for m in reader.iter_metadata()]
    except Exception:   # noqa: BLE001 - a truncated or unreadable recording stays as it is
        return None
    if summary is None:
        return None
    counts = summary.statistics.channel_message_counts if summary.statistics else {}
    live = [c for c in summary.channels.values() if c.metadata.get("source") != CAPTURE_SOURCE
            and summary.schemas.get(c.schema_id) is not None
            and summary.schemas[c.schema_id].name == CAN_FRAME_SCHEMA_NAME and counts.get(c.id, 1)]
    retime = bool(live) and not sim_bus and clock is not None and wall_offset_s is not None
    captured = []
    if not live and run.can_log is not None:
        from bench.report.tables import _protocol

        frames = list(can.CanutilsLogReader(str(run.can_log)))   # error frames too, as can_frames.parquet
        sim_s = canbus.capture_sim_s(run.run_dir, clock, [m.timestamp for m in frames]) if frames else None
        if sim_s is not None:
            protocol = _protocol(Path(run.run_dir))
            running = -np.inf
            for i, (msg, t) in enumerate(zip(frames, sim_s)):
                running = max(running, min(max(float(t), lo), hi))
                body = can_frame_json(protocol, msg, str(msg.channel), 0, i, running)
                body.pop("sender_id")
                body["sequence"] = i        # the frame's place in can.log
                captured.append((_topic_of(body["direction"]), log_ns(running), body, msg.timestamp))
    if not retime and not captured:
        return None

    tmp = path.with_name(path.name + ".placing")
    retimed = 0
    with open(path, "rb") as source, open(tmp, "wb") as out:
        records = make_reader(source).iter_messages(log_time_order=False)
        writer = Writer(out)
        writer.start(profile="", library="bench.report.recording_can")
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        for schema, channel, message in records:
            if channel.metadata.get("source") == CAPTURE_SOURCE:
                continue     # placed before: placed again below
            if channel.id not in channel_ids:
                sid = 0
                if schema is not None:
                    if schema.id not in schema_ids:
                        schema_ids[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
                    sid = schema_ids[schema.id]
                channel_ids[channel.id] = writer.register_channel(channel.topic, channel.message_encoding, sid,
                                                                  dict(channel.metadata))
            log_time, data = message.log_time, message.data
            if retime and schema is not None and schema.name == CAN_FRAME_SCHEMA_NAME:
                body = json.loads(data)
                t = float(clock.sim_s(wall_to_mono_ns(body["timestamp_s"], float(wall_offset_s))))
                log_time = log_ns(t)
                body["sim_time_s"] = log_time / 1e9
                data = json.dumps(body).encode()
                retimed += 1
            writer.add_message(channel_ids[channel.id], log_time=log_time, data=data,
                               publish_time=message.publish_time, sequence=message.sequence)
        if captured:
            can_schema = writer.register_schema(CAN_FRAME_SCHEMA_NAME, "jsonschema", json.dumps(CAN_FRAME_SCHEMA).encode())
            topics: dict[str, int] = {}
            for topic, t_ns, body, stamp in captured:
                if topic not in topics:
                    topics[topic] = writer.register_channel(topic, "json", can_schema, {"source": CAPTURE_SOURCE})
                writer.add_message(topics[topic], log_time=t_ns, data=json.dumps(body).encode(),
                                   publish_time=t_ns, sequence=body["sequence"])
        for name, data in metadata:
            if name != MARK:
                writer.add_metadata(name, data)
        done = {"retimed": retimed, "from_capture": len(captured)}
        writer.add_metadata(MARK, {"log_time": "the run's simulated time, clipped to the run's span",
                                   **{k: str(v) for k, v in done.items()}})
        writer.finish()
    os.replace(tmp, path)
    return done
