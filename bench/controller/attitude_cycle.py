"""One attitude-controller cycle under its deadline: estimate in, dipole out. Shared by the
controller process and the in-process loop (bench.sim) so the two cannot drift apart.

The law picks the dipole (bench.controller.attitude_laws, from the scenario); the deadline monitor
of the translational loop times it, and on a miss in real-time mode holds the last dipole. A law
that needs an attitude gets no say until the estimate is valid: the cycle commands zero (coils off).

The FDIR actuator monitor ([attitude_control.fdir], bench.controller.fdir) takes the estimate and
the dipole commanded on it in `monitor_actuators`, called once the command is out (its fit must not
delay the command: ~0.7 ms a simulated second at 1 Hz, ~5 ms at 10 Hz), and says when a
coil does not give the torque it should, on the estimate's simulated time; with a pointing limit,
the pointing envelope (bench.gnc.pointing_envelope) says when the law's error stays outside it. With `accommodate` on,
`run` adapts the law's dipole to the coils as the monitor has identified them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.controller.attitude_laws import build_attitude_law
from bench.config.controller import ATTITUDE_FREE_LAWS
from bench.controller.deadline import DeadlineMonitor
from bench.controller.fdir import build_actuator_monitor, build_pointing_envelope
from bench.gnc.actuator_monitor import FdirEvent, accommodate
from bench.gnc.attitude_law import AttitudeControlInput
from bench.runtime.deadline import CycleOutcome
from bench.runtime.time_model import TimeModel
from bench.scenario import Scenario


@dataclass
class AttitudeCycleOutcome:
    dipole_am2: np.ndarray
    monitored: CycleOutcome | None     # None when no law ran (no valid estimate yet)
    saturated: bool
    weak_field: bool
    error_angle_rad: float | None


class AttitudeCycle:
    def __init__(self, scenario: Scenario):
        self.law_name = scenario.attitude_control.law
        self.law = build_attitude_law(scenario)
        self.needs_attitude = self.law_name not in ATTITUDE_FREE_LAWS
        deadline = scenario.controller.deadline
        if deadline.fallback == "lqr":
            raise ValueError("controller.deadline.fallback: 'lqr' is a translational law; the attitude loop holds")
        self.monitor = DeadlineMonitor(deadline, n_inputs=3, apply_fallback=TimeModel.of(scenario).deadlines_apply)
        self.saturated_cycles = 0
        self.weak_field_cycles = 0
        self.waiting_for_estimate_cycles = 0
        self.bad_estimate_cycles = 0
        self.fdir = build_actuator_monitor(scenario)      # None: [attitude_control.fdir] enabled = false
        self.envelope = build_pointing_envelope(scenario)  # None: no pointing_error_limit_deg
        self._envelope_input: tuple[float, float | None] | None = None
        self.accommodate = self.fdir is not None and scenario.attitude_control.fdir.accommodate
        if self.accommodate:
            from bench.controller.attitude_laws import dipole_limit_am2

            self.dipole_limit_am2 = dipole_limit_am2(scenario)
        self.accommodated_cycles = 0
        self._fdir_input: tuple | None = None     # this cycle's data for the monitor; None: restart its window

    def run(self, time_s: float, valid: bool, q_wxyz, omega_radps, field_body_t,
            start_ns: int | None = None, gyro_bias_radps=None) -> AttitudeCycleOutcome:
        """`gyro_bias_radps`: the estimate's bias, for the FDIR monitor (None: zero)."""
        if self.needs_attitude and not valid:
            self.waiting_for_estimate_cycles += 1
            self._fdir_input = None
            return AttitudeCycleOutcome(np.zeros(3), None, False, False, None)
        q, omega, field_t = (np.asarray(v, float) for v in (q_wxyz, omega_radps, field_body_t))
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(omega)) and abs(np.linalg.norm(q) - 1.0) < 1e-6):
            # A schema-valid estimate with a NaN or non-unit attitude: coils off, counted, never fatal.
            self.bad_estimate_cycles += 1
            self._fdir_input = None
            return AttitudeCycleOutcome(np.zeros(3), None, False, False, None)
        x = AttitudeControlInput(time_s, q, omega, field_t)
        outcome = self.monitor.run_cycle(x, self.law.eval, start_ns)
        dipole = outcome.thrust_n      # the monitor's name for the command vector
        if not np.all(np.isfinite(dipole)):
            # The laws never return one (they check |B| and finiteness); a last guard all the same.
            dipole = np.zeros(3)
        info = outcome.info
        saturated, weak = bool(info.get("saturated", False)), bool(info.get("weak_or_bad_field", False))
        self.saturated_cycles += saturated
        self.weak_field_cycles += weak
        angle = info.get("error_angle_rad")
        self._envelope_input = (time_s, None if angle is None else float(angle))
        if self.fdir is not None:
            if self.accommodate and any(b.fault is not None for b in self.fdir.beliefs):
                dipole = accommodate(dipole, field_t, self.fdir.beliefs, self.dipole_limit_am2)
                self.accommodated_cycles += 1
            bias = np.zeros(3) if gyro_bias_radps is None else gyro_bias_radps
            self._fdir_input = (time_s, q, omega, bias, field_t, dipole) if valid else None
        return AttitudeCycleOutcome(dipole, outcome, saturated, weak, None if angle is None else float(angle))

    def monitor_actuators(self, board_ok: bool = True) -> list[FdirEvent]:
        """The FDIR monitor's step on this cycle's estimate and command (after `run`, once the
        command is out): the coil faults detected at this cycle, usually none. `board_ok`: the
        flight-side driver's word on the board (BoardHealth.ok, as of the step just flown). While
        it says the board is lost, off, in safe state or its commands refused, the coils did not
        make the commanded torque for a reason the driver already names: the monitor's window
        restarts instead of reading a power loss or a run of dropped commands as a weak coil."""
        events = []
        if self.envelope is not None and self._envelope_input is not None:
            events += self.envelope.step(*self._envelope_input)
        self._envelope_input = None
        if self.fdir is None:
            return events
        pending, self._fdir_input = self._fdir_input, None
        if pending is None or not board_ok:
            self.fdir.reset()     # no valid estimate or no command this cycle: the window restarts
            return events
        return self.fdir.step(*pending) + events

    def fdir_events(self) -> list:
        """Every FDIR detection so far: the coils' (actuator monitor), then the pointing envelope's."""
        return ((self.fdir.events if self.fdir is not None else [])
                + (self.envelope.events if self.envelope is not None else []))

    def summary(self) -> dict:
        return self.monitor.summary() | {"law": self.law_name, "saturated_cycles": self.saturated_cycles,
                                         "weak_field_cycles": self.weak_field_cycles,
                                         "waiting_for_estimate_cycles": self.waiting_for_estimate_cycles,
                                         "bad_estimate_cycles": self.bad_estimate_cycles} | (
            {} if self.fdir is None else {"fdir_events": len(self.fdir_events()),
                                          "fdir_accommodated_cycles": self.accommodated_cycles})
