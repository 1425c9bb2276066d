"""The published contract holds every number and meaning an outsider needs (issue 47).

`bench contract export` writes contract.json with the code's defaults, the launcher writes a run's
own beside scenario.json, every field of every exported schema is described (a new field without
a description fails here), and the allowed values are those the code emits. The outside example
reads its numbers and Zenoh settings from the run's contract.json (tests/test_contract.py runs it
through `bench contract check`).
"""
from __future__ import annotations

import hashlib
import hmac
import importlib.util
import json
import re
import sys
from pathlib import Path

import jsonschema
import msgspec
import pytest
from mcap.reader import make_reader

from bench.bus import data_auth, keys
from bench.bus.can.config import BoardConfig
from bench.bus.schemas import ThrustCommand, encode, header
from bench.bus.session import KEEP_ALIVE_PER_LEASE, SessionOptions, build_config, free_loopback_port, loopback_endpoint
from bench.contract import document, fields
from bench.contract_check import check, probe
from bench.contract.export import export
from bench.contract.table import TOPICS
from bench.config.controller import ATTITUDE_LAWS, DeadlineConfig, FallbackPolicy
from bench.gnc.cwh import RendezvousParams
from bench.plant.acceptance import REASONS
from bench.config.plant import CommandAcceptanceConfig, PlantConfig
from bench.scenario import LivelinessConfig, RunConfig, Scenario, parse_scenario
from conftest import REPO, run_bench_cli

EXAMPLE = REPO / "examples" / "outside_lqr_controller.py"
ZENOH_KEYS = ("mode", "scouting/multicast/enabled", "scouting/gossip/enabled", "listen/endpoints", "connect/endpoints",
              "transport/link/tx/lease", "transport/link/tx/keep_alive", "transport/shared_memory/enabled",
              "adminspace/enabled")


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> Path:
    directory = tmp_path_factory.mktemp("contract")
    export(directory)
    return directory


def session_settings(connect: str, lease_ms: int) -> dict:
    """What the bench's own session factory configures, read back from the zenoh.Config it builds."""
    config = build_config(SessionOptions(connect=(connect,), lease_ms=lease_ms))
    return {k: json.loads(config.get_json(k)) for k in ZENOH_KEYS}


# --- contract.json from `bench contract export`: the code's defaults ---------------------------
def test_export_writes_contract_json_with_the_codes_defaults(exported):
    c = json.loads((exported / "contract.json").read_text())
    run, live, params = RunConfig(), LivelinessConfig(), RendezvousParams.from_reference()
    # Envelopes: the thrusters' limit the plant's output stage applies, the board's dipole limit.
    thrust = c["envelopes"]["thrust"]
    assert thrust["max_abs_n"] == params.max_abs_thrust_n == 1.0
    assert thrust["on_reject"] == CommandAcceptanceConfig().on_reject
    assert list(thrust["refusal_reasons"]) == list(REASONS)
    assert "refuses" in thrust["outside"] and "never clips" in thrust["outside"]
    assert c["envelopes"]["dipole"]["max_abs_am2"] == BoardConfig().max_dipole_am2
    # Step period and deadlines.
    timing = c["timing"]
    assert timing["time_step_s"] == PlantConfig().time_step_s
    assert timing["time_factor"] == run.time_factor
    assert timing["real_time_period_s"] == PlantConfig().time_step_s / run.time_factor
    assert timing["command_timeout_s"] == run.command_timeout_s
    assert timing["controller_deadline"]["budget_s"] == DeadlineConfig().budget_s
    assert timing["liveliness"]["lease_s"] == live.lease_s
    assert "missed step" in timing["real_time"] and "fallback" in timing["controller_budget"]
    # Zenoh: exactly what the bench's own sessions get.
    zenoh = c["zenoh"]
    hub = "tcp/127.0.0.1:7447"
    assert {**zenoh["settings"], "connect/endpoints": [hub]} == session_settings(hub, int(live.lease_s * 1000))
    assert zenoh["settings"]["connect/endpoints"] == [document.HUB_PLACEHOLDER]
    assert zenoh["settings"]["mode"] == "peer" and zenoh["settings"]["scouting/multicast/enabled"] is False
    assert zenoh["settings"]["scouting/gossip/enabled"] is True
    assert zenoh["settings"]["listen/endpoints"] == [loopback_endpoint(0)]
    assert zenoh["settings"]["transport/shared_memory/enabled"] is False
    assert zenoh["lease_ms"] == 2000 and zenoh["keep_alive_per_lease"] == KEEP_ALIVE_PER_LEASE
    # Frames: LVLH/Hill axes, the target at the origin; quaternions scalar first, body to inertial.
    frames = c["frames"]
    assert frames["navigation_frame"] == "cartesian"
    assert "x radially outward" in frames["lvlh"] and "origin at the target" in frames["lvlh"]
    assert "scalar first" in frames["quaternions"] and "body to inertial" in frames["quaternions"]
    assert frames["vector_fields"]["TranslationEstimate.state_m_mps"]["frame"] == "navigation"
    assert frames["vector_fields"]["AttitudeEstimate.q_wxyz"]["frame"] == "body_to_inertial"
    # Readiness, the check's --command, the presence answer.
    assert "recorder" in c["readiness"]["matching"]
    assert "shlex" in c["check"]["command"] and "without a shell" in c["check"]["command"]
    assert set(c["presence"]["answer_payload"]) == {"process", "host", "ready", "monotonic_ns", "nonce"}
    assert c["rendezvous_model"]["state_scaling"] == list(params.scaling)
    assert c["schema_version"] == 1 and c["keys"]["prefix"] == "bench/<run_id>/"


