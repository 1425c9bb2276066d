"""contract.json: every number and meaning an outside node needs, as data, from one Scenario.

`bench contract export DIR` writes it with the code's defaults (DIR/contract.json); the launcher
writes one per run beside scenario.json (runs/<id>/contract.json) with that run's numbers: its hub
endpoint, run id, lease, step period, timeouts, envelopes and navigation frame. Both come from
`contract_document`, which reads each number from the code that applies it (the plant's output
stage, the board's configuration, the session factory, the tag and presence modules), so neither
can drift from the bench. It holds no secret: the run's key stays in bus.key (mode 0600).
"""
from __future__ import annotations

import json
from pathlib import Path

import msgspec
import msgspec.inspect

from bench.bus import data_auth, keys, presence
from bench.bus.can.config import BoardConfig, DriverConfig
from bench.bus.schemas import SCHEMA_VERSION, STAGES
from bench.bus.session import KEEP_ALIVE_PER_LEASE, loopback_endpoint, plain_settings
from bench.contract import fields
from bench.contract.table import TOKENS, TOPICS
from bench.plant.acceptance import ENVELOPE_REL_TOL, REASONS
from bench.scenario import Scenario

CONTRACT_FILE = "contract.json"
CONTRACT_VERSION = 1
# `bench contract check`: how long an outside node has to stop once the launcher has left, and the
# inputs it forges (bench/contract_check/check.py STOP_GRACE_S, probe.py; tests/test_contract_export.py
# holds these to them).
CHECK_STOP_GRACE_S = 5.0
CHECK_FORGED_ESTIMATES = 3
CHECK_REPLAYED_ESTIMATES = 2
HUB_PLACEHOLDER = "<the hub endpoint `bench run` prints, e.g. tcp/127.0.0.1:7447>"

REFUSAL_MEANINGS = {
    "wrong_size": "not three numbers",
    "non_finite": "a NaN or an infinity",
    "stale": "header.seq below the step being integrated (late, or a replay)",
    "future": "header.seq above the step being integrated (no such sample yet)",
    "too_old": "older than the output stage's max age (real time, where one applies; not the thrusters)",
    "out_of_envelope": "some |component| above the actuator's limit",
}


def contract_document(scenario: Scenario, run_id: str | None = None, hub: str | None = None) -> dict:
    """The contract for `scenario` (the defaults: `Scenario(name="defaults")`); run_id and hub are
    a run's (placeholders without them)."""
    run, live = scenario.run, scenario.run.liveliness
    rid = run_id or "<run_id>"
    lease_ms = int(round(live.lease_s * 1000))
    return {
        "contract_version": CONTRACT_VERSION,
        "schema_version": SCHEMA_VERSION,
        "written_for": {
            "run_id": run_id, "scenario": scenario.name, "kind": scenario.kind, "mode": run.mode,
            "external": list(run.external),
            "numbers": ("this run's" if run_id else "the code's defaults; a run's own numbers are in "
                        "runs/<run_id>/contract.json, beside scenario.json"),
        },
        "start": _start(rid, hub),
        "zenoh": _zenoh(hub, lease_ms),
        "keys": {"prefix": keys.key(rid, ""), "topics": [{**t.to_json(), "key": keys.key(rid, t.topic)} for t in TOPICS],
                 "control_plane": [{"key": keys.key(rid, k), "meaning": v} for k, v in TOKENS.items()]},
        "signing": _signing(),
        "presence": _presence(rid, live.lease_s),
        "readiness": _readiness(),
        "timing": _timing(scenario),
        "envelopes": _envelopes(scenario),
        "frames": _frames(scenario),
        "rendezvous_model": _rendezvous_model(scenario),
        "messages": _messages(),
        "check": _check(),
    }


def write_contract(path: Path, scenario: Scenario, run_id: str | None = None, hub: str | None = None) -> Path:
    path = Path(path)
    path.write_text(json.dumps(contract_document(scenario, run_id, hub), indent=2) + "\n")
    return path


