"""The live view's own Foxglove topics and the JSON schemas of what it sends on them (the figures
derived from the run, the criteria, its status) and of its fault-injection service's request and
reply (bench/live/node.py).
"""
from __future__ import annotations

import json

TF_TOPIC, EVENTS_TOPIC, CRITERIA_TOPIC, STATUS_TOPIC = "/tf", "/events", "live/criteria", "live/status"
ERROR_TOPIC, ESTIMATE_ERROR_TOPIC = "live/attitude_error", "live/estimate_error"

_NUM = {"type": "number"}
_NUM_OR_NULL = {"type": ["number", "null"]}
_VEC = {"type": "array", "items": _NUM, "minItems": 3, "maxItems": 3}
ERROR_SCHEMA = {
    "title": "bench.LiveAttitudeError", "type": "object",
    "description": "From truth/attitude at each step: pointing error to the flight side's target and body rate",
    "properties": {"sim_time_s": _NUM, "pointing_error_deg": {**_NUM_OR_NULL, "description": "null for laws without "
                                                                             "a target (B-dot, rate damping)"},
                   "rate_dps": {**_NUM, "description": "|omega| [deg/s]"},
                   "rate_dps_xyz": {**_VEC, "description": "omega per body axis [deg/s]"}},
}
ESTIMATE_ERROR_SCHEMA = {
    "title": "bench.LiveEstimateError", "type": "object",
    "description": "estimate/attitude against truth/attitude of the same step",
    "properties": {"sim_time_s": _NUM, "attitude_error_deg": _NUM,
                   "rate_error_dps_xyz": {**_VEC, "description": "estimated minus true body rate [deg/s]"},
                   "estimated_rate_dps": _NUM, "valid": {"type": "boolean"}},
}
CRITERIA_SCHEMA = {
    "title": "bench.LiveCriteria", "type": "object",
    "description": "The scenario's criteria as they stand (bench/live/criteria.py): a figure computed live, or "
                   "judged at the end",
    "properties": {
        "sim_time_s": _NUM,
        "holds_now": {"type": ["boolean", "null"], "description": "every live criterion holds now (null: none is live)"},
        "criteria": {"type": "array", "items": {"type": "object", "properties": {
            "metric": {"type": "string"}, "bound": {"type": "string"}, "why": {"type": "string"},
            "value": {}, "state": {"type": "string", "enum": ["holds now", "does not hold now", "judged at the end"]},
            "live": {"type": "boolean"}, "passed": {"type": "boolean"}}}},
    },
}
STATUS_SCHEMA = {
    "title": "bench.LiveStatus", "type": "object",
    "description": "What the live view did: forwarded, dropped (its queue full), refused (no valid tag), malformed",
    "properties": {"sim_time_s": _NUM, "forwarded": {"type": "object"}, "dropped": {"type": "object"},
                   "unauthentic": {"type": "object"}, "malformed": {"type": "object"}, "watched": {"type": "object"},
                   "zenoh_subscriptions": {"type": "array", "items": {"type": "string"}},
                   "faults_allowed": {"type": "boolean"}, "service_calls": {"type": "object"}},
}
REQUEST_SCHEMA = {
    "title": "bench.InjectFaultRequest", "type": "object",
    "description": "A fault to inject now, as a [[can.faults]] entry (`bench faults` lists the kinds), with the run's "
                   "token the terminal printed",
    "properties": {
        "token": {"type": "string", "description": "printed by `bench run --live --allow-live-faults`"},
        "kind": {"type": "string", "description": "a [[can.faults]] name, e.g. drop, corrupt, coil_gain"},
        "duration_s": {**_NUM, "description": "simulated seconds (window faults and board_power_loss need it)"},
        "after_s": {**_NUM, "description": "simulated seconds from now to its start (default 0)"},
        "axis": {"type": "string", "enum": ["x", "y", "z"], "description": "coil faults: the body axis"},
        "frames": {"type": "array", "items": {"type": "string"}, "description": "DBC frame names (frame faults)"},
        "count": {"type": "integer"}, "every": {"type": "integer"},
        "params": {"type": "object", "description": "the kind's own parameters (`bench faults`)"},
    },
    "required": ["token", "kind"],
}
REPLY_SCHEMA = {
    "title": "bench.InjectFaultReply", "type": "object",
    "properties": {"accepted": {"type": "boolean"}, "reason": {"type": "string"}, "detail": {"type": "string"},
                   "label": {"type": "string"}, "start_sim_s": _NUM_OR_NULL, "end_sim_s": _NUM_OR_NULL,
                   "authentic": {"type": "boolean", "description": "the answer is signed by canbus under the run's key"}},
}


def json_schema(name: str, schema: dict):
    import foxglove

    return foxglove.Schema(name=name, encoding="jsonschema", data=json.dumps(schema).encode())
