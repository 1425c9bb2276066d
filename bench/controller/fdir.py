"""The FDIR actuator monitor as the flight side runs it: built from the scenario's beliefs, and its
detections reported where the driver's go.

The algorithm is bench.gnc.actuator_monitor (pure); this module only reads the scenario:
- inertia: [attitude_control] inertia_kgm2 (else the plant's), as the laws believe it;
- the board: the command frame's scaling (mtq.dbc), then [can.board] dipole_resolution_am2 and
  max_dipole_am2 (its datasheet): `BoardModel`, what the board sets for each command;
- the residual dipole: [attitude_control] residual_dipole_compensation_am2 (what was calibrated);
- gravity gradient: the orbit of [attitude.orbit] (the flight side's orbit model, as the nadir
  target uses) with the believed inertia;
- gyro noise: the smoother's belief ([estimator.attitude] gyro_noise_density_radps_per_rthz) per
  sample; a mean-rate sample with the smoother (the integrating gyro), an instant one with `truth`.
Its settings are [attitude_control.fdir] (bench.config.controller.FdirConfig).

With `pointing_error_limit_deg` set, the system-level check (bench.gnc.pointing_envelope) runs
beside it: kind "fdir_pointing", no coil named.

Detections become FaultEvents of kind "fdir_<class>" with frame "FDIR" beside the driver's own in
can/driver.json (so metrics.json's can_bus.driver.events and the report's CAN table count them),
and the monitor's whole account, with simulated detection times, is the run's fdir.json.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bench.gnc.actuator_monitor import ActuatorMonitor, FdirEvent, MonitorSettings, OnboardActuatorModel
from bench.gnc.pointing_envelope import PointingEnvelope
from bench.scenario import Scenario

FDIR_REPORT_NAME = "fdir.json"
MONITOR_NAME = "FDIR"


def monitor_settings(scenario: Scenario) -> MonitorSettings:
    c = scenario.attitude_control.fdir
    return MonitorSettings(window_s=c.window_s, min_window_s=min(c.min_window_s, c.window_s),
                           evaluate_every_s=c.evaluate_every_s, gain_tolerance=c.gain_tolerance,
                           offset_tolerance_am2=c.offset_tolerance_am2, threshold=c.threshold,
                           persistence=c.persistence, max_gain_std=c.max_gain_std)


class BoardModel:
    """The dipole the board sets for a command, as the flight side knows its own frames and the
    board's datasheet: the command frame's DBC scaling (1e-4 A m^2), then the DAC step and the limit
    (bench.bus.can.board.coil_driver_dipole). Rounding to the DAC step alone missed the frame's own
    rounding: a full step (1e-3 A m^2) off on 160 of 900 steps of attitude_pointing_pd, whose
    commands are a step or two. Cached per command (the encoder costs ~0.3 ms; a hold repeats)."""

    def __init__(self, scenario: Scenario):
        from bench.bus.can import protocol as p
        from bench.bus.can.config import BoardConfig

        self.board = scenario.can.board if scenario.can is not None else BoardConfig()
        self.protocol = p.Protocol(scenario.can.node_id if scenario.can is not None else 0x10)
        self.axes = p.AXES
        self._cache: dict[bytes, np.ndarray] = {}

    def __call__(self, commanded_am2: np.ndarray) -> np.ndarray:
        from bench.bus.can.board import coil_driver_dipole

        key = np.asarray(commanded_am2, float).tobytes()
        if key not in self._cache:
            if len(self._cache) > 10_000:
                self._cache.clear()
            frame = self.protocol.decode(self.protocol.command(np.asarray(commanded_am2, float), 0))
            requested = np.array([frame.signals[f"Dipole{a}"] for a in self.axes])
            self._cache[key] = coil_driver_dipole(requested, self.board)[0]
        return self._cache[key].copy()


def onboard_actuator_model(scenario: Scenario) -> OnboardActuatorModel:
    from bench.bus.can.config import BoardConfig
    from bench.controller.attitude_laws import believed_inertia, dipole_limit_am2
    from bench.plant.attitude_plant import build_orbit    # the flight side's orbit model

    board = scenario.can.board if scenario.can is not None else BoardConfig()
    orbit = build_orbit(scenario.attitude)
    density = scenario.estimator.attitude.gyro_noise_density_radps_per_rthz
    return OnboardActuatorModel(
        inertia_kgm2=believed_inertia(scenario), step_s=scenario.step_s,
        gyro_noise_std_radps=density / np.sqrt(scenario.step_s),
        rate_sample="instant" if scenario.estimator.mode == "truth" else "mean",
        residual_dipole_am2=np.asarray(scenario.attitude_control.residual_dipole_compensation_am2, float),
        dipole_limit_am2=min(board.max_dipole_am2, dipole_limit_am2(scenario)),
        dipole_resolution_am2=board.dipole_resolution_am2,    # without [can] the plant's board model has it too
        position_m=orbit.position_m, board_model=BoardModel(scenario))


def build_actuator_monitor(scenario: Scenario) -> ActuatorMonitor | None:
    """The monitor for an attitude scenario, or None when [attitude_control.fdir] enabled is false."""
    if scenario.kind != "attitude" or not scenario.attitude_control.fdir.enabled:
        return None
    return ActuatorMonitor(onboard_actuator_model(scenario), monitor_settings(scenario))


def build_pointing_envelope(scenario: Scenario) -> PointingEnvelope | None:
    """The system-level check, or None when the FDIR is off or no pointing limit is set."""
    c = scenario.attitude_control.fdir
    if scenario.kind != "attitude" or not c.enabled or c.pointing_error_limit_deg is None:
        return None
    return PointingEnvelope(float(np.deg2rad(c.pointing_error_limit_deg)), c.pointing_persistence_s)


def fault_event(event: FdirEvent, detected_ns: int):
    """The detection as the driver's FaultEvent (can/driver.json): kind fdir_<class>, frame FDIR,
    the latency the span of evidence it took (the monitor cannot know the onset)."""
    from bench.bus.can.driver import FaultEvent

    return FaultEvent(event.kind, detected_ns, event.window_s, MONITOR_NAME, event.describe())


def write_report(run_dir: Path, monitor: ActuatorMonitor | None, envelope: PointingEnvelope | None = None) -> None:
    if monitor is None:
        return
    summary = monitor.summary() | ({} if envelope is None else {"pointing_envelope": envelope.summary()})
    (Path(run_dir) / FDIR_REPORT_NAME).write_text(json.dumps(summary, indent=1))


def event_arrays(events: list) -> dict[str, np.ndarray]:
    """The detections as columns (the in-process loop's trajectory, a campaign's row)."""
    return {"fdir_event_time_s": np.array([e.time_s for e in events], float),
            "fdir_event_axis": np.array([e.axis_name for e in events], dtype=str),
            "fdir_event_class": np.array([e.fault_class for e in events], dtype=str)}