def _start(run_id: str, hub: str | None) -> dict:
    return {
        "run": f"bench run SCENARIO --external controller --run-id {run_id} --port PORT",
        "then": ("start your node with the hub endpoint the launcher prints (zenoh.connect), the run id, and the run "
                 "directory runs/<run_id>/: scenario.json (the scenario), contract.json (this document, that run's "
                 "numbers) and bus.key (the run's key, mode 0600: run as the user who started the run); the "
                 "launcher writes all three before it starts any node"),
        "check": "bench contract check controller|estimator --command \"YOUR COMMAND --connect {connect} "
                 "--run-id {run_id} --scenario {scenario}\"",
        "name": "join under the part's name: controller or estimator (the role's row in keys.topics)",
    }


def _zenoh(hub: str | None, lease_ms: int) -> dict:
    listen = [loopback_endpoint(0)]
    connect = [hub or HUB_PLACEHOLDER]
    settings = {k: json.loads(v) for k, v in plain_settings("peer", listen, connect, lease_ms).items()}
    return {
        "settings": settings,
        "connect": connect[0],
        "lease_ms": lease_ms,
        "keep_alive_per_lease": KEEP_ALIVE_PER_LEASE,
        "how": ("build the session from these settings (Zenoh config key -> JSON value, e.g. "
                "config.insert_json5(key, json.dumps(value))), never from Zenoh's default configuration, which "
                "scouts by UDP multicast on your network: peer mode, multicast scouting off, gossip on (the run's "
                "other peers are found through the hub), the hub as the only connect endpoint, one ephemeral "
                "loopback listen endpoint, the lease from [run.liveliness] lease_s with keep_alive messages per "
                "lease, no shared memory, no admin space"),
        "secure_runs": ("a --secure run or a deployment speaks mutual TLS only (tls/ endpoints, the node's "
                        "certificate from the run's certificate directory) and enforces the access-control table"),
    }


def _signing() -> dict:
    return {
        "where": "every sample's Zenoh attachment (the payload stays the JSON of the schemas); presence answers too",
        "layout": ["version: 1 byte", "sender length n: 1 byte", "sender: n bytes, ASCII, your node's name",
                   f"counter: {data_auth.COUNTER_BYTES} bytes, big endian",
                   f"mac: {data_auth.MAC_BYTES} bytes, HMAC-SHA256"],
        "version": data_auth.VERSION,
        "max_sender_bytes": data_auth.MAX_SENDER_BYTES,
        "counter_bytes": data_auth.COUNTER_BYTES,
        "mac_bytes": data_auth.MAC_BYTES,
        "mac": "HMAC-SHA256(key, key_expr as UTF-8 | 0x00 | version | n | sender | counter | payload)",
        "counter": ("starts at the wall clock in ns (so a restarted node goes on upwards) and goes up by one with "
                    "every message the node publishes"),
        "key": {"file": data_auth.KEY_FILE, "bytes": data_auth.KEY_BYTES,
                "format": f"{2 * data_auth.KEY_BYTES} hexadecimal digits and a newline, mode 0600, in the run "
                          "directory beside scenario.json",
                "deployment": ("with certificates (--secure, deployments): HMAC-SHA256 with the deployment's "
                               f"secoc.key (16 bytes) as the key, over the ASCII text "
                               f"\"{data_auth.DEPLOYMENT_LABEL.decode()}\"; the launcher writes it to bus.key too")},
        "receiving": ("take a sample only if its attachment is exactly 2 + n + 8 + 32 bytes of version 1 whose MAC "
                      "checks out over the sample's own key expression (hmac.compare_digest), and from each sender "
                      f"on each key only a counter above the last one taken; the bench drops and counts the others "
                      f"as \"{data_auth.FORGED}\" and \"{data_auth.REPLAYED}\""),
    }


