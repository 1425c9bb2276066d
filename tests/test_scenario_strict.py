"""Strict scenario and deployment input (issue 26): every number in the schema bounded, no type
coercion, nesting refused by the parser naming the key, the issue's four inputs through a real
`bench run`, deployment files naming the field, and the launcher naming the process that failed.
The generated cases are in test_scenario_fuzz.py (hypothesis)."""
from __future__ import annotations

import re
import signal

import msgspec.inspect as mi
import pytest

from bench.bus.deployment import DeploymentError, load_deployment
from bench.launcher import Child, NodeFailed, RunInterrupted, SignalGuard, _check_children, _wait_alive
from bench.plant.divergence import EXIT_DIVERGED
from bench.scenario import MAX_NESTING, Scenario, ScenarioError, load_scenario, parse_scenario
from conftest import bench_processes, run_bench_cli

# Issue 26: four closing quotes, then 600 nested arrays on the same line. The text scan this replaced
# thought the rest of the line was inside a string; tomllib ran out of recursion, naming no field.
QUOTES_THEN_DEEP = 'name = "x"\nz = ["""a"""", ' + "[" * 600 + "]" * 600 + "]\n"


# --- the schema, walked -----------------------------------------------------------------------
# Numbers the schema leaves to a check of their own, with the reason.
CHECKED_ELSEWHERE = {
    ".can.faults[].params{}": "each fault parameter has its own range (bench.bus.can.faults.Param.check)",
    ".attitude_control.dipole_limit_am2": "positive: the scenario's own message (bench.scenario._check_attitude)",
    ".can.security.key_hex": "a 16-byte hexadecimal key, checked in SecurityConfig (and the file is at most 1 MiB)",
}


def unbounded(t, path, out):
    def lower_upper(info):
        low = info.ge if info.ge is not None else info.gt
        high = info.le if info.le is not None else info.lt
        return low, high

    if isinstance(t, mi.StructType):
        for f in t.fields:
            unbounded(f.type, f"{path}.{f.name}", out)
    elif isinstance(t, mi.UnionType):
        for member in t.types:
            unbounded(member, path, out)
    elif isinstance(t, mi.ListType):
        if t.max_length is None:
            out.append(f"{path} (list without max_length)")
        unbounded(t.item_type, path + "[]", out)
    elif isinstance(t, mi.DictType):
        if t.max_length is None:
            out.append(f"{path} (dict without max_length)")
        unbounded(t.value_type, path + "{}", out)
    elif isinstance(t, (mi.IntType, mi.FloatType)):
        low, high = lower_upper(t)
        if (low is None or high is None) and path not in CHECKED_ELSEWHERE:
            out.append(f"{path} ({type(t).__name__} in [{low}, {high}])")
    elif isinstance(t, mi.StrType) and t.max_length is None and t.pattern is None and path not in CHECKED_ELSEWHERE:
        out.append(f"{path} (str without max_length)")


def test_every_number_and_list_in_the_schema_is_bounded():
    found = []
    unbounded(mi.type_info(Scenario), "", found)
    assert found == [], "unbounded scenario fields: " + ", ".join(found)


# --- the issue's inputs, one by one -------------------------------------------------------------
ISSUE_INPUTS = {
    "string steps": ('name = "x"\n[run]\nsteps = "20"\n', "run.steps"),
    "fault start 1e300": ('name = "x"\n[can]\n[[can.faults]]\nname = "drop"\nstart_s = 1e300\n', "can.faults[0].start_s"),
    "count 1e20": ('name = "x"\n[can]\n[[can.faults]]\nname = "drop"\ncount = 100000000000000000000\n',
                   "can.faults[0].count"),
    "quotes then 600 brackets": (QUOTES_THEN_DEEP, "z: nested deeper"),
}


