"""The scenario's [can] section: faults validated on load, errors that name the fault and field."""
from __future__ import annotations

import pytest

from bench.bus.can import faults
from bench.bus.can.cli import cmd_faults
from bench.bus.schemas import MtqApplied, decode, encode, header
from bench.scenario import ScenarioError, parse_scenario


def scenario_with(*fault_tables: dict, **can) -> dict:
    return {"name": "can-test", "can": {"faults": list(fault_tables), **can}}


def test_a_scenario_without_can_has_no_can_section():
    assert parse_scenario({"name": "plain"}).can is None


def test_faults_load_with_their_parameters_and_defaults():
    s = parse_scenario(scenario_with({"name": "delay", "start_s": 1.0, "count": 3, "params": {"delay_s": 0.2}},
                                     {"name": "flood", "start_s": 2.0, "duration_s": 0.5}))
    delay, flood = s.can.faults
    assert delay.param("delay_s") == 0.2 and delay.target_frames() == ("MTQ_CMD",)
    assert flood.param("frame_id") == 0x010 and flood.param("period_s") == 0.0


@pytest.mark.parametrize("fault, message", [
    ({"name": "explode"}, "can.faults[0]: unknown fault 'explode'"),
    ({"name": "delay", "params": {"delay_s": 5.0}}, "delay_s = 5.0 is out of range [0.0001, 2.0] s"),
    ({"name": "corrupt", "params": {"bits": 4}}, "bits = 4 is out of range [1, 3]"),
    ({"name": "corrupt", "params": {"recompute_crc": 1}}, "recompute_crc must be true or false"),
    ({"name": "drop", "params": {"probability": 0.5}}, "unknown parameter 'probability'"),
    ({"name": "drop", "frames": ["MTQ_CMND"]}, "unknown frame 'MTQ_CMND'"),
    ({"name": "flood"}, "fault 'flood' acts for a time window: give duration_s"),
    ({"name": "drop", "every": 0}, "can.faults[0].every"),
])
def test_a_bad_fault_is_a_validation_error_naming_it(fault, message):
    with pytest.raises(ScenarioError) as err:
        parse_scenario(scenario_with(fault))
    assert message in str(err.value)


def test_bad_can_fields_are_named():
    with pytest.raises(ScenarioError, match="can.transport"):
        parse_scenario(scenario_with(transport="carrier-pigeon"))
    with pytest.raises(ScenarioError, match="can.bitrate_bps"):
        parse_scenario(scenario_with(bitrate_bps=2_000_000))


def test_scripted_dipole_profile_holds_steps_and_repeats():
    config = parse_scenario(scenario_with(
        dipole_profile=[{"t_s": 0.0, "dipole_am2": [0.1, 0, 0]}, {"t_s": 0.5, "dipole_am2": [0, 0.1, 0]}],
        profile_repeat_s=1.0)).can
    assert config.dipole_at(0.2) == [0.1, 0, 0]
    assert config.dipole_at(0.7) == [0, 0.1, 0]
    assert config.dipole_at(1.2) == [0.1, 0, 0]


def test_every_fault_kind_has_an_injector_and_is_listed(capsys):
    from bench.bus.can.injector import KINDS

    hardware = {name for name, kind in faults.FAULTS.items() if kind.trigger == faults.HARDWARE}
    assert hardware == {"board_power_loss", "coil_open", "coil_stuck", "coil_reversed", "coil_gain"}
    assert set(KINDS) == set(faults.FAULTS) - hardware     # the board's hardware acts on no frame (coils.py)
    assert cmd_faults(None) == 0
    listed = capsys.readouterr().out
    for name in faults.FAULTS:
        assert name in listed


def test_mtq_applied_message_round_trips():
    message = MtqApplied(header=header("r1", 3, 0.0, board_received=1, applied=2), dipole_am2=[0.1, 0.0, -0.1],
                         coil_current_a=[0.05, 0.0, -0.05], safe_state=False, alive_counter=7)
    assert decode(encode(message), MtqApplied) == message


def test_periods_come_from_the_dbc_cycle_times_and_send_types():
    import cantools

    from bench.bus.can import protocol as p
    from bench.bus.can.config import CanConfig
    db = cantools.database.load_file(str(p.DBC_PATH))     # read here with cantools, not through protocol.py
    cycle_ms = {m.name: m.cycle_time for m in db.messages if m.send_type in ("Cyclic", "CyclicAndSpontaneous")}
    assert cycle_ms == {"MTQ_CMD": 20, "MTQ_CMD_AUTH": 20, "MTQ_TLM_DIPOLE": 50, "MTQ_TLM_COIL": 50,
                        "MTQ_HEARTBEAT": 100}
    assert {m.name for m in db.messages if m.send_type == "Spontaneous"} == {"MTQ_EMCY", "NMT", "MTQ_NMT_AUTH",
                                                                        "MTQ_TLM_SETPOINT"}
    # the commands are sent on change and every cycle (AUTOSAR COM's mixed mode): the driver's default
    assert {m.name for m in db.messages if m.send_type == "CyclicAndSpontaneous"} == {"MTQ_CMD", "MTQ_CMD_AUTH"}
    assert p.transmission_mode(p.CMD) == "mixed" and p.transmission_mode(p.TLM_DIPOLE) == "cyclic"
    config = CanConfig()
    assert config.driver.transmission == "mixed"
    assert config.driver.command_period_s == cycle_ms["MTQ_CMD"] / 1000
    assert config.board.telemetry_period_s == cycle_ms["MTQ_TLM_DIPOLE"] / 1000
    assert config.board.heartbeat_period_s == cycle_ms["MTQ_HEARTBEAT"] / 1000
    assert p.cycle_time_s(p.EMCY) is None