def _presence(run_id: str, lease_s: float) -> dict:
    return {
        "query_key": keys.key(run_id, f"{presence.PRESENCE}/*"),
        "answer_key": keys.key(run_id, f"{presence.PRESENCE}/<your name>"),
        "query_payload": f"a nonce: {presence.NONCE_HEX} hexadecimal digits, fresh per query",
        "answer_payload": {"process": "<your name>", "host": "<your host>", "ready": "true|false",
                           "monotonic_ns": "<your CLOCK_MONOTONIC in ns>", "nonce": "<the query's nonce>"},
        "answer": ("declare a queryable on answer_key from the moment your session is up and reply on answer_key "
                   "with that JSON payload and the tag of a message over answer_key and the payload (sender = "
                   "your name); ignore a query whose payload is not a 32-digit nonce"),
        "counts_only_if": "a valid tag whose sender, the key's last chunk and `process` are one name, and the query's "
                          "nonce",
        "asked_every_s": lease_s / 4,
        "silent_after_s": lease_s,
        "launcher": (f"the launcher answers on {keys.key(run_id, presence.PRESENCE + '/launcher')}; stop when it no "
                     f"longer does (its liveliness token {keys.key(run_id, keys.ALIVE + '/launcher')} goes at the "
                     "same moment: a hint to ask at once, never a proof)"),
        "liveliness_tokens": "prove nothing (anyone on the bus can declare one): neither the launcher nor the plant "
                             "takes them as a sign of life",
    }


def _readiness() -> dict:
    return {
        "ready": ("answer \"ready\": true once each topic you publish into the loop has a matching subscriber "
                  "(the Zenoh publisher's matching status); declare your own subscribers before that"),
        "matching": ("a matching subscriber is any subscriber on the key: the recorder subscribes to "
                     "bench/<run_id>/** and so matches every publisher as soon as it is up. Matching proves only "
                     "that the recorder (or the reader) is there, which is what the bench's own nodes also judge "
                     "by: the plant declares its command subscriber before it asks its peers, and publishes step 0 "
                     "only after every peer, you included, has answered ready"),
        "plant_waits": "for a ready answer from every peer before it publishes step 0, up to startup_timeout_s",
        "launcher_waits": "for an authentic answer (ready or not) from every node, up to startup_timeout_s",
    }


def _timing(scenario: Scenario) -> dict:
    run, live, deadline = scenario.run, scenario.run.liveliness, scenario.controller.deadline
    step_s = scenario.step_s
    return {
        "mode": run.mode,
        "time_step_s": step_s,
        "time_factor": run.time_factor,
        "real_time_period_s": step_s / run.time_factor,
        "command_timeout_s": run.command_timeout_s,
        "controller_deadline": {"budget_s": deadline.budget_s, "fallback": deadline.fallback,
                                "hard_limit_s": deadline.hard_limit_s},
        "liveliness": {"lease_s": live.lease_s, "startup_timeout_s": live.startup_timeout_s,
                       "stopped_grace_s": live.stopped_grace_s, "hang_timeout_s": live.hang_timeout_s},
        "lock_step": ("sample k releases estimate k, estimate k releases command k, command k releases step k + 1; "
                      "the plant waits up to command_timeout_s for an acceptable command with header.seq = k. "
                      "Refused commands do not end the wait; if only refused ones came by then, it applies its "
                      "on_reject policy and goes on; if none came, the loop is broken (the plant exits 1, the run "
                      "fails)"),
        "real_time": ("the plant publishes sample k at t0 + k real_time_period_s on its monotonic clock and never "
                      "waits: the command for step k must arrive before step k + 1's tick, else step k is "
                      "integrated on the last accepted command (zero-order hold) and counted as a missed step; a "
                      "command for a step already integrated is counted as late and not applied (refused as stale)"),
        "realtime_priority": run.realtime_priority,
        "realtime_scheduling": (f"in real time the bench's plant, estimator and controller run at SCHED_FIFO "
                                f"{run.realtime_priority} (run.realtime_priority; 0: the default scheduler), every "
                                "thread of them, set before their Zenoh session opens so its threads inherit it. An "
                                "outside node of the loop should do the same (it needs CAP_SYS_NICE): at the default "
                                "scheduler a busy host holds it up behind the bench's own processes, and its "
                                "commands come late"),
        "controller_budget": ("[controller.deadline] budget_s is the controller's budget from the estimate's arrival "
                              "to the command leaving: the bench's controller, in real time, sends its fallback "
                              "(fallback = hold: the last command; shifted_plan: the last on-time plan; lqr) past it, "
                              "with ThrustCommand.fallback set, and publishes a DeadlineEvent on event/deadline; "
                              "`bench contract check` reports an outside controller's response time at the recorder "
                              "against it"),
        "stages": list(STAGES),
        "stop": (f"after the last step (status/step with finished = true) the launcher stops answering "
                 f"presence/launcher; stop within {CHECK_STOP_GRACE_S:g} s of that (bench contract check kills and "
                 "fails a node that does not)"),
    }