@pytest.mark.parametrize("case", sorted(ISSUE_INPUTS))
def test_issue_26_inputs_exit_2_naming_the_field(tmp_path, runs_dir, case):
    text, field = ISSUE_INPUTS[case]
    path = tmp_path / "bad.toml"
    path.write_text(text)
    run_id = "strict-" + "".join(c if c.isalnum() else "-" for c in case)
    result = run_bench_cli("run", str(path), "--run-id", run_id, "--runs-dir", str(runs_dir), "--no-progress")
    assert result.returncode == 2, result.stderr + result.stdout
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and field in lines[0], result.stderr
    assert "Traceback" not in result.stderr + result.stdout
    assert not runs_dir.exists() and bench_processes(run_id) == []


def test_strict_types():
    base = {"name": "x"}
    for section, key, value in [("run", "steps", "20"), ("run", "steps", True), ("run", "steps", 20.0),
                                ("run", "time_factor", "1.5"), ("plant", "mass_kg", "1e3")]:
        with pytest.raises(ScenarioError, match=rf"{section}\.{key}: Expected"):
            parse_scenario(base | {section: {key: value}})
    # An integer is a float.
    assert parse_scenario(base | {"run": {"time_factor": 2}}).run.time_factor == 2.0


def test_nesting_is_refused_naming_the_key(tmp_path):
    for text, where in [('name = "x"\n[run]\nq = ' + "[" * 40 + "]" * 40 + "\n", "run.q" + "[0]" * (MAX_NESTING - 2) + ": nested deeper"),
                        ('name = "x"\n[run]\nq = ' + "[" * 5000 + "\n", "run.q: nested deeper"),
                        ('name = "x"\na = ' + "{b = " * 600 + "\n", "a: nested deeper")]:
        path = tmp_path / "deep.toml"
        path.write_text(text)
        with pytest.raises(ScenarioError, match=re.escape(where)):
            load_scenario(path)


# --- deployment files ---------------------------------------------------------------------------
GOOD_DEPLOYMENT = 'name = "lab"\nlauncher = "sim"\n[hosts.sim]\nendpoints = ["tcp/127.0.0.1:7447"]\nnodes = ["plant"]\n'


@pytest.mark.parametrize("text, field", [
    (GOOD_DEPLOYMENT.replace("7447", "9" * 5000), "hosts.sim.endpoints[0]: Expected `str` of length <= 256"),
    (GOOD_DEPLOYMENT.replace("7447", "9" * 200), "hosts.sim.endpoints: 'tcp/127.0.0.1:999"),
    (GOOD_DEPLOYMENT.replace("7447", "\u0663\u0663"), "hosts.sim.endpoints"),     # Arabic-Indic digits
    (GOOD_DEPLOYMENT.replace('"lab"', "7"), "name: Expected `str`"),
    (GOOD_DEPLOYMENT.replace('nodes = ["plant"]', 'nodes = "plant"'), "hosts.sim.nodes: Expected `array`"),
    (GOOD_DEPLOYMENT.replace("launcher", 'secure = "yes"\nlauncher'), "secure: Expected `bool"),
    (GOOD_DEPLOYMENT + "colour = 1\n", "hosts.sim: Object contains unknown field `colour`"),
    (GOOD_DEPLOYMENT.replace('nodes = ["plant"]', "nodes = " + "[" * 600), "nested deeper"),
    (GOOD_DEPLOYMENT.replace('nodes = ["plant"]', "nodes = " + "[" * 20 + "]" * 20), "nested deeper"),
    (GOOD_DEPLOYMENT + "".join(f'[hosts.h{i}]\nendpoints = ["tcp/127.0.0.1:0"]\n' for i in range(70)), "hosts: Expected `object` of length <= 64"),
    (GOOD_DEPLOYMENT + "\"a\\nb\" = 1\n", "a\\nb"),
])
def test_bad_deployment_files_name_the_field(tmp_path, text, field):
    path = tmp_path / "deploy.toml"
    path.write_text(text)
    with pytest.raises(DeploymentError) as refused:
        load_deployment(path)
    message = str(refused.value)
    assert "\n" not in message and field in message, message