def test_contract_json_describes_every_message_field_and_its_allowed_values(exported):
    messages = json.loads((exported / "contract.json").read_text())["messages"]
    status = messages["ThrustCommand"]["fields"]["status"]
    assert "solved" in status["allowed"] and "waiting_for_estimate" in status["allowed"]
    assert messages["ThrustCommand"]["fields"]["fallback"]["allowed"] == ["hold", "shifted_plan", "lqr"]
    assert messages["ThrustCommand"]["fields"]["solve_time_s"]["unit"] == "s"
    assert "ctrl_feasible" in messages["ThrustCommand"]["fields"]
    assert messages["ThrustCommand"]["topics"] == ["command/thrust", "command/applied"]
    for name, kind in document.struct_types().items():
        assert set(kind.__struct_fields__) <= set(messages[name]["fields"]), name


def test_the_tag_as_contract_json_describes_it_is_the_bench_tag(exported):
    """An outsider following `signing` byte for byte writes the tag data_auth checks."""
    s = json.loads((exported / "contract.json").read_text())["signing"]
    key, key_expr, payload, sender, counter = bytes(range(32)), "bench/r/command/thrust", b'{"a":1}', b"controller", 7
    head = bytes((s["version"], len(sender))) + sender + counter.to_bytes(s["counter_bytes"], "big")
    mac = hmac.new(key, key_expr.encode() + b"\x00" + head + payload, hashlib.sha256).digest()
    assert len(mac) == s["mac_bytes"]
    assert head + mac == data_auth.tag(key, key_expr, payload, sender, counter)
    assert data_auth.open_tag(key, key_expr, payload, head + mac) == (sender, counter)


def test_the_check_numbers_in_the_contract_are_the_checks():
    assert document.CHECK_STOP_GRACE_S == check.STOP_GRACE_S
    assert (document.CHECK_FORGED_ESTIMATES, document.CHECK_REPLAYED_ESTIMATES) == (probe.N_FORGED, probe.N_REPLAYED)


# --- every field described, in the schemas the outsider gets -------------------------------------
def undescribed(directory: Path) -> list[str]:
    """Fields of the exported schemas without a description: Struct.field for each."""
    missing = []
    for path in sorted((directory / "schemas").glob("*.schema.json")):
        schema = json.loads(path.read_text())
        for node in [schema, *schema.get("$defs", {}).values()]:
            props = node.get("properties", {})
            items = list(props.items()) or [(str(i), p) for i, p in enumerate(node.get("prefixItems", []))]
            missing += [f"{node.get('title')}.{name}" for name, prop in items if not prop.get("description")]
    return sorted(set(missing))


