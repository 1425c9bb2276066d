"""The FDIR actuator monitor judges only steps the flight-side driver vouches for (BoardHealth.ok).

attitude_fault_all (the built-in with a board power loss, dropped, corrupted and flooded commands
and frozen telemetry; B-dot detumbling) in the in-process loop with its lock-step bus: the coils
are off or their commands refused for seconds at a time, each time for a reason the driver names.
Read as dynamics alone, those seconds look like a weak coil: without the driver's word the monitor
raised `fdir_gain` on this run (its report said so beside the driver's events). With it, none.
"""
import numpy as np

from bench.bus.can.lockstep_loop import LockStepLoopBus
from bench.scenario import load_scenario
from bench.sim import simulate_attitude_in_process


def _fdir_events(scenario):
    trajectory = simulate_attitude_in_process(scenario)
    return list(zip(trajectory["fdir_event_time_s"], trajectory["fdir_event_axis"], trajectory["fdir_event_class"]))


def test_bus_faults_the_driver_names_are_not_read_as_coil_faults(monkeypatch):
    scenario = load_scenario("attitude_fault_all")
    assert _fdir_events(scenario) == []
    # The same run with a driver that always vouches for the board: the monitor is fooled.
    monkeypatch.setattr(LockStepLoopBus, "board_ok", lambda self: True)
    fooled = _fdir_events(scenario)
    assert fooled and {c for _, _, c in fooled} <= {"gain", "open", "stuck", "reversed"}, fooled
    assert np.isfinite([t for t, _, _ in fooled]).all()
