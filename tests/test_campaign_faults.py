"""Fault-injection campaigns for the attitude loop (bench/studies/fault_campaign.py, fault_bus.py,
fault_report.py): the co-simulated bus against an independent model of the board's command
timeout, the campaign's rows on both engines, the failure-modes matrix."""
import math

import msgspec
import numpy as np
import pytest

from bench.bus.can.faults import FaultSpec
from bench.scenario import load_scenario
from bench.studies.attitude_comparison import coils_off_window
from bench.studies.campaign import CampaignError, load_spec
from bench.studies.fault_bus import BusCoSimulation
from bench.studies.fault_campaign import effect_metrics, parse_spec
from test_campaign import local_and_ray_rows, tests_on_path  # noqa: F401 - the fixture


def tiny(spec, laws=None, faults=None, steps=20, start_s=5.0, duration_s=2.0):
    """The spec cut to `steps` steps per mission, one seed, its faults (all or the named) moved to
    start_s for duration_s (count-limited ones keep their count)."""
    chosen = {name: msgspec.structs.replace(f, start_s=start_s, duration_s=duration_s if f.duration_s else None)
              for name, f in spec.faults.items() if faults is None or name in faults}
    laws_kept = {name: law for name, law in spec.laws.items() if laws is None or name in laws}
    return msgspec.structs.replace(spec, seeds=1, steps=steps, onset_jitter_s=0.0, faults=chosen, laws=laws_kept)


def test_dropped_commands_switch_the_real_board_off_after_its_command_timeout():
    """The co-simulated board (the real MagnetorquerBoard behind the real bus model) against an
    independent model of what it must do: coils off from the command timeout after the first lost
    frame until commands come back (attitude_comparison.CoilsOffWindow)."""
    scenario = load_scenario("attitude_quick")
    fault = FaultSpec(name="drop", frames=["MTQ_CMD"], start_s=10.0, duration_s=3.5)
    hook = BusCoSimulation(scenario.can, [fault], step_s=1.0, seed=3)
    window = coils_off_window(fault, scenario)
    command = np.array([0.05, -0.02, 0.1])
    period_s = scenario.can.driver.command_period_s
    for k in range(20):
        out = hook(float(k), command)
        off_s = max(0.0, min(k + 1.0, window.on_s) - max(float(k), window.off_s))
        expected = command * (1.0 - off_s)
        # The board acts on its own tick and the first command after the window: a period's slack.
        assert np.allclose(out, expected, atol=np.abs(command).max() * 1.5 * period_s), (k, out, expected)
    assert hook.coils_off_s() == pytest.approx(window.on_s - window.off_s, abs=1.5 * period_s)
    detection = hook.first_detection()
    assert detection.kind == "board_command_timeout"
    # The board's EMCY after its 0.1 s timeout, on the bus to the driver: at most a period more.
    assert scenario.can.board.command_timeout_s <= detection.time_s - fault.start_s + period_s
    assert detection.time_s - fault.start_s <= scenario.can.board.command_timeout_s + 2 * period_s
    assert hook.false_alarms() == 0


def test_a_fault_the_board_rejects_leaves_the_coils_alone_and_is_detected():
    scenario = load_scenario("attitude_quick")
    hook = BusCoSimulation(scenario.can, [FaultSpec(name="spoof", start_s=3.0, duration_s=2.0)], step_s=1.0)
    command = np.array([0.05, -0.02, 0.1])
    outs = [hook(float(k), command) for k in range(8)]
    assert all(np.allclose(o, command, atol=1e-3) for o in outs)     # only the first 0.3 ms of a step differs
    assert hook.first_detection().kind == "spoofed_command"
    # Off only until the first command reaches the freshly booted board at the window's start.
    assert hook.coils_off_s() < 1e-3


def test_effect_metrics_against_hand_worked_series():
    t = np.arange(10.0)
    clean = np.zeros(10)
    faulted = np.array([0, 0, 0, 0.5, 1.0, 0.3, 0.05, 0, 0, 0])
    m = effect_metrics(t, faulted, clean, tolerance=0.1, onset_s=3.0, end_s=4.0)
    assert m["max_deviation"] == 1.0 and m["deviated"] and m["time_to_recover_s"] == 2.0   # back at 6 s
    m = effect_metrics(t, np.r_[faulted[:-1], 0.2], clean, tolerance=0.1, onset_s=3.0, end_s=4.0)
    assert math.isnan(m["time_to_recover_s"])                          # not back by the end
    assert effect_metrics(t, clean, clean, 0.1, 3.0, 4.0)["time_to_recover_s"] == 0.0
    # A fault that outlasts the mission (a coil that does not heal): back 3 s after its onset.
    assert effect_metrics(t, faulted, clean, tolerance=0.1, onset_s=3.0, end_s=3000.0)["time_to_recover_s"] == 3.0