def test_every_field_of_every_exported_message_is_described(exported):
    assert len(list((exported / "schemas").glob("*.schema.json"))) == 1 + len(document.message_types())
    assert undescribed(exported) == []
    for name, kind in document.struct_types().items():
        for field_name in kind.__struct_fields__:
            entry = fields.field(name, field_name)
            assert entry is not None and entry.text, f"{name}.{field_name} has no description in bench/contract/fields.py"


def test_a_field_without_a_description_fails(tmp_path, monkeypatch):
    """What a new, undocumented field does: the check above names it."""
    thrust = {k: v for k, v in fields.FIELDS["ThrustCommand"].items() if k != "ctrl_feasible"}
    monkeypatch.setitem(fields.FIELDS, "ThrustCommand", thrust)
    export(tmp_path)
    assert undescribed(tmp_path) == ["ThrustCommand.ctrl_feasible"]


def test_units_frames_and_allowed_values_are_in_the_schemas(exported):
    schema = json.loads((exported / "schemas" / "ThrustCommand.schema.json").read_text())
    props = schema["properties"]
    assert "Unit: N." in props["thrust_n"]["description"] and "LVLH" in props["thrust_n"]["description"]
    assert props["fallback"]["enum"] == [*fields.FALLBACKS, None]
    good = json.loads(encode(ThrustCommand(header("r1", 3, 1800.0, sensed=5), [0.1, -0.2, 0.3], True, "solved", 1e-5)))
    jsonschema.validate(good, schema)
    jsonschema.validate({**good, "status": "in-plane SOLVED, out-of-plane INFEASIBLE"}, schema)    # the tube MPC
    for bad in ({**good, "status": "optimal"}, {**good, "fallback": "retry"}):
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(bad, schema)
    estimate = json.loads((exported / "schemas" / "TranslationEstimate.schema.json").read_text())["properties"]
    assert "x radially out" in estimate["state_m_mps"]["description"]
    assert "origin at the target" in estimate["state_m_mps"]["description"]
    attitude = json.loads((exported / "schemas" / "AttitudeEstimate.schema.json").read_text())["properties"]
    assert "scalar first" in attitude["q_wxyz"]["description"] and "body to inertial" in attitude["q_wxyz"]["description"]
    header_schema = json.loads((exported / "schemas" / "Header.schema.json").read_text())
    assert header_schema["properties"]["schema_version"]["enum"] == [1]


def _literals(paths, pattern: str) -> set[str]:
    found: set[str] = set()
    for path in paths:
        for match in re.finditer(pattern, (REPO / path).read_text()):
            found.add(next(g for g in match.groups() if g))
    return found


def test_allowed_values_are_those_the_code_emits():
    import proxsuite

    from bench.controller.cycle import WAITING_FOR_ESTIMATE

    emitted = _literals([*Path(REPO / "bench" / "gnc").glob("*.py"), *Path(REPO / "bench" / "controller").glob("*.py")],
                        r'"status": "([A-Za-z_]+)"|status="([A-Za-z_]+)"')
    emitted -= _literals([REPO / "bench" / "gnc" / "boxqp.py", REPO / "bench" / "gnc" / "milqr.py"],
                         r'"status": "([A-Za-z_]+)"|status="([A-Za-z_]+)"')    # not ThrustCommand statuses
    proxqp = {n for n in dir(proxsuite.proxqp.QPSolverOutput) if n.startswith("PROXQP_")} - {"PROXQP_SOLVED"}
    assert {"solved", "SOLVED", "INFEASIBLE", "UNCERTIFIED", "NO_RESULT_BY_DEADLINE"} <= emitted
    assert emitted | proxqp | {WAITING_FOR_ESTIMATE} <= set(fields.THRUST_STATUSES)
    stop_reasons = _literals([REPO / "bench" / "gnc" / "milqr.py", REPO / "bench" / "planner" / "plan.py"],
                             r'stop_reason(?:, \w+)* = "([a-z_]+)"|"stop_reason": "([a-z_]+)"')
    assert stop_reasons == set(fields.PLAN_STOP_REASONS)
    assert fields.FALLBACKS == FallbackPolicy.__args__
    assert set(fields.FIELDS["DipoleCommand"]["law"].allowed) == set(ATTITUDE_LAWS)
    assert fields.UNAUTHENTIC_KINDS == (data_auth.FORGED, data_auth.REPLAYED)
    by_topic = {t.topic: t for t in TOPICS}
    assert set(fields.DEADLINE_PROCESSES) == set(by_topic[keys.EVENT_DEADLINE].publishers)
    assert set(fields.STATS_PROCESSES) == set(by_topic[f"{keys.STATUS_STATS}/<process>"].publishers)


