"""CAN bus load from the candump capture (can.log) and the fault timeline of the run.

vcan has no bit timing, so the load is computed the way the bus model charges it: each frame's
bits with stuffing (bench.bus.can.bittiming) at the configured bitrate, summed per window. The
fault timeline is the scenario's fault windows and the injector's log (can/injections.jsonl), both
in seconds since the bus model started; the load's time axis starts at the first captured frame.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import can
import numpy as np

from bench.bus.can.bittiming import DEFAULT_BITRATE_BPS, frame_bits
from bench.report.rundata import RunData

WINDOW_S = 0.1
INJECTIONS_FILE = Path("can") / "injections.jsonl"
BUSMODEL_FILE = Path("can") / "busmodel.json"


@dataclass
class BusLoad:
    window_start_s: np.ndarray      # since the first frame of the capture
    load: np.ndarray                # fraction of the bus time busy per window
    frames: int
    bitrate_bps: int
    fault_windows: list[tuple[str, float, float]] = field(default_factory=list)   # (name, start_s, end_s)
    injections: list[tuple[float, str, str]] = field(default_factory=list)        # (t_s, fault, action)

    def to_metrics(self) -> dict:
        actions: dict[str, int] = {}
        for _, fault, action in self.injections:
            actions[f"{fault} {action}"] = actions.get(f"{fault} {action}", 0) + 1
        return {
            "frames": self.frames,
            "bitrate_bps": self.bitrate_bps,
            "mean_load": float(self.load.mean()) if self.load.size else 0.0,
            "peak_load": float(self.load.max()) if self.load.size else 0.0,
            "faults": [{"name": n, "start_s": a, "end_s": b} for n, a, b in self.fault_windows],
            "injections": actions,
        }


def read_capture(path: Path) -> list[can.Message]:
    return [m for m in can.CanutilsLogReader(str(path)) if not m.is_error_frame]


def bus_load(run: RunData) -> BusLoad | None:
    if run.can_log is None:
        return None
    frames = read_capture(run.can_log)
    can_cfg = getattr(run.scenario, "can", None)
    bitrate = int(getattr(can_cfg, "bitrate_bps", DEFAULT_BITRATE_BPS))
    result = BusLoad(np.zeros(0), np.zeros(0), len(frames), bitrate, _fault_windows(can_cfg), _injections(run.run_dir))
    if frames:
        t_s = np.asarray([f.timestamp - frames[0].timestamp for f in frames])
        bits = np.asarray([frame_bits(f) for f in frames], dtype=float)
        # Rounded first: candump's microsecond timestamps put 0.3 s at 2.9999... windows otherwise.
        window = np.floor(np.round(t_s / WINDOW_S, 6)).astype(int)
        busy_bits = np.bincount(window, weights=bits, minlength=int(window.max()) + 1)
        n_windows = busy_bits.size
        result.window_start_s = np.arange(n_windows) * WINDOW_S
        result.load = busy_bits / (bitrate * WINDOW_S)
    return result


def _fault_windows(can_cfg) -> list[tuple[str, float, float]]:
    """Configured faults as (name, start_s, end_s), times since the bus model started."""
    windows = []
    for fault in getattr(can_cfg, "faults", None) or []:
        start = float(fault.start_s)
        windows.append((str(fault.name), start, start + fault.duration_s if fault.duration_s else float("inf")))
    return windows


def _injections(run_dir: Path) -> list[tuple[float, str, str]]:
    """What the injector did and when (s since the bus model's t0), if it logged anything."""
    path, model = run_dir / INJECTIONS_FILE, run_dir / BUSMODEL_FILE
    if not (path.is_file() and model.is_file()):
        return []
    t0_ns = json.loads(model.read_text()).get("t0_ns", 0)
    records = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return [((r["t_ns"] - t0_ns) / 1e9, r["fault"], r["action"]) for r in records]
