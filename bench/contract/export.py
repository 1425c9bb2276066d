"""`bench contract export DIR`: the message contract as files another team can build against.

DIR/schemas/<Message>.schema.json   JSON Schema (draft 2020-12, from msgspec) of each message
DIR/keys.json, DIR/keys.md          the key-expression table (bench.contract.table)
DIR/protocol.md                     lock-step and real time: what releases what, timeouts, staleness,
                                    sequence numbers, the header and its stamps
DIR/contract.json                   every number and meaning as data (bench.contract.document): Zenoh
                                    settings, tag and presence formats, timing, envelopes, frames,
                                    and each message's fields with their units and allowed values

Every field in the schemas carries a `description` (its unit and frame included) and, where it has
allowed values, an `enum`, from bench.contract.fields. The numbers in protocol.md and contract.json
(timeouts, budgets, lease, envelopes) are the scenario defaults read from the code that applies
them, so the documents cannot drift from the bench; a run's own are in runs/<id>/contract.json.
"""
from __future__ import annotations

import json
from pathlib import Path

from bench.bus import keys
from bench.bus.schemas import SCHEMA_VERSION, STAGES, Header, Message, json_schema
from bench.contract import fields
from bench.contract.document import CONTRACT_FILE, message_types, struct_types, write_contract
from bench.contract.table import TOKENS, TOPICS
from bench.config.controller import DeadlineConfig
from bench.runtime.time_model import TimeModel
from bench.plant.acceptance import REASONS
from bench.scenario import LivelinessConfig, RunConfig, Scenario

SCHEMA_DIR = "schemas"


def root_object_schema(kind: type) -> dict:
    """msgspec's schema with the message's object at the root ($defs kept for nested types), every
    field described."""
    schema = json_schema(kind)
    defs = schema.get("$defs", {})
    root = schema.get("$ref", "").rpartition("/")[2]
    out = {**defs[root], "$defs": defs} if root in defs else dict(schema)
    return described({"$schema": "https://json-schema.org/draft/2020-12/schema", "$id": f"{kind.__name__}.schema.json",
                      **out})


def described(schema: dict) -> dict:
    """The schema with each struct's description and each field's `description` (unit, frame and
    allowed values in words) and `enum` (or `anyOf` of an enum and a pattern) from bench.contract.fields."""
    structs = struct_types([*message_types(), Header])
    for node in [schema, *schema.get("$defs", {}).values()]:
        name = node.get("title")
        kind = structs.get(name)
        if kind is None:
            continue
        if "description" not in node and name in fields.MESSAGES:
            node["description"] = fields.MESSAGES[name]
        items = node.get("properties", {}).items() if "properties" in node else \
            zip(kind.__struct_fields__, node.get("prefixItems", []))
        for field_name, prop in items:
            entry = fields.field(name, field_name)
            if entry is not None:
                _describe(prop, entry)
    return schema


def _describe(prop: dict, entry: fields.Field) -> None:
    prop["description"] = entry.description()
    if entry.allowed:
        nullable = {"type": "null"} in prop.get("anyOf", [])
        values = [*entry.allowed, *([None] if nullable else [])]
        if entry.pattern:
            prop["anyOf"] = [{"enum": values}, {"type": "string", "pattern": entry.pattern}]
        else:
            prop["enum"] = values
    if entry.keys:
        prop["propertyNames"] = {"enum": list(entry.keys)}


def keys_markdown() -> str:
    lines = ["# Key expressions", "",
             f"Every key is `{keys.PREFIX}/<run_id>/<topic>`. Payloads are JSON, one message each, "
             "schemas in `schemas/`. The recorder reads every topic.", "",
             "| topic | message | loop | published by | read by | what |", "|---|---|---|---|---|---|"]
    for t in TOPICS:
        lines.append(f"| `{t.topic}` | {', '.join(m.__name__ for m in t.messages)} | {t.loop} | "
                     f"{', '.join(t.publishers)} | {', '.join(t.readers) or '(recorder)'} | {t.what} |")
    lines += ["", "## Control plane (presence queries and the launcher's token)", "", "| key | meaning |", "|---|---|"]
    lines += [f"| `{keys.PREFIX}/<run_id>/{token}` | {meaning} |" for token, meaning in TOKENS.items()]
    return "\n".join(lines) + "\n"