def _envelopes(scenario: Scenario) -> dict:
    params = scenario.params()
    board = scenario.can.board if scenario.can is not None else BoardConfig()
    driver = scenario.can.driver if scenario.can is not None else DriverConfig()
    on_reject = scenario.plant.command_acceptance.on_reject
    return {
        "thrust": {
            "message": "ThrustCommand", "field": "thrust_n", "topic": keys.COMMAND_THRUST, "loop": "rendezvous",
            "unit": "N", "max_abs_n": params.max_abs_thrust_n, "per_axis": True,
            "tolerance_rel": ENVELOPE_REL_TOL,
            "rule": "each |thrust_n[i]| <= max_abs_n (1 + tolerance_rel), and three finite numbers",
            "on_reject": on_reject,
            "outside": (f"the plant's output stage refuses the command and counts it under its reason "
                        f"(command_acceptance.json, `thrust`), never applies it and never clips it; the step then gets "
                        f"the on_reject policy: \"hold\" (the last accepted command) or \"zero\"; currently "
                        f"\"{on_reject}\". In lock-step the plant first waits for an acceptable command until "
                        f"command_timeout_s"),
            "refusal_reasons": {r: REFUSAL_MEANINGS[r] for r in REASONS},
        },
        "dipole": {
            "message": "DipoleCommand", "field": "dipole_am2", "topic": keys.COMMAND_DIPOLE, "loop": "attitude",
            "unit": "A m^2", "max_abs_am2": board.max_dipole_am2, "per_axis": True,
            "resolution_am2": board.dipole_resolution_am2,
            "refused_above_am2": board.max_dipole_am2 + 0.5 * board.dipole_resolution_am2,
            "controller_limit_am2": scenario.attitude_control.dipole_limit_am2 or board.max_dipole_am2,
            "board_command_timeout_s": board.command_timeout_s,
            "driver_command_period_s": driver.command_period_s,
            "on_reject": on_reject,
            "outside": ("the board ([can.board]) saturates each axis at max_abs_am2 and quantises to resolution_am2; "
                        "the attitude plant refuses a DipoleCommand or a board report beyond refused_above_am2 "
                        "(out_of_envelope: the command gets the on_reject policy, a report is replaced by zero, "
                        "coils off); no valid command for board_command_timeout_s puts the board in its safe "
                        "state (coils off)"),
        },
    }


def _frames(scenario: Scenario) -> dict:
    return {
        "navigation_frame": scenario.plant.navigation_frame,
        "navigation": fields.NAVIGATION,
        "lvlh": fields.LVLH,
        "curvilinear": fields.CURVILINEAR,
        "target": ("the target flies a circular orbit of radius target_radius_m and sits at the origin of the "
                   "navigation frame; the chaser's state is relative to it"),
        "body": fields.BODY,
        "inertial": fields.INERTIAL,
        "quaternions": fields.QUATERNION,
        "units": "SI throughout, as each field's name says (_m, _mps, _n, _s, _rad, _radps, _t, _am2, _a, _ns)",
        "vector_fields": {f"{struct}.{name}": {"frame": f.frame, "unit": f.unit}
                          for struct, entries in fields.FIELDS.items() for name, f in entries.items() if f.frame},
    }


