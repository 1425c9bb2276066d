"""Latency of the loop from the monotonic stamps in message headers.

Every stage stamps `time.monotonic_ns()` into the header of the sample it handles, and headers flow
downstream, so the command for step k carries every stamp from sensing on. Per step k the stamps of
the loop's recorded messages of that step are merged (the most downstream message first), then the plant's
own record of what it applied (trajectory.npz `stamp_<stage>_ns`) fills what no message carried
(plant_received, applied). A hop is the difference of two stamps of the same step.

Stamps of different hosts are on different monotonic clocks: where clock_offsets.json says a
process ran on another host than the recorder, its offset is removed first (and its uncertainty
stated in the report). On one host every process reads the same clock and nothing is corrected.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.bus import keys
from bench.bus.schemas import STAGES
from bench.report.rundata import RunData

# Which process stamps which stage (for clock-offset correction across hosts).
STAGE_PROCESS = {
    "sensed": "plant",
    "estimator_received": "estimator",
    "estimated": "estimator",
    "controller_received": "controller",
    "commanded": "controller",
    "can_sent": "canbus",
    "board_received": "mtq",
    "plant_received": "plant",
    "applied": "plant",
}


@dataclass(frozen=True)
class Hop:
    name: str
    start: str
    end: str
    # The direct controller-to-plant hop only exists for steps whose command did not go by CAN.
    only_without: str | None = None


HOPS = (
    Hop("plant → estimator", "sensed", "estimator_received"),
    Hop("estimator compute", "estimator_received", "estimated"),
    Hop("estimator → controller", "estimated", "controller_received"),
    Hop("controller compute", "controller_received", "commanded"),
    Hop("controller → plant", "commanded", "plant_received", only_without="can_sent"),
    Hop("controller → CAN", "commanded", "can_sent"),
    Hop("CAN → board", "can_sent", "board_received"),
    Hop("board → plant", "board_received", "plant_received"),
    Hop("plant apply", "plant_received", "applied"),
)
# The magnetorquer board's own chain: its MtqApplied header carries board_received and applied
# under the board's counter, not the plant's step index, so it is kept apart from the loop's steps.
BOARD_APPLY = Hop("board decode → coils set (CAN)", "board_received", "applied")
# Two end-to-end quantities, named by what they measure. The plant applies a command at a step
# boundary: in real time a command that reaches it during step k waits there for step k+1 (the
# zero-order hold, one step), in lock-step the plant waits for it and applies it at once. So
# sensed -> applied holds the step hold in real time (101.5 ms at 0.1 s steps) and not in lock-step;
# sensed -> at the plant (plant_received) holds no hold in either mode: the loop's own latency,
# comparable across modes.
SENSE_TO_PLANT = Hop("sensed → command at the plant (loop, no hold)", "sensed", "plant_received")
END_TO_END = Hop("sensed → applied (with the plant's step hold in real time)", "sensed", "applied")
SENSE_TO_COMMAND = Hop("sensed → commanded", "sensed", "commanded")
PERCENTILES = (50, 90, 99)


# Topics whose headers carry the plant's step index k as seq: the translation loop.
LOOP_TOPICS = (keys.TRUTH, keys.SENSE_RELPOS, keys.ESTIMATE_TRANSLATION, keys.COMMAND_THRUST)


def stamps_from_messages(run: RunData, topics=LOOP_TOPICS) -> dict[int, dict[str, int]]:
    """Per step, the union of the stamps of every recorded message of that step on `topics`.

    The message with the most stamps (the furthest downstream) wins a conflict: it is the chain
    that reached the actuator. Messages without stamps (status, stats) contribute nothing.
    """
    by_seq: dict[int, list[dict[str, int]]] = {}
    for message in run.messages:
        if message.topic in topics and message.stamps_ns:
            by_seq.setdefault(message.seq, []).append(message.stamps_ns)
    merged = {}
    for seq, stamp_sets in by_seq.items():
        stamps: dict[str, int] = {}
        for one in sorted(stamp_sets, key=len, reverse=True):
            for stage, value in one.items():
                stamps.setdefault(stage, int(value))
        merged[seq] = stamps
    return merged


def stamps_from_trajectory(trajectory: dict[str, np.ndarray]) -> dict[int, dict[str, int]]:
    """The plant's record of the command it applied at each step (-1 where absent)."""
    per_seq: dict[int, dict[str, int]] = {}
    for stage in STAGES:
        column = trajectory.get(f"stamp_{stage}_ns")
        if column is None:
            continue
        for k, value in enumerate(np.asarray(column)):
            if value >= 0:
                per_seq.setdefault(k, {})[stage] = int(value)
    return per_seq


