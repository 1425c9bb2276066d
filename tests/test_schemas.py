"""Message schemas: round trip and rejection of malformed payloads."""
import msgspec
import pytest

from bench.bus.schemas import (
    SCHEMA_VERSION, MalformedMessage, RelativePosition, ThrustCommand, TranslationEstimate, decode, encode, header,
)


def thrust(**changes):
    msg = ThrustCommand(header(run_id="r1", seq=7, sim_time_s=4200.0, sensed=11, commanded=22),
                        thrust_n=[0.1, -0.25, 1e-9], ctrl_feasible=True, status="solved", solve_time_s=7e-5)
    return msgspec.structs.replace(msg, **changes)


def test_round_trip_is_exact():
    original = thrust()
    assert decode(encode(original), ThrustCommand) == original
    est = TranslationEstimate(header("r1", 3, 1800.0), [1.0, 2.0, 3.0, 0.1, 0.2, 0.3],
                              covariance=[float(i) for i in range(36)], mean_motion_radps=1.078e-3)
    assert decode(encode(est), TranslationEstimate) == est


def test_floats_survive_bit_for_bit():
    value = 0.1 + 0.2  # 0.30000000000000004: shortest-repr JSON must keep every bit
    msg = thrust(thrust_n=[value, 1 / 3, -2.5e-308])
    assert decode(encode(msg), ThrustCommand).thrust_n == [value, 1 / 3, -2.5e-308]


@pytest.mark.parametrize("payload, problem", [
    (b"\x00\xffgarbage", "malformed"),
    (b"{}", "header"),
    (b'{"type":"thrust","header":{"schema_version":1,"run_id":"r","seq":0,"sim_time_s":0},'
     b'"thrust_n":[1,2],"ctrl_feasible":true,"status":"x","solve_time_s":0}', "length"),
    (b'{"type":"thrust","header":{"schema_version":1,"run_id":"r","seq":-1,"sim_time_s":0},'
     b'"thrust_n":[1,2,3],"ctrl_feasible":true,"status":"x","solve_time_s":0}', "seq"),
    (b'{"type":"thrust","header":{"schema_version":1,"run_id":"r","seq":0,"sim_time_s":"later"},'
     b'"thrust_n":[1,2,3],"ctrl_feasible":true,"status":"x","solve_time_s":0}', "sim_time_s"),
    (b'{"type":"thrust","header":{"schema_version":1,"run_id":"r","seq":0,"sim_time_s":0},'
     b'"thrust_n":[1,2,3],"ctrl_feasible":true,"status":"x","solve_time_s":0,"extra":1}', "extra"),
])
def test_malformed_payloads_are_rejected_with_a_reason(payload, problem):
    with pytest.raises(MalformedMessage, match=problem):
        decode(payload, ThrustCommand)


def test_wrong_message_type_is_rejected():
    relpos = RelativePosition(header("r1", 0, 0.0), [1.0, 2.0, 3.0], 10.0)
    with pytest.raises(MalformedMessage, match="type"):
        decode(encode(relpos), ThrustCommand)


def test_other_schema_version_is_rejected():
    msg = thrust()
    msg.header.schema_version = SCHEMA_VERSION + 1
    with pytest.raises(MalformedMessage, match="schema version"):
        decode(encode(msg), ThrustCommand)
