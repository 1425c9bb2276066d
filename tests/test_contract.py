"""The message contract (issue 25): the export, the outside example controller and `bench contract check`.

The example is the proof: it imports nothing from `bench`, closes the rendezvous loop as an
external controller, passes the check and flies the built-in LQR's trajectory (bench.sim, the
in-process reference the multi-process runs equal) to 1e-9; broken on purpose, it fails the check
with each problem named. Two bench runs in all, so the file stays short.
"""
from __future__ import annotations

import ast
import json
import re
import sys

import jsonschema
import msgspec
import pytest

from bench.bus import acl
from bench.bus.schemas import ThrustCommand, encode, header
from bench.contract_check.check import _sequence_problems
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
    assert "7 answers none of the estimates" in text and "went back" in text
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


# --- what the bench did with the outsider's messages, and what it did with the bench's ----------
def _check(runs_dir, run_id: str, *misbehave: str, mode: str = "lock-step", steps: int = 6):
    command = example_command(*(f"--misbehave {m}" for m in misbehave))
    return run_bench_cli("contract", "check", "controller", "--steps", str(steps), "--mode", mode,
                         "--command-timeout", "2", "--runs-dir", str(runs_dir), "--run-id", run_id,
                         "--command", command, timeout_s=240)


@pytest.mark.parametrize("mode", ["lock-step", "real-time"])
def test_a_controller_without_saturation_fails_naming_the_plant_refusals(runs_dir, mode):
    """No thrust limit: the plant refuses the commands over 1 N as out_of_envelope. Both modes fail
    naming the reason and the count, and a refused command is not called a deadline miss."""
    result = _check(runs_dir, f"nosat-{mode}", "no-saturation", mode=mode)
    assert result.returncode == 1, result.stdout + result.stderr
    acceptance = json.loads((runs_dir / f"nosat-{mode}" / "command_acceptance.json").read_text())["thrust"]
    n = acceptance["rejected"]["out_of_envelope"]
    assert n > 0
    assert f"refused by the plant: out_of_envelope {n} command(s)" in result.stdout
    assert "at most 1 N" in result.stdout
    assert "deadline" not in result.stdout


@pytest.mark.parametrize("misbehaviour, named", [
    ("foreign-key", "foreign key: 6 message(s) signed by the controller on bench/bad-foreign-key/command/applied"),
    ("no-stamps", "stamps: 6 command(s) without the stamps controller_received and commanded"),
    ("trust-all", "acted on forged estimates: 3 command(s)"),
    ("ignore-stop", "stop not obeyed"),
    ("free-status", "status: 'ok' is not one of the contract's values"),
])
def test_a_misbehaving_controller_fails_the_check_naming_the_problem(runs_dir, misbehaviour, named):
    result = _check(runs_dir, f"bad-{misbehaviour}", misbehaviour)
    assert result.returncode == 1, result.stdout + result.stderr
    assert named in result.stdout, result.stdout
    if misbehaviour == "trust-all":
        assert "acted on replayed estimates" in result.stdout


def test_the_check_sends_forged_and_replayed_estimates_and_a_careful_controller_ignores_them(runs_dir):
    result = _check(runs_dir, "probed")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "3 forged and 2 replayed estimates sent by the check" in result.stdout
    assert_rendezvous_lqr_run_equals_in_process(runs_dir / "probed", 6)


def test_a_controller_that_never_connects_is_named_with_the_launcher_reason(runs_dir):
    result = run_bench_cli("contract", "check", "controller", "--steps", "3", "--runs-dir", str(runs_dir),
                           "--run-id", "never", "--command", f"{sys.executable} -c pass", "--startup-timeout", "5",
                           timeout_s=240)
    assert result.returncode == 1
    assert "not alive after" in result.stdout and "controller" in result.stdout, result.stdout


# --- bench contract check estimator -----------------------------------------------------------------
def _bench_node_command(node: str, *extra: str) -> str:
    return " ".join([sys.executable, "-m", "bench.cli", "node", node, "--run-id {run_id} --scenario {scenario}",
                     "--connect {connect} --run-dir {run_dir}", *extra])


def test_the_bench_estimator_from_outside_passes_the_estimator_check(runs_dir):
    result = run_bench_cli("contract", "check", "estimator", "--steps", "8", "--runs-dir", str(runs_dir),
                           "--run-id", "est-pass", "--command", _bench_node_command("estimator"), timeout_s=240)
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.startswith("contract check estimator: pass (rendezvous_smoother, lock-step, 8 samples, "
                                    "8 valid estimates seq 0-7 on estimate/translation")
    assert "3 forged and 2 replayed samples sent by the check" in result.stdout


def test_an_estimator_that_trusts_its_inputs_fails_the_estimator_check(runs_dir):
    """The bench's own estimator broken on purpose (`bench node --break trust-inputs`): it takes
    the check's forged sensor samples, and the check names it. How many of the three it answers
    before the run ends is a race (each forged fix makes it wait up to 2 s for a command of a step
    that never was, as long as the plant's command timeout here): one is enough to fail."""
    result = run_bench_cli("contract", "check", "estimator", "--steps", "8", "--command-timeout", "2",
                           "--runs-dir", str(runs_dir), "--run-id", "est-trust",
                           "--command", _bench_node_command("estimator", "--break trust-inputs"), timeout_s=240)
    assert result.returncode == 1, result.stdout + result.stderr
    assert re.search(r"acted on forged samples: [123] estimate\(s\) answer samples the check sent with a wrong tag "
                     r"\(seq 100000[012]\.\.\.\)", result.stdout), result.stdout