def merged_stamps(run: RunData) -> dict[int, dict[str, int]]:
    """Recording first, the plant's record for whatever the recording does not carry."""
    merged = stamps_from_messages(run)
    for seq, stamps in stamps_from_trajectory(run.trajectory).items():
        target = merged.setdefault(seq, {})
        for stage, value in stamps.items():
            target.setdefault(stage, value)
    return correct_clock_offsets(merged, run.clock_offsets)


def correct_clock_offsets(stamps: dict[int, dict[str, int]], offsets: dict) -> dict[int, dict[str, int]]:
    """Move stamps of processes on other hosts onto the reference (recorder's) clock."""
    reference_host = offsets.get("recorder", {}).get("host")
    shift = {
        process: int(o["offset_ns"])
        for process, o in offsets.items()
        if reference_host is not None and o.get("host") != reference_host
    }
    if not shift:
        return stamps
    return {
        seq: {stage: v - shift.get(STAGE_PROCESS.get(stage, ""), 0) for stage, v in s.items()}
        for seq, s in stamps.items()
    }


def hop_samples_s(stamps: dict[int, dict[str, int]], hop: Hop) -> tuple[np.ndarray, np.ndarray]:
    """(steps, latency in s) of every step that has both stamps of the hop."""
    seqs, values = [], []
    for seq in sorted(stamps):
        s = stamps[seq]
        if hop.start in s and hop.end in s and (hop.only_without is None or hop.only_without not in s):
            seqs.append(seq)
            values.append((s[hop.end] - s[hop.start]) / 1e9)
    return np.asarray(seqs, dtype=int), np.asarray(values, dtype=float)


def percentiles_ms(latency_s: np.ndarray) -> dict:
    """n, mean, p50/p90/p99 and max in milliseconds (numpy's linear-interpolation percentiles)."""
    if latency_s.size == 0:
        return {"n": 0}
    ms = latency_s * 1e3
    out = {"n": int(ms.size), "mean_ms": float(ms.mean())}
    out.update({f"p{p}_ms": float(np.percentile(ms, p)) for p in PERCENTILES})
    out["max_ms"] = float(ms.max())
    return out


@dataclass
class LatencyResult:
    hops: dict[str, np.ndarray]            # hop name -> latency samples in s (only hops with data)
    summary: dict[str, dict]               # hop name -> percentiles_ms

    def to_metrics(self) -> dict:
        return self.summary


def latency(run: RunData) -> LatencyResult:
    """Every hop with data, then sense-to-command and end-to-end."""
    stamps = merged_stamps(run)
    hops: dict[str, np.ndarray] = {}
    for hop in (*HOPS, SENSE_TO_COMMAND, SENSE_TO_PLANT, END_TO_END):
        _, values = hop_samples_s(stamps, hop)
        if values.size:
            hops[hop.name] = values
    board = correct_clock_offsets(stamps_from_messages(run, (keys.ACTUATOR_MTQ,)), run.clock_offsets)
    _, values = hop_samples_s(board, BOARD_APPLY)
    if values.size:
        hops[BOARD_APPLY.name] = values
    return LatencyResult(hops, {name: percentiles_ms(v) for name, v in hops.items()})
