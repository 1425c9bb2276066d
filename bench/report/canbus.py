"""CAN bus load from the candump capture (can.log), and the fault timeline of the scenario.

vcan has no bit timing, so the load is computed the way the bus model charges it: the bits of
each frame at the configured bitrate, summed per window. Frame length without stuff bits:
47 + 8*DLC bits for an 11-bit identifier, 67 + 8*DLC for a 29-bit one (ISO 11898-1, including
the 3-bit interframe space): a lower bound of the real occupancy.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import can
import numpy as np

from bench.report.rundata import RunData

DEFAULT_BITRATE_BPS = 1_000_000
WINDOW_S = 0.1


def frame_bits(is_extended_id: bool, dlc: int) -> int:
    return (67 if is_extended_id else 47) + 8 * dlc


@dataclass
class BusLoad:
    window_start_s: np.ndarray      # since the first frame of the capture
    load: np.ndarray                # fraction of the bus time busy per window
    frames: int
    bitrate_bps: int
    fault_windows: list[tuple[str, float, float]] = field(default_factory=list)   # (name, start_s, end_s)

    def to_metrics(self) -> dict:
        return {
            "frames": self.frames,
            "bitrate_bps": self.bitrate_bps,
            "mean_load": float(self.load.mean()) if self.load.size else 0.0,
            "peak_load": float(self.load.max()) if self.load.size else 0.0,
            "faults": [{"name": n, "start_s": a, "end_s": b} for n, a, b in self.fault_windows],
        }


def read_capture(path: Path) -> list[can.Message]:
    return list(can.CanutilsLogReader(str(path)))


def bus_load(run: RunData) -> BusLoad | None:
    if run.can_log is None:
        return None
    frames = [f for f in read_capture(run.can_log) if not f.is_error_frame]
    can_cfg = getattr(run.scenario, "can", None)
    bitrate = int(getattr(can_cfg, "bitrate_bps", DEFAULT_BITRATE_BPS))
    if not frames:
        return BusLoad(np.zeros(0), np.zeros(0), 0, bitrate, _fault_windows(can_cfg))
    t0 = frames[0].timestamp
    t_s = np.asarray([f.timestamp - t0 for f in frames])
    bits = np.asarray([frame_bits(f.is_extended_id, f.dlc) for f in frames], dtype=float)
    n_windows = int(t_s.max() // WINDOW_S) + 1
    busy_bits = np.bincount((t_s // WINDOW_S).astype(int), weights=bits, minlength=n_windows)
    return BusLoad(np.arange(n_windows) * WINDOW_S, busy_bits / (bitrate * WINDOW_S), len(frames), bitrate,
                   _fault_windows(can_cfg))


def _fault_windows(can_cfg) -> list[tuple[str, float, float]]:
    """Configured faults as (name, start_s, end_s), times since the bus model started."""
    windows = []
    for fault in getattr(can_cfg, "faults", None) or []:
        start = float(getattr(fault, "start_s", 0.0))
        duration = getattr(fault, "duration_s", None)
        windows.append((str(fault.name), start, start + float(duration) if duration else float("inf")))
    return windows