def _rendezvous_model(scenario: Scenario) -> dict:
    params, believed = scenario.params(), scenario.onboard_params()
    return {
        "mass_kg": params.mass_kg,
        "gravitational_parameter_m3ps2": params.gravitational_parameter_m3ps2,
        "target_radius_m": params.target_radius_m,
        "believed_target_radius_m": believed.target_radius_m,
        "believed_mean_motion_radps": believed.mean_motion,
        "time_step_s": params.time_step_s,
        "state_scaling": list(params.scaling),
        "scaling_meaning": ("seed 003's V: x_scaled = diag(state_scaling) x (m -> Mm, m/s -> km/s); the scenario's "
                            "[controller] q_diag weighs x_scaled and r_diag the thrust in N"),
        "controller_weights": {"q_diag": list(scenario.controller.q_diag), "r_diag": list(scenario.controller.r_diag)},
        "dynamics": ("Clohessy-Wiltshire-Hill in the LVLH frame (bench/gnc/cwh.py): x'' = 3 n^2 x + 2 n y' + "
                     "u_x / m, y'' = -2 n x' + u_y / m, z'' = -n^2 z + u_z / m, n = sqrt(mu / R^3), thrust held "
                     "over each step (zero-order hold)"),
        "plant_dynamics": scenario.plant.dynamics,
    }


def message_types() -> list[type]:
    """Every message of the key table, once, in table order."""
    seen: dict[str, type] = {}
    for topic in TOPICS:
        for kind in topic.messages:
            seen.setdefault(kind.__name__, kind)
    return list(seen.values())


def struct_types(kinds: list[type] | None = None) -> dict[str, type]:
    """Every Struct type the messages are made of, by name: the messages, their Header and nested
    types (CanWindow's SimFrame)."""
    found: dict[str, type] = {}

    def walk(info) -> None:
        if isinstance(info, msgspec.inspect.StructType):
            if info.cls.__name__ in found:
                return
            found[info.cls.__name__] = info.cls
            for f in info.fields:
                walk(f.type)
        if isinstance(info, msgspec.inspect.Metadata):
            walk(info.type)
        for attr in ("item_type", "key_type", "value_type"):
            if hasattr(info, attr):
                walk(getattr(info, attr))
        for sub in getattr(info, "types", ()) or ():
            walk(sub)
        for sub in getattr(info, "item_types", ()) or ():
            walk(sub)

    for info in msgspec.inspect.multi_type_info(kinds if kinds is not None else message_types()):
        walk(info)
    return found


def _messages() -> dict:
    by_message: dict[str, list[str]] = {}
    for t in TOPICS:
        for kind in t.messages:
            by_message.setdefault(kind.__name__, []).append(t.topic)
    out = {}
    for name, kind in struct_types(message_types()).items():
        tag = getattr(kind, "__struct_config__").tag
        entry = {"description": fields.MESSAGES.get(name) or _first_paragraph(kind.__doc__)}
        if tag is not None and tag is not False:
            entry["tag"] = tag
            entry["topics"] = by_message.get(name, [])
        names = ["type", *kind.__struct_fields__] if tag not in (None, False) else list(kind.__struct_fields__)
        entry["fields"] = {n: fields.field(name, n).to_json() for n in names if fields.field(name, n) is not None}
        out[name] = entry
    return out


def _first_paragraph(doc: str | None) -> str:
    return " ".join((doc or "").strip().split("\n\n")[0].split())


def _check() -> dict:
    return {
        "command": ("`bench contract check NODE --command CMD` splits CMD into words with shlex (POSIX rules) and "
                    "starts it without a shell (no pipes, redirections, variables or globs), then fills "
                    "{connect}, {run_id}, {scenario} and {run_dir} into each word"),
        "placeholders": {"connect": "the hub endpoint", "run_id": "the run's id",
                         "scenario": "runs/<run_id>/scenario.json", "run_dir": "runs/<run_id>"},
        "stop_grace_s": CHECK_STOP_GRACE_S,
        "forged_estimates": CHECK_FORGED_ESTIMATES,
        "replayed_estimates": CHECK_REPLAYED_ESTIMATES,
        "judged": ["authenticity (a valid, fresh tag on every message)", "keys (only the contract's, only your role's)",
                   "schemas", "sequence numbers and the header carried", "your own stages' stamps",
                   "the plant's refusals, by reason and count", "deadlines (real time: steps held)",
                   "commands that answer forged or replayed estimates", "the stop obeyed"],
        "output": "one line and exit 0 on a pass; exit 1 naming each problem; runs/<run_id>/contract_check.json",
    }
