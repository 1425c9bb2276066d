"""The message contract (issue 25): the export, the outside example controller and `bench contract check`.

The example is the proof: it imports nothing from `bench`, closes the rendezvous loop as an
external controller, passes the check and flies the built-in LQR's trajectory (bench.sim, the
in-process reference the multi-process runs equal) to 1e-9; broken on purpose, it fails the check
with each problem named. Two bench runs in all, so the file stays short.
"""
from __future__ import annotations

import ast
import json
import sys

import jsonschema
import msgspec
import pytest

from bench.bus import acl
from bench.bus.schemas import ThrustCommand, encode, header
from bench.contract.check import _sequence_problems
from bench.contract.export import export
from bench.contract.table import TOPICS, chunks_match
from bench.launcher import external_parts
from bench.report.deadlines import deadlines
from bench.report.rundata import load_run
from bench.scenario import ScenarioError, load_scenario, parse_scenario
from conftest import REPO, assert_rendezvous_lqr_run_equals_in_process, run_bench_cli

EXAMPLE = REPO / "examples" / "outside_lqr_controller.py"
STEPS = 20


def example_command(*extra: str) -> str:
    return " ".join([sys.executable, str(EXAMPLE), "--connect {connect} --run-id {run_id} --scenario {scenario}", *extra])


# --- fast: the example's imports, the export, the table, the sequence rules -------------------
def test_the_example_imports_nothing_from_bench():
    imported = set()
    for node in ast.walk(ast.parse(EXAMPLE.read_text())):
        if isinstance(node, ast.Import):
            imported |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            imported.add((node.module or ".").split(".")[0])
    assert "bench" not in imported and "." not in imported
    assert {"zenoh", "json", "numpy"} <= imported


def test_exported_schemas_accept_the_bench_messages_and_refuse_what_msgspec_refuses(tmp_path):
    written = export(tmp_path)
    assert {"keys.json", "keys.md", "protocol.md"} <= {p.name for p in written}
    schema = json.loads((tmp_path / "schemas" / "ThrustCommand.schema.json").read_text())
    good = json.loads(encode(ThrustCommand(header("r1", 3, 1800.0, sensed=5), [0.1, -0.2, 0.3], True, "solved", 1e-5)))
    jsonschema.validate(good, schema)          # an independent validator agrees with msgspec
    for bad in ({**good, "thrust_vec": [0, 0, 0]}, {**good, "thrust_n": [0.1, 0.2]},
                {**good, "header": {**good["header"], "seq": -1}}):
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(bad, schema)
    table = json.loads((tmp_path / "keys.json").read_text())
    thrust = next(t for t in table["topics"] if t["topic"] == "command/thrust")
    assert thrust["publishers"] == ["controller"] and thrust["key"] == "bench/<run_id>/command/thrust"
    assert "command_timeout_s" in (tmp_path / "protocol.md").read_text()


@pytest.mark.parametrize("topic", TOPICS, ids=lambda t: t.topic)
def test_the_access_control_table_allows_every_publisher_and_reader_of_the_key_table(topic):
    concrete = topic.topic.replace("<process>", "{name}")
    for name in topic.publishers:
        assert any(chunks_match(p, concrete.format(name=name)) for p in acl.publications(name)), (name, topic.topic)
    for name in topic.readers:
        assert any(chunks_match(p, concrete.format(name="plant")) for p in acl.subscriptions(name)), (name, topic.topic)


def test_sequence_rules_name_skipped_repeated_unknown_and_disordered():
    problems: list[str] = []
    _sequence_problems([0, 2, 2, 1, 7], [0, 1, 2, 3], problems)
    text = "\n".join(problems)
    assert "header.seq 3 (skipped" in text and "header.seq 2 repeated" in text
    assert "7 answers no estimate" in text and "went back" in text
    clean: list[str] = []
    _sequence_problems([0, 1, 2, 3], [0, 1, 2, 3], clean)
    assert clean == []


def test_external_is_bounded_to_the_controller_and_the_board():
    with pytest.raises(ScenarioError, match="run.external"):
        parse_scenario({"name": "x", "run": {"external": ["plant"]}}, "test")
    attitude = load_scenario("attitude_quick")
    attitude = msgspec.structs.replace(attitude, run=msgspec.structs.replace(attitude.run, external=["controller"] * 2))
    with pytest.raises(ScenarioError, match="named twice"):
        external_parts(attitude)
    # The attitude loop's controller (law and CAN driver) and board: tests/test_external_roles.py.


# --- two runs: the example passes and equals the built-in LQR; the broken one fails --------------
def test_the_example_passes_the_check_and_flies_the_built_in_lqr(runs_dir):
    result = run_bench_cli("contract", "check", "controller", "--steps", str(STEPS), "--runs-dir", str(runs_dir),
                           "--run-id", "contract-pass", "--command", example_command(), timeout_s=240)
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.startswith("contract check controller: pass") and result.stdout.count("\n") == 1
    assert_rendezvous_lqr_run_equals_in_process(runs_dir / "contract-pass", STEPS)
    metrics = json.loads((runs_dir / "contract-pass" / "metrics.json").read_text())
    assert metrics["processes"]["controller"]["host"] == "external"
    # The report does not take the outside controller's own stamps for a measured cycle time.
    result = deadlines(load_run(runs_dir / "contract-pass"))
    assert result.external == ["controller"] and result.cycle_time_s.size == 0


def test_a_broken_controller_fails_the_check_naming_each_problem(runs_dir):
    broken = example_command("--break skip-seq:1", "--break bad-field:3", "--break wrong-key:3")
    result = run_bench_cli("contract", "check", "controller", "--steps", "5", "--command-timeout", "2",
                           "--runs-dir", str(runs_dir), "--run-id", "contract-broken", "--command", broken, timeout_s=240)
    assert result.returncode == 1, result.stdout + result.stderr
    out = result.stdout
    assert "contract check controller: FAIL" in out
    assert "wrong key: 1 message(s) on bench/contract-broken/command/thrust_cmd" in out
    assert "schema-invalid" in out and "unknown field `thrust_vec`" in out
    assert "no command with header.seq 1, 3 (skipped" in out
    assert "the run did not finish" in out