def test_spec_errors_name_the_field():
    base = {"name": "x", "kind": "attitude_faults", "missions": {"m": {"base_scenario": "attitude_quick"}},
            "laws": {"l": {"mission": "nope"}}, "faults": {"f": {"name": "drop", "duration_s": 1.0}}}
    with pytest.raises(CampaignError, match="laws.l.mission"):
        parse_spec(base)
    with pytest.raises(CampaignError, match="faults.f: give duration_s or count"):
        parse_spec({**base, "laws": {"l": {"mission": "m"}}, "faults": {"f": {"name": "drop"}}})
    with pytest.raises(CampaignError, match="unknown fault"):
        parse_spec({**base, "laws": {"l": {"mission": "m"}}, "faults": {"f": {"name": "melt", "duration_s": 1.0}}})


def test_local_and_ray_engines_give_identical_fault_rows(tmp_path, tests_on_path):  # noqa: F811
    spec = tiny(load_spec("attitude_faults"), laws=["bdot_rate_damping", "pd"], faults=["drop", "board_power_loss"],
                steps=12, start_s=3.0, duration_s=2.0)
    rows = local_and_ray_rows(spec, tmp_path, cases=4)
    drop = next(r for r in rows if r["fault"] == "drop" and r["mission"] == "detumble")
    assert drop["detected"] and drop["first_detection"] == "board_command_timeout" and drop["coils_off_s"] > 1.5
    assert drop["detected_by"] == "board"          # its command timeout, reported by EMCY
    power = next(r for r in rows if r["fault"] == "board_power_loss" and r["mission"] == "detumble")
    assert power["detected_by"] == "driver" and power["first_detection"] == "error_warning"   # commands unacknowledged
    assert power["coils_off_in_fault_s"] == pytest.approx(power["fault_duration_s"], abs=1e-6)
    assert power["board_operational_after"] and 0.0 < power["board_recovery_ms"] < 150.0


def test_hardware_faults_act_on_the_co_simulated_coils():
    """The campaign's bus co-simulation with the board's hardware: an open x coil gives no x dipole
    and its telemetry says so (actuator_mismatch); a board without power has its coils off for the
    whole window, boots after it and is operational again at the driver's NMT start."""
    scenario = load_scenario("attitude_quick")
    command = np.array([0.05, -0.02, 0.1])
    hook = BusCoSimulation(scenario.can, [FaultSpec(name="coil_open", start_s=3.0, duration_s=3.0,
                                                    params={"axis": 0})], step_s=1.0, seed=2)
    outs = [hook(float(k), command) for k in range(9)]
    assert all(np.array_equal(o, [0.0, -0.02, 0.1]) for o in outs[3:5])
    assert np.allclose(outs[7], command, atol=1e-3) and outs[1][0] == pytest.approx(0.05, abs=1e-3)
    detection = hook.first_detection()
    assert detection.kind == "actuator_mismatch" and "axis x" in detection.detail and detection.time_s < 3.5
    hook = BusCoSimulation(scenario.can, [FaultSpec(name="board_power_loss", start_s=3.0, duration_s=2.0)],
                           step_s=1.0, seed=2)
    outs = [hook(float(k), command) for k in range(8)]
    assert np.array_equal(outs[3], np.zeros(3)) and np.array_equal(outs[4], np.zeros(3))
    assert hook.coils_off_in_fault_ns == 2_000_000_000
    events = [event for event, _ in hook.power_log()]
    assert events == ["power_lost", "booted", "operational"]
    assert np.allclose(outs[6], command, atol=1e-3)


def test_the_matrix_names_the_monitor_and_never_greens_an_undetected_fault():
    from bench.studies.fault_report import matrix_markdown

    def row(i, fault, detected, by="", first="", effect="none"):
        return {"case_index": i, "fault": fault, "law": "PD", "mission": "hold", "status": "ok", "effect": effect,
                "fault_kind": fault, "detected": detected, "detection_latency_s": 0.1 if detected else float("nan"),
                "time_to_recover_s": float("nan"), "first_detection": first, "detected_by": by,
                "monitors": by, "max_deviation": 0.0, "coils_off_in_fault_s": 0.0, "fault_duration_s": 10.0,
                "board_recovery_ms": float("nan"), "board_operational_after": True}

    table = matrix_markdown([row(0, "coil_open", True, "driver", "actuator_mismatch"),
                             row(1, "coil_reversed", True, "FDIR", "fdir_reversed", "degraded"),
                             row(2, "telemetry_freeze", False)])
    lines = {line.split(" | ")[0].strip("| "): line for line in table.splitlines()}
    assert "🟩" in lines["coil_open"] and "by **driver** (actuator_mismatch)" in lines["coil_open"]
    assert "by **FDIR** (fdir_reversed)" in lines["coil_reversed"]
    assert "🟪" in lines["telemetry_freeze"] and "🟩" not in lines["telemetry_freeze"]
    assert "**undetected**" in lines["telemetry_freeze"]