# --- the example reads what it needs from contract.json ------------------------------------------
def _example_module():
    spec = importlib.util.spec_from_file_location("outside_lqr_controller", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_example_takes_its_numbers_and_zenoh_settings_from_contract_json(exported):
    example = _example_module()
    contract = json.loads((exported / "contract.json").read_text())
    source = EXAMPLE.read_text()
    assert "SEED_MAX_ABS_THRUST_N" not in source and "SEED_SCALING" not in source
    assert "insert_json5(key, json.dumps(value))" in source
    assert example.session_settings(contract, "tcp/127.0.0.1:7447") == session_settings("tcp/127.0.0.1:7447", 2000)
    version, scaling, u_max = example.contract_numbers(contract)
    assert (version, list(scaling), u_max) == (1, list(RendezvousParams.from_reference().scaling), 1.0)
    other = {**contract, "envelopes": {"thrust": {**contract["envelopes"]["thrust"], "max_abs_n": 0.25}}}
    assert example.contract_numbers(other)[2] == 0.25
    with pytest.raises(SystemExit, match="tag version"):
        example.contract_numbers({**contract, "signing": {**contract["signing"], "version": 2}})


# --- a run's own contract.json ------------------------------------------------------------------
SCENARIO = """
name = "contract_numbers"
[run]
steps = 3
command_timeout_s = 7.5
time_factor = 3000.0
[run.liveliness]
lease_s = 3.5
[controller.deadline]
budget_s = 0.04
[plant]
dynamics = "nonlinear"
navigation_frame = "curvilinear"
[plant.command_acceptance]
on_reject = "zero"
"""


def test_a_run_writes_its_own_contract_json_beside_scenario_json(tmp_path, runs_dir, exported):
    """The per-run contract carries that run's numbers (lease, timeout, period, budget, on_reject, frame,
    hub and run id), equals the document built from its scenario, holds no key, and the run's own
    messages validate against the exported schemas (enums included)."""
    path = tmp_path / "numbers.toml"
    path.write_text(SCENARIO)
    port = free_loopback_port()
    result = run_bench_cli("run", str(path), "--runs-dir", str(runs_dir), "--run-id", "numbers", "--port", str(port),
                           "--no-progress", "--no-report", timeout_s=240)
    assert result.returncode == 0, result.stdout + result.stderr
    run_dir = runs_dir / "numbers"
    text = (run_dir / "contract.json").read_text()
    c = json.loads(text)
    hub = loopback_endpoint(port)
    scenario = parse_scenario(msgspec.json.decode((run_dir / "scenario.json").read_bytes()), "run")
    assert c == json.loads(json.dumps(document.contract_document(scenario, "numbers", hub)))
    assert c["zenoh"]["settings"] == session_settings(hub, 3500)
    assert c["zenoh"]["connect"] == hub and c["keys"]["prefix"] == "bench/numbers/"
    assert c["timing"]["command_timeout_s"] == 7.5 and c["timing"]["liveliness"]["lease_s"] == 3.5
    assert c["timing"]["real_time_period_s"] == PlantConfig().time_step_s / 3000.0
    assert c["timing"]["controller_deadline"]["budget_s"] == 0.04
    assert c["envelopes"]["thrust"]["on_reject"] == "zero" and c["frames"]["navigation_frame"] == "curvilinear"
    assert c["written_for"] == {**c["written_for"], "run_id": "numbers", "scenario": "contract_numbers"}
    assert all(t["key"] == f"bench/numbers/{t['topic']}" for t in c["keys"]["topics"])
    assert c != json.loads((exported / "contract.json").read_text())
    assert (run_dir / "bus.key").read_text().strip() not in text
    schemas = {json.loads(p.read_text())["properties"]["type"]["enum"][0]: json.loads(p.read_text())
               for p in (exported / "schemas").glob("*.schema.json") if p.name != "Header.schema.json"}
    validated = 0
    with open(run_dir / "recording.mcap", "rb") as f:
        for _schema, _channel, message in make_reader(f).iter_messages():
            obj = json.loads(message.data)
            if isinstance(obj, dict) and obj.get("type") in schemas:
                jsonschema.validate(obj, schemas[obj["type"]])
                validated += 1
    assert validated >= 3 * 6       # truth, two sensors, estimate, command, applied, step per step


# --- docs/contract.md: the outsider's first page -------------------------------------------------
def test_the_outsiders_page_opens_in_order_with_the_codes_numbers():
    text = (REPO / "docs" / "contract.md").read_text()
    sections = ["## 1. What to run", "## 2. How to connect", "## 3. The presence answer", "## 4. Signing",
                "## 5. The messages and their fields", "## 6. Envelopes and timing", "## 7. How to check your node"]
    positions = [text.index(s) for s in sections]
    assert positions == sorted(positions) and positions[0] < text.index("## Roles in the attitude loop")
    c = document.contract_document(Scenario(name="defaults"))
    envelopes = text[positions[5]:positions[6]]
    timing = c["timing"]
    for expected in (f"at most {c['envelopes']['thrust']['max_abs_n']:g} N",
                     f"at most {c['envelopes']['dipole']['max_abs_am2']:g} A m^2", f"{timing['time_step_s']:g} s",
                     f"= {timing['real_time_period_s']:g} s", f"{timing['command_timeout_s']:g} s",
                     f"{timing['controller_deadline']['budget_s'] * 1e3:g} ms", f"{timing['liveliness']['lease_s']:g} s"):
        assert expected in envelopes, expected
    connect = text[positions[1]:positions[2]]
    for key, value in c["zenoh"]["settings"].items():
        if key != "connect/endpoints":
            assert f"`{key}`" in connect and json.dumps(value) in connect, key
    assert "shlex" in text[positions[6]:] and "without a shell" in text[positions[6]:]


# --- a controller written from contract.json alone passes the check ----------------------------
CONTRACT_ONLY = REPO / "tests" / "contract_only_controller.py"


def test_a_controller_from_contract_json_alone_passes_the_check_and_flies_the_built_in_lqr(runs_dir):
    """tests/contract_only_controller.py reads nothing but the run's contract.json and bus.key (no
    scenario.json, nothing from bench): its keys, presence key, tag format, Zenoh settings, model,
    weights, scaling and thrust limit all come from the contract."""
    from conftest import assert_rendezvous_lqr_run_equals_in_process

    source = CONTRACT_ONLY.read_text()
    code = source.split('"""', 2)[2]
    assert "scenario.json" not in code and "import bench" not in code and "from bench" not in code
    command = f"{sys.executable} {CONTRACT_ONLY} --run-dir {{run_dir}}"
    result = run_bench_cli("contract", "check", "controller", "--steps", "12", "--runs-dir", str(runs_dir),
                           "--run-id", "contract-only", "--command", command, timeout_s=240)
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.startswith("contract check controller: pass")
    assert_rendezvous_lqr_run_equals_in_process(runs_dir / "contract-only", 12)