def protocol_markdown() -> str:
    run, live, budget = RunConfig(), LivelinessConfig(), DeadlineConfig().budget_s
    period_s = 600.0 / run.time_factor
    stages = ", ".join(f"`{s}`" for s in STAGES)
    return f"""# The bench's loop protocol (schema version {SCHEMA_VERSION})

Written by `bench contract export`; the numbers are the scenario defaults (`[run]`,
`[run.liveliness]`, `[controller.deadline]`), which a scenario may change.

## Messages and the header

Each payload is one JSON object: a `"type"` tag, a `header` and the message's fields (see
`schemas/`). Unknown fields, missing required fields, wrong types and vectors of the wrong length
are refused; a refused payload is counted by its receiver and dropped, never fatal.

Each sample also carries a tag in its Zenoh attachment: version 1, the sender's name (length
byte, then the name), an 8-byte big-endian counter that goes up with every message, and
HMAC-SHA256 under the run's key (`runs/<run_id>/bus.key`, 64 hex digits) over the key expression,
a zero byte, those bytes and the payload. A sample without a valid tag is dropped as forged, one
whose counter its receiver has already passed as replayed (docs/contract.md, "Signing").

The header: `schema_version` ({SCHEMA_VERSION}), `run_id` (the run's id, also the second chunk of
every key), `seq` (the index k of the plant sample the message derives from), `sim_time_s` (the
simulated time of sample k) and `stamps_ns` (stage -> `CLOCK_MONOTONIC` in ns on the host that
handled it). Stages, in loop order: {stages}. A message derived from another carries its header:
same `seq`, same `sim_time_s`, the upstream stamps unchanged, its own stages added. Stamps of a part
the bench does not run are that part's own claims; the report marks them as such.

## Start

1. Each node opens its Zenoh session (contract.json `zenoh.settings`: peer, multicast scouting
   off, the launcher's hub as connect endpoint) and answers presence queries on `presence/<name>` (below). The launcher waits for
   an authentic answer from every node, up to `startup_timeout_s` = {live.startup_timeout_s:g} s.
2. A node's answer says `"ready": true` once every topic it publishes into the loop has a
   subscriber (a sample published before its subscriber matched is lost).
3. The plant waits for a ready answer from every peer, then publishes step 0.

## Presence: liveliness, readiness and clock

A presence query on `presence/*` (or `presence/<name>`) carries a nonce, 32 hex digits, as its
payload. A node answers on its own key `presence/<name>` with the JSON payload
`{{"process": "<name>", "host": "<host>", "ready": true|false, "monotonic_ns": <CLOCK_MONOTONIC ns>,
"nonce": "<the query's nonce>"}}` and the tag of a message (the attachment above, sender
`<name>`) over that key expression and payload. An answer counts only with a valid tag whose
sender is the name in the key and in the payload, and the query's nonce: without the run's key
nothing can declare a node alive or ready, hide that one stopped (a stopped process answers
nothing), or skew the clock offsets the recorder measures from the same answers.

## Lock-step (`[run] mode = "lock-step"`)

Step k, with sample k releasing estimate k, estimate k releasing command k, command k releasing step k+1:
1. The plant publishes `truth`, `sense/relpos` and `sense/range_bearing` of step k (`seq` = k,
   stamp `sensed`).
2. The estimator publishes one `estimate/translation` with `seq` = k (stamps `estimator_received`,
   `estimated`). In smoother mode it first waits up to {TimeModel(lock_step=True).promised_wait_s(0.0):g} s for command k-1 (the thrust
   it fuses); truth mode passes `truth` on.
3. The controller publishes exactly one `command/thrust` for estimate k: `header.seq` = k, the
   estimate's `sim_time_s` and stamps, plus `controller_received` and `commanded`. One command
   per step, no step skipped, no step repeated.
4. The plant waits for the first acceptable command with `seq` = k, applies it, publishes
   `command/applied` (stamps `plant_received`, `applied`), integrates and publishes `status/step`.

Acceptable means (the plant's output stage): three finite numbers, `seq` equal to the step being
integrated, each |u_i| within the thrusters' limit. Refusal reasons, counted per reason:
{', '.join(f'`{r}`' for r in REASONS)}. `stale` is a command for a step already integrated
(`seq` < k), `future` one for a step not reached (`seq` > k).

Timeout: no command for step k within `command_timeout_s` = {run.command_timeout_s:g} s breaks the loop (the plant
exits 1, the run ends with exit 1). If only refused commands came by then, the plant applies its
`[plant.command_acceptance] on_reject` policy (hold the last accepted command, or zero) and goes on.

## Real time (`[run] mode = "real-time"`)

The plant publishes sample k at t0 + k * period on its monotonic clock, period = `time_step_s /
time_factor` ({period_s:g} s by default) and never waits. The command for step k must arrive before
step k+1's tick; otherwise step k is integrated on the last accepted command (zero-order hold) and
counted as a plant-side missed step; a command that comes after its step was integrated is counted
as late and not applied. The estimator does not wait for commands ({TimeModel(lock_step=False).promised_wait_s(0.0):g} s). The controller's
own budget, from the estimate's arrival to the command leaving, is `[controller.deadline] budget_s`
= {budget * 1e3:g} ms (the built-in controller applies its fallback past it and publishes a
`DeadlineEvent` on `event/deadline`).

## Liveliness and the end

Leases are `lease_s` = {live.lease_s:g} s: the launcher and the plant ask every lease / 4, and a
node that gives no authentic presence answer for a lease is silent; one silent for `hang_timeout_s`
= {live.hang_timeout_s:g} s (or stopped, state T, for `stopped_grace_s` = {live.stopped_grace_s:g} s) is lost: the plant
breaks the loop and the launcher names the process. After the last step (its `status/step` has
`finished` = true) the launcher stops answering `presence/launcher`, undeclares its liveliness token
`alive/launcher` (a hint to ask at once) and stops its own nodes; a node the launcher did not start
stops when the launcher no longer answers. A node may publish
its counts once as it stops (`status/stats/<name>`, ProcessStats).
"""


