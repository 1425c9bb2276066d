"""The time model (docs/time-model.md) chosen once per run: the plant's step clock, the attitude
plant's source of the applied dipole, and what the other nodes ask of bench.runtime.time_model."""
from __future__ import annotations

import queue
from types import SimpleNamespace

import msgspec
import pytest

from bench.bus.schemas import AttitudeEstimate, header
from bench.controller.newest import NewestEstimate
from bench.plant.acceptance import ActuatorEnvelope, CommandGate
from bench.plant.board_dipole import (
    AppliedLog, BoardReports, HeldReport, ReportOfCommand, ReportOfStep, board_dipole_source,
)
from bench.plant.mtq_acceptance import DipoleAcceptance
from bench.plant.stepping import LockStepClock, RealTimeClock, step_clock
from bench.runtime.time_model import LOCK_STEP_PROMISED_WAIT_S, TimeModel
from bench.scenario import load_scenario


def with_run(scenario, **run):
    return msgspec.structs.replace(scenario, run=msgspec.structs.replace(scenario.run, **run))


def test_lock_step_takes_every_message_waits_for_promised_ones_and_has_no_deadline():
    lock_step, real_time = TimeModel(lock_step=True), TimeModel(lock_step=False)
    assert lock_step.takes_every_message and not lock_step.deadlines_apply
    assert not real_time.takes_every_message and real_time.deadlines_apply
    assert lock_step.promised_wait_s(0.005) == LOCK_STEP_PROMISED_WAIT_S
    assert real_time.promised_wait_s(0.005) == 0.005
    scenario = load_scenario("rendezvous_lqr")
    assert TimeModel.of(with_run(scenario, mode="lock-step")).lock_step
    assert not TimeModel.of(with_run(scenario, mode="real-time")).lock_step


def estimate(seq: int) -> AttitudeEstimate:
    return AttitudeEstimate(header("t", seq, float(seq)), True, [1.0, 0.0, 0.0, 0.0], [0.0] * 3, [0.0] * 3, [0.0] * 3)


@pytest.mark.parametrize("lock_step", [True, False])
def test_the_controller_acts_on_every_estimate_in_lock_step_and_on_the_newest_in_real_time(lock_step):
    queued: queue.Queue = queue.Queue()
    for seq in (4, 5, 6):
        queued.put(estimate(seq))
    newest = NewestEstimate(TimeModel(lock_step=lock_step))
    taken = newest.take(queued, estimate(3))
    assert taken.header.seq == (3 if lock_step else 6)
    assert newest.skipped == (0 if lock_step else 3)
    assert queued.qsize() == (3 if lock_step else 0)


def test_the_plant_clock_follows_the_run_mode_and_its_step():
    scenario = load_scenario("rendezvous_lqr")
    lock_step = step_clock(with_run(scenario, mode="lock-step", command_timeout_s=7.0))
    assert isinstance(lock_step, LockStepClock) and lock_step.command_timeout_s == 7.0
    assert lock_step.late_commands == 0 and lock_step.missed_steps == 0
    real_time = step_clock(with_run(scenario, mode="real-time", time_factor=100.0))
    assert isinstance(real_time, RealTimeClock)
    assert real_time.period_s == pytest.approx(scenario.plant.time_step_s / 100.0)
    attitude = load_scenario("attitude_pointing_rt")
    assert step_clock(attitude).period_s == pytest.approx(attitude.step_s / attitude.run.time_factor)


@pytest.mark.parametrize("name, mode, lock_step_clock, source", [
    ("attitude_fault_commands", "lock-step", "simulated", ReportOfStep),
    ("attitude_quick", "lock-step", "wall", ReportOfCommand),
    ("attitude_pointing_rt", "real-time", "auto", HeldReport),
])
def test_the_attitude_plant_takes_its_dipole_from_the_time_models_source(name, mode, lock_step_clock, source):
    scenario = load_scenario(name)
    scenario = with_run(scenario, mode=mode)
    scenario = msgspec.structs.replace(scenario, can=msgspec.structs.replace(scenario.can, lock_step_clock=lock_step_clock))
    ctx = SimpleNamespace(scenario=scenario, run_id="t", time_model=TimeModel.of(scenario))
    acceptance = DipoleAcceptance(scenario.can)
    gate = CommandGate(ActuatorEnvelope("dipole", "A m^2", acceptance.envelope_am2))
    chosen = board_dipole_source(ctx, gate, acceptance, BoardReports(), AppliedLog(scenario.n_steps))
    assert type(chosen) is source
