"""Fault descriptions for the bus model, in the manner of Vector CANoe's disturbance settings.

A fault in a scenario names what it does (`name`, a key of FAULTS), which frames it acts on
(`frames`, DBC message names), when (`start_s` after the driver's first command frame, for
`duration_s`, both in the run's simulated seconds: `window_ns` converts them to a bus on the wall
clock), how many frames it affects (`count`, 0 = no limit), how often (`every` n-th matching
frame) and its own parameters (`params`), each with a range. What a fault does to frames is in
injector.py; what a hardware fault ("hardware" trigger: the board's power supply and coils, not
its frames) does is in coils.py. This module only describes and validates, so `bench faults` and
the scenario loader share it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import msgspec

BOARD_FRAMES = ("MTQ_TLM_DIPOLE", "MTQ_TLM_COIL", "MTQ_TLM_SETPOINT", "MTQ_HEARTBEAT", "MTQ_EMCY")


@dataclass(frozen=True)
class Param:
    name: str
    default: float | int | bool
    low: float | None = None
    high: float | None = None
    unit: str = ""
    doc: str = ""

    def check(self, value) -> None:
        if isinstance(self.default, bool):
            if not isinstance(value, bool):
                raise ValueError(f"{self.name} must be true or false, not {value!r}")
            return
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{self.name} must be a number, not {value!r}")
        if isinstance(self.default, int) and not float(value).is_integer():
            raise ValueError(f"{self.name} must be an integer, not {value!r}")
        if not self.low <= value <= self.high:
            raise ValueError(f"{self.name} = {value} is out of range [{self.low}, {self.high}]{' ' + self.unit if self.unit else ''}")


@dataclass(frozen=True)
class FaultKind:
    name: str
    summary: str
    default_frames: tuple[str, ...]
    params: tuple[Param, ...] = ()
    # "frame": acts on each matching frame a node sends; "window": acts for a time window,
    # whatever the nodes send, and needs duration_s; "hardware": acts on the board's power supply
    # or coils (bench/bus/can/coils.py) from start_s, for duration_s or to the end of the run.
    trigger: str = "frame"
    needs_duration: bool = False      # a hardware fault that must end (a power loss)


_SEED = Param("seed", 1, 0, 2**31 - 1, "", "random generator seed (which bits)")
_AXIS = Param("axis", 0, 0, 2, "", "the body axis of the coil: 0 = x, 1 = y, 2 = z")
FAULTS: dict[str, FaultKind] = {f.name: f for f in (
    FaultKind("drop", "frame lost on the bus", ("MTQ_CMD",)),
    FaultKind("delay", "frame held back before it competes for the bus", ("MTQ_CMD",),
              (Param("delay_s", 0.05, 1e-4, 2.0, "s", "how long each frame is held"),)),
    FaultKind("duplicate", "frame sent again right after itself", ("MTQ_CMD",),
              (Param("copies", 1, 1, 10, "", "extra copies per frame"),)),
    FaultKind("replay", "an earlier frame, recorded on the bus, sent again", ("MTQ_CMD",),
              (Param("after_s", 0.2, 0.0, 10.0, "s", "age of the recording when replays start"),)),
    FaultKind("corrupt", "the same data bits (never the counter) flipped in each frame, E2E CRC left or recomputed",
              ("MTQ_CMD",),
              (Param("bits", 1, 1, 3, "", "bits flipped per frame (CRC-8 0x2F detects up to 3 here)"),
               Param("recompute_crc", False, doc="recompute the E2E CRC with the right data id (corruption before protection)"),
               _SEED)),
    FaultKind("spoof", "a command from another source, sent right after a genuine one", ("MTQ_CMD",),
              (Param("dipole_am2", 0.15, -3.2, 3.2, "A.m2", "dipole the spoofer commands on every axis"),
               Param("knows_data_id", False, doc="spoofer knows the E2E data ids (E2E then cannot reject it)"),
               Param("data_id", 0x00, 0, 255, "", "data id the spoofer's CRC uses when it does not know ours"))),
    FaultKind("counter_freeze", "alive counter stuck at its value when the fault starts (CRC valid)", ("MTQ_CMD",)),
    FaultKind("counter_offset", "alive counter shifted by an offset (CRC valid)", ("MTQ_CMD",),
              (Param("offset", 5, 1, 15, "", "added to the counter modulo 16"),)),
    FaultKind("flood", "babbling node sending back to back at a higher priority", (),
              (Param("frame_id", 0x010, 0, 0x7FF, "", "its 11-bit identifier (lower wins arbitration)"),
               Param("period_s", 0.0, 0.0, 1.0, "s", "time between its frames; 0 = back to back"),
               Param("dlc", 8, 0, 8, "bytes", "its payload length")), trigger="window"),
    FaultKind("telemetry_freeze", "telemetry frozen at its values when the fault starts while the board and its "
              "coils go on as commanded", ("MTQ_TLM_DIPOLE", "MTQ_TLM_COIL"),
              (Param("freeze_counter", False, doc="freeze the alive counter too (else it keeps counting)"),),
              trigger="window"),
    # The board's hardware (coils.py): the plant's torque changes, not only the frames.
    FaultKind("board_power_loss", "the board loses power: coils off, no frame at all (no ACK either); when power "
              "returns it boots (CiA 301 boot-up, pre-operational) and takes commands only after the driver's NMT "
              "start", (), trigger="hardware", needs_duration=True),
    FaultKind("coil_open", "an open coil: no current on that axis whatever is commanded (the current telemetry, "
              "in series with it, shows zero)", (), (_AXIS,), trigger="hardware"),
    FaultKind("coil_stuck", "the axis's coil driver holds one dipole whatever is commanded, in safe state too "
              "(the current telemetry shows it)", (),
              (_AXIS, Param("value_am2", 0.1, -3.2, 3.2, "A.m2", "the dipole it holds (within the board's "
                            "max_dipole_am2)")), trigger="hardware"),
    FaultKind("coil_reversed", "the axis's coil wired backwards after the current sensor: opposite dipole, "
              "telemetry as commanded", (), (_AXIS,), trigger="hardware"),
    FaultKind("coil_gain", "the axis's coil gives gain x the commanded dipole (a weak coil), telemetry reads the "
              "commanded current", (), (_AXIS, Param("gain", 0.5, 0.0, 1.0, "", "dipole per commanded dipole")),
              trigger="hardware"),
    FaultKind("error_frames", "each transmission of a matching frame destroyed by an error frame", ("MTQ_CMD",),
              (Param("restart_delay_s", 0.1, 0.0, 5.0, "s", "bus-off recovery delay (SocketCAN restart-ms)"),)),
)}


# Kinds whose names promised more than they did (issue 45): refused, naming what replaces them.
RETIRED = {
    "board_death": "fault 'board_death' is no more (it silenced frames while the coils went on): use "
                   "'board_power_loss' (coils off, no frames, a reboot the driver recovers from)",
    "stuck_actuator": "fault 'stuck_actuator' is no more (it froze the telemetry only): use 'telemetry_freeze' "
                      "for that, or 'coil_stuck' for a coil driver holding one value",
}
HARDWARE = "hardware"


class FaultSpec(msgspec.Struct, forbid_unknown_fields=True):
    # Bounded like every scenario number (docs/run_safety.md): times to 1e6 s (11.6 days; times
    # become integer nanoseconds, which 1e300 s overflowed), counts to 1e9 frames (a saturated bus
    # carries ~8000 frames/s), parameters by their own ranges (Param.check).
    name: Annotated[str, msgspec.Meta(max_length=64)]
    frames: Annotated[list[Annotated[str, msgspec.Meta(max_length=64)]], msgspec.Meta(max_length=64)] = []
    start_s: Annotated[float, msgspec.Meta(ge=0, le=1e6)] = 0.0
    duration_s: Annotated[float, msgspec.Meta(gt=0, le=1e6)] | None = None
    count: Annotated[int, msgspec.Meta(ge=0, le=1_000_000_000)] = 0
    every: Annotated[int, msgspec.Meta(ge=1, le=1_000_000_000)] = 1
    params: Annotated[dict[Annotated[str, msgspec.Meta(max_length=64)], bool | int | float], msgspec.Meta(max_length=16)] = {}

    def __post_init__(self):
        if self.name in RETIRED:
            raise ValueError(RETIRED[self.name])
        kind = FAULTS.get(self.name)
        if kind is None:
            raise ValueError(f"unknown fault {self.name!r} (known: {', '.join(sorted(FAULTS))})")
        declared = {p.name: p for p in kind.params}
        for key, value in self.params.items():
            if key not in declared:
                known = ", ".join(declared) or "none"
                raise ValueError(f"fault {self.name!r}: unknown parameter {key!r} (known: {known})")
            try:
                declared[key].check(value)
            except ValueError as exc:
                raise ValueError(f"fault {self.name!r}: parameter {exc}") from None
        from bench.bus.can.protocol import database  # the DBC is the list of frame names
        names = {m.name for m in database().messages}
        for frame in self.frames:
            if frame not in names:
                raise ValueError(f"fault {self.name!r}: unknown frame {frame!r} (known: {', '.join(sorted(names))})")
        if (kind.trigger == "window" or kind.needs_duration) and self.duration_s is None:
            raise ValueError(f"fault {self.name!r} acts for a time window: give duration_s")
        if kind.trigger == HARDWARE and (self.frames or self.count or self.every != 1):
            raise ValueError(f"fault {self.name!r} acts on the board's hardware, not on frames: "
                             f"no frames, count or every")

    @property
    def kind(self) -> FaultKind:
        return FAULTS[self.name]

    def param(self, name: str):
        """The parameter's value, or its default."""
        if name in self.params:
            return self.params[name]
        return next(p.default for p in self.kind.params if p.name == name)

    def target_frames(self) -> tuple[str, ...]:
        return tuple(self.frames) or self.kind.default_frames

    @property
    def hardware(self) -> bool:
        return self.kind.trigger == HARDWARE

    def window_ns(self, t0_ns: int, wall_s_per_sim_s: float = 1.0) -> tuple[int, int | None]:
        """The fault's window on a clock whose t0_ns is the first command frame: start_s and
        duration_s are simulated seconds, `wall_s_per_sim_s` of that clock's seconds each (1 on a
        bus on simulated time; 1 / time_factor on a real-time run's wall clock)."""
        start = t0_ns + round(self.start_s * wall_s_per_sim_s * 1e9)
        return start, (start + round(self.duration_s * wall_s_per_sim_s * 1e9) if self.duration_s is not None else None)