# --- who died ---------------------------------------------------------------------------------
class Exited:
    def __init__(self, code: int | None, pid: int):
        self.returncode, self.pid = code, pid

    def poll(self):
        return self.returncode


def test_the_process_that_failed_is_named(tmp_path):
    # The plant ended cleanly after the controller died, both seen by the same poll (start order
    # puts the plant first); nobody is allowed to be done here.
    children = [Child("plant", Exited(0, 10), tmp_path / "plant.log"),
                Child("controller", Exited(1, 11), tmp_path / "controller.log"),
                Child("estimator", Exited(None, 12), tmp_path / "estimator.log")]
    with pytest.raises(NodeFailed, match=r"^process 'controller' \(pid 11\) exited with code 1"):
        _check_children(children, allowed_done=set())
    with pytest.raises(NodeFailed, match=r"^process 'plant' \(pid 10\) exited with code 0"):
        _check_children(children[:1] + children[2:], allowed_done=set())


class NoTokensYet:
    """A presence query that no node has answered yet (as through a router, where the answers can
    come after a 20-step run has ended)."""

    refused_by_name: dict = {}

    def ask(self, names="*", timeout_s=0.5):
        return {}


def test_a_plant_that_ended_cleanly_during_start_up_ran_the_loop(tmp_path):
    # The plant steps only once it has seen every peer's token: its clean exit is a finished run,
    # not a node that died while the others were starting.
    children = [Child("plant", Exited(0, 10), tmp_path / "plant.log"),
                Child("controller", Exited(None, 11), tmp_path / "controller.log")]
    _wait_alive(NoTokensYet(), children, timeout_s=0.2)
    # A node that failed is still named, whatever the plant did.
    children[1] = Child("controller", Exited(1, 11), tmp_path / "controller.log")
    with pytest.raises(NodeFailed, match=r"^process 'controller' \(pid 11\) exited with code 1"):
        _wait_alive(NoTokensYet(), children, timeout_s=0.2)
    # A plant that stopped on divergence during start-up (CI97: step 4, 36 ms after its peers were
    # ready) is left to _follow_run, which names the divergence; a node that failed still comes first.
    children = [Child("plant", Exited(EXIT_DIVERGED, 10), tmp_path / "plant.log"),
                Child("controller", Exited(None, 11), tmp_path / "controller.log")]
    _wait_alive(NoTokensYet(), children, timeout_s=0.2)
    children[1] = Child("controller", Exited(1, 11), tmp_path / "controller.log")
    with pytest.raises(NodeFailed, match=r"^process 'controller' \(pid 11\) exited with code 1"):
        _wait_alive(NoTokensYet(), children, timeout_s=0.2)
    # Any other node that ends during start-up has failed, even cleanly.
    children = [Child("plant", Exited(None, 10), tmp_path / "plant.log"),
                Child("controller", Exited(0, 11), tmp_path / "controller.log")]
    with pytest.raises(NodeFailed, match=r"^process 'controller' \(pid 11\) exited with code 0"):
        _wait_alive(NoTokensYet(), children, timeout_s=0.2)


def test_the_start_up_wait_delivers_a_signal_whose_exception_was_dropped(tmp_path):
    """A SIGINT whose RunInterrupted Python dropped (raised inside a weakref callback: CI105, the
    run went on for its 2000 steps) ends the wait for the nodes at its next look."""
    children = [Child("plant", Exited(None, 10), tmp_path / "plant.log"),
                Child("controller", Exited(None, 11), tmp_path / "controller.log")]
    guard = SignalGuard(group=None)
    guard.first = signal.SIGINT          # what the handler leaves when its exception is dropped
    with pytest.raises(RunInterrupted):
        _wait_alive(NoTokensYet(), children, timeout_s=60.0, interrupted=guard.check)
