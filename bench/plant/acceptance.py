"""The plant's actuator output stage: which commands it applies, and what it does with the rest.

Whatever arrives on a command topic (from the controller, a rogue process on the same host, a
replay), the plant applies a command only if it is
- the right size and finite (a 1e308 N or NaN command turns the state into NaN),
- for the step being integrated (lock-step), or for the current step and no older than
  `max_age_s` (real-time; a sample-based freshness check as an output stage does), and
- inside the actuator envelope (|u_i| <= u_max per axis, plus a tolerance for the rounding of
  a saturating flight side).
Everything else is counted under its reason and not applied; the output holds the last accepted
command or goes to zero, as the scenario says (`[plant.command_acceptance] on_reject`). PX4 does
the same at its output stage: the mixer clamps, and nothing non-finite reaches an actuator.

One `CommandGate` per actuator: the translational plant gates thrust in N, the attitude plant gates
the magnetorquer dipole in A m^2 with the same class (its sequence is the board's alive counter, so
it uses the age check only). Who may publish is the transport's job (multi-host issue); this
module makes sure that whatever arrives, only what is physically and temporally valid is applied.
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Literal, Sequence

import numpy as np

OnReject = Literal["hold", "zero"]
ACCEPTANCE_FILE = "command_acceptance.json"    # what the plant accepted and refused, per actuator

# Reasons a command is refused, in the order they are checked. They are the keys of the counts
# that go to command_acceptance.json, metrics.json and the report.
WRONG_SIZE = "wrong_size"
NON_FINITE = "non_finite"
STALE = "stale"                    # for a step already integrated (late, or a replay)
FUTURE = "future"                  # for a step the plant has not reached (no sample exists yet)
TOO_OLD = "too_old"                # real-time: its age exceeds max_age_s
OUT_OF_ENVELOPE = "out_of_envelope"
REASONS = (WRONG_SIZE, NON_FINITE, STALE, FUTURE, TOO_OLD, OUT_OF_ENVELOPE)

# A flight side that saturates at exactly u_max may hand over u_max * (1 + a few ulp) after a
# unit conversion; 1e-9 relative is far below any actuator's resolution.
ENVELOPE_REL_TOL = 1e-9


@dataclass(frozen=True)
class ActuatorEnvelope:
    """What the actuator can physically do: `size` axes, each |value| <= max_abs (in `unit`)."""

    name: str
    unit: str
    max_abs: float
    size: int = 3

    def __post_init__(self):
        if not (math.isfinite(self.max_abs) and self.max_abs > 0):
            raise ValueError(f"{self.name}: max_abs must be finite and > 0, got {self.max_abs}")


@dataclass
class Verdict:
    accepted: bool
    reason: str | None = None


@dataclass
class CommandGate:
    """Accepts or refuses commands for one actuator and keeps the output the plant applies.

    `check(...)` decides and counts; `output` is what the plant applies this step: the last
    accepted command, or zero after a refusal when on_reject is "zero".
    """

    envelope: ActuatorEnvelope
    on_reject: OnReject = "hold"
    max_age_s: float | None = None
    accepted: int = 0
    rejected: Counter = field(default_factory=Counter)
    output: np.ndarray = None      # set in __post_init__: zeros of the envelope's size

    def __post_init__(self):
        if self.on_reject not in ("hold", "zero"):
            raise ValueError(f"on_reject must be 'hold' or 'zero', got {self.on_reject!r}")
        if self.output is None:
            self.output = np.zeros(self.envelope.size)

    def check(self, value: Sequence[float], *, seq: int | None = None, step: int | None = None,
              age_s: float | None = None) -> Verdict:
        """Judge one command. seq/step: the command's sample index and the plant's step (both or
        neither); age_s: how old the command is (real-time), checked against max_age_s."""
        reason = self._reason(value, seq, step, age_s)
        if reason is None:
            self.accepted += 1
            self.output = np.array(value, dtype=float)
            return Verdict(True)
        self.rejected[reason] += 1
        return Verdict(False, reason)

    def refuse_step(self) -> None:
        """No acceptable command for this step: hold the last accepted one, or zero."""
        if self.on_reject == "zero":
            self.output = np.zeros(self.envelope.size)

    def _reason(self, value, seq, step, age_s) -> str | None:
        try:
            u = np.asarray(value, dtype=float)
        except (TypeError, ValueError, OverflowError):
            return WRONG_SIZE
        if u.shape != (self.envelope.size,):
            return WRONG_SIZE
        if not np.all(np.isfinite(u)):
            return NON_FINITE
        if seq is not None and step is not None:
            if seq < step:
                return STALE
            if seq > step:
                return FUTURE
        if self.max_age_s is not None and age_s is not None and not (0.0 <= age_s <= self.max_age_s):
            return TOO_OLD
        if np.max(np.abs(u)) > self.envelope.max_abs * (1.0 + ENVELOPE_REL_TOL):
            return OUT_OF_ENVELOPE
        return None

    def counts(self) -> dict:
        return {"actuator": self.envelope.name, "unit": self.envelope.unit, "max_abs": self.envelope.max_abs,
                "on_reject": self.on_reject, "accepted": self.accepted,
                "rejected": {reason: int(self.rejected[reason]) for reason in REASONS if self.rejected[reason]}}