def export(directory: Path) -> list[Path]:
    """Write the contract into `directory` (created); the files written."""
    directory = Path(directory)
    (directory / SCHEMA_DIR).mkdir(parents=True, exist_ok=True)
    written = []
    for kind in [Header, *message_types()]:
        path = directory / SCHEMA_DIR / f"{kind.__name__}.schema.json"
        schema = root_object_schema(kind) if issubclass(kind, Message) else described({
            "$schema": "https://json-schema.org/draft/2020-12/schema", "$id": "Header.schema.json",
            **_header_schema()})
        path.write_text(json.dumps(schema, indent=2) + "\n")
        written.append(path)
    table = {"prefix": f"{keys.PREFIX}/<run_id>/", "schema_version": SCHEMA_VERSION,
             "topics": [t.to_json() for t in TOPICS],
             "control_plane": [{"key": keys.key("<run_id>", k), "meaning": v} for k, v in TOKENS.items()]}
    for name, text in (("keys.json", json.dumps(table, indent=2) + "\n"), ("keys.md", keys_markdown()),
                       ("protocol.md", protocol_markdown())):
        (directory / name).write_text(text)
        written.append(directory / name)
    written.append(write_contract(directory / CONTRACT_FILE, Scenario(name="defaults")))
    return written


def _header_schema() -> dict:
    schema = json_schema(Header)
    defs = schema.get("$defs", {})
    return {**defs["Header"], "$defs": {k: v for k, v in defs.items() if k != "Header"}} if "Header" in defs else schema
