"""The CAN bus on simulated time (lock-step): the windowed driver (bench/bus/can/windowed_driver.py)
against the bus model and the board (bench/bus/can/lockstep_bus.py), in process, window by window
as the controller and canbus processes trade them. Checked against the in-process loop's board
model and an independent model of the board's command timeout (attitude_comparison.coils_off_window)."""
import msgspec
import numpy as np
import pytest

from bench.bus.can.faults import FaultSpec
from bench.bus.can.lockstep_bus import LockStepBus
from bench.bus.can.run_key import can_with_key
from bench.bus.can.sim_window import bus_on_simulated_time, mission_s, sim_ns
from bench.bus.can.windowed_driver import BOOT_WINDOWS, WindowedDriver
from bench.plant.mtq_acceptance import board_dipole_without_bus
from bench.scenario import load_scenario
from bench.studies.attitude_comparison import coils_off_window

BENIGN = {"heartbeat_resumed", "board_error_reset", "error_active"}


def can_config(*faults, transmission="mixed", scenario="attitude_quick"):
    config = load_scenario(scenario).can
    config = msgspec.structs.replace(config, faults=list(faults),
                                     driver=msgspec.structs.replace(config.driver, transmission=transmission))
    return can_with_key(config, "2b7e151628aed2a6abf7158809cf4f3c")


class Loop:
    """The two processes' halves in one: each step, the driver's window through the bus."""

    def __init__(self, config, step_s=1.0):
        self.step_s = step_s
        self.driver = WindowedDriver(config)
        self.bus = LockStepBus(config, seed=1)
        self.events = []
        for _, start_ns, end_ns in BOOT_WINDOWS:
            self._window(start_ns, end_ns, None)

    def _window(self, start_ns, end_ns, dipole):
        frames, counter, _ = self.driver.window(start_ns, end_ns, dipole)
        heard, coils = self.bus.advance(start_ns, end_ns, frames)
        self.events += self.driver.heard(heard)
        return frames, counter, coils

    def step(self, k, dipole):
        return self._window(sim_ns(k * self.step_s), sim_ns((k + 1) * self.step_s), dipole)

    def faults(self):
        return [e for e in self.events if e.kind not in BENIGN]


# On change alone, nothing keeps the board alive between steps: the law must be faster than the
# board's 0.1 s command timeout (DriverConfig.transmission).
@pytest.mark.parametrize("transmission, step_s", [("mixed", 1.0), ("cyclic", 1.0), ("on_change", 0.05)])
def test_a_fault_free_bus_gives_each_step_exactly_the_board_models_dipole(transmission, step_s):
    """What the in-process loop applies (board_dipole_without_bus: the DBC's scaling, the coil
    drivers' quantisation and saturation) is what the step's coils average to, for every
    transmission mode; the board is started by the driver's NMT before step 0 and no fault is
    detected."""
    config = can_config(transmission=transmission)
    loop = Loop(config, step_s)
    rng = np.random.default_rng(5)
    period_s = config.driver.command_period_s
    for k in range(12):
        dipole = rng.uniform(-0.3, 0.3, 3)
        frames, counter, coils = loop.step(k, dipole)
        expected = board_dipole_without_bus(dipole, config)
        assert np.array_equal(coils.dipole_am2, expected), (k, coils.dipole_am2, expected)
        # Off only before step 0's first command reached the board (the bus latency, < 1 ms).
        assert (coils.off_fraction * step_s < 1e-3 if k == 0 else coils.off_fraction == 0.0) and not coils.safe_state
        assert coils.applied_counter == counter
        commands = [f for f in frames if f.arbitration_id == loop.bus._command_id]
        assert len(commands) == (1 if transmission == "on_change" else round(step_s / period_s))
    assert loop.faults() == []
    assert loop.driver.driver.health().ok


def test_dropped_commands_switch_the_coils_off_after_the_boards_timeout_on_simulated_time():
    """Against an independent model of the board (coils off from its command timeout after the
    first lost frame until commands return): each step's average, the time the driver hears of
    it, and the same answer every time (no host in it)."""
    scenario = load_scenario("attitude_quick")
    fault = FaultSpec(name="drop", frames=["MTQ_CMD"], start_s=4.3, duration_s=2.25)
    window = coils_off_window(fault, scenario)
    period_s = scenario.can.driver.command_period_s
    command = np.array([0.05, -0.02, 0.1])
    runs = []
    for _ in range(2):
        loop = Loop(can_config(fault))
        averages = [loop.step(k, command)[2].dipole_am2 for k in range(10)]
        runs.append((np.array(averages), [(e.kind, e.detected_ns) for e in loop.events]))
        for k, average in enumerate(averages):
            off_s = max(0.0, min(k + 1.0, window.on_s) - max(float(k), window.off_s))
            # The model counts the timeout from the first lost frame, the board from the last one
            # it got (a period earlier), plus the bus latency (~0.2 ms): within 1.5 periods.
            assert np.allclose(average, command * (1.0 - off_s), atol=np.abs(command).max() * 1.5 * period_s), (k, average)
        timeouts = [e for e in loop.faults() if e.kind == "board_command_timeout"]
        assert len(timeouts) == 1
        detected_s = mission_s(timeouts[0].detected_ns)
        # The last frame before the drop went at the period before start_s; the board's timeout
        # runs from it; its EMCY takes one frame time on the bus.
        assert window.off_s - period_s <= detected_s <= window.off_s + 1e-3
    assert np.array_equal(runs[0][0], runs[1][0]) and runs[0][1] == runs[1][1]


def test_corrupted_commands_are_rejected_and_reported_at_their_simulated_times():
    fault = FaultSpec(name="corrupt", frames=["MTQ_CMD"], start_s=2.0, count=5)
    loop = Loop(can_config(fault))
    command = np.array([0.1, 0.0, -0.1])
    for k in range(4):
        loop.step(k, command)
    # The corrupted frames fail the MAC (checked first); the E2E receiver then sees the counter
    # jump over them and rejects the next frames as out of sequence until it resynchronises.
    rejected = [e for e in loop.faults() if e.kind == "command_rejected" and "WRONG_MAC" in e.detail]
    assert len(rejected) == 5
    times = [mission_s(e.detected_ns) for e in rejected]
    # One per corrupted frame, each within a millisecond of the frame's slot (10 ms apart).
    for i, t in enumerate(times):
        assert 2.0 + i * 0.01 <= t <= 2.0 + i * 0.01 + 1e-3, times


def test_a_step_back_in_time_is_refused():
    loop = Loop(can_config())
    loop.step(0, [0.1, 0.0, 0.0])
    with pytest.raises(ValueError, match="not after the bus's time"):
        loop.bus.advance(sim_ns(0.5), sim_ns(1.5), [])


def test_the_bus_is_on_simulated_time_in_lock_step_with_faults_or_when_asked():
    quick = load_scenario("attitude_quick")
    assert not bus_on_simulated_time(quick)              # fault-free "auto": paired on the wall clock
    asked = msgspec.structs.replace(quick, can=msgspec.structs.replace(quick.can, lock_step_clock="simulated"))
    assert bus_on_simulated_time(asked)
    faulted = load_scenario("attitude_fault_commands")
    assert not bus_on_simulated_time(faulted)             # real time
    lock_step = msgspec.structs.replace(faulted, run=msgspec.structs.replace(faulted.run, mode="lock-step"))
    assert bus_on_simulated_time(lock_step)
