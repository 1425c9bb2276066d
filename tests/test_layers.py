"""The package's import layers: no cycles, and no arrow from a lower layer up to a higher one.

LAYERS below is the one place the layering is written down. Each rank is a list of groups; a
module may import its own group and any group of a lower rank, never a group of its own rank
(plant and estimator are peers: neither reads the other) or of a higher one. Every import counts,
also one inside a function: a lazy import is still a dependency. `bench.cli` finds subcommands
and `bench.runtime.node.NODES` finds nodes by module name (strings), so those are not arrows.
"""
from __future__ import annotations

import ast
import fnmatch
from pathlib import Path

import pytest

import bench

# Lowest rank first. Group -> patterns (fnmatch on dotted module names); a module belongs to the
# first group, in this order, with a matching pattern.
LAYERS: list[dict[str, list[str]]] = [
    {"data": ["bench", "bench.data"]},                     # reference numbers (TOML)
    {"gnc": ["bench.gnc", "bench.gnc.*"]},                # pure algorithms and models
    {"bus": ["bench.bus", "bench.bus.*"]},                # Zenoh session, messages, CAN
    # The section schema each part owns (bench/config/<part>.py): plain data, below the scenario
    # that loads them from TOML.
    {"config": ["bench.config", "bench.config.*"]},
    # The scenario: below every process so each part can read the scenario it runs.
    {"scenario": ["bench.scenario", "bench.scenarios", "bench.criteria"]},
    {"runtime": ["bench.runtime", "bench.runtime.*"]},    # node context, process start, deadlines
    {"plant": ["bench.plant", "bench.plant.*"],           # the processes that only know the bus
     "estimator": ["bench.estimator", "bench.estimator.*"],
     "recorder": ["bench.recorder", "bench.recorder_intake"]},
    {"controller": ["bench.controller", "bench.controller.*"]},
    # The planner plans for the flight side: it reads the controller's beliefs and replan rule.
    {"planner": ["bench.planner", "bench.planner.*"]},
    {"studies": ["bench.studies", "bench.studies.*"],     # seed 003 studies, campaigns
     # Live operation (issue 48): the Foxglove server node reads the recorder's schemas and the flight
     # side's target; `bench inject` only the bus. The launcher starts the node and prints its URL.
     "live": ["bench.live", "bench.live.*"]},
    {"report": ["bench.report", "bench.report.*"]},
    # The message contract as text: the key table, the fields' meanings, contract.json and the
    # export, which the launcher writes beside each run (it describes every part, so it sits above them).
    {"contract": ["bench.contract", "bench.contract.*"]},
    {"sim": ["bench.sim"],                                # the whole loop in one process
     "launcher": ["bench.launcher", "bench.launcher.*"]},  # `bench run`: one concern a module
    # The contract's check: it runs the bench (the launcher) against an outside node.
    {"contract_check": ["bench.contract_check", "bench.contract_check.*"]},
    {"cli": ["bench.cli", "bench.__main__"]},
]


# --- the checker (generic: the tests below also run it on a synthetic package) -----------------
def module_names(root: Path, package: str) -> dict[str, Path]:
    """Dotted name -> file of every module under the package directory `root`."""
    names = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        names[".".join([package, *parts])] = path
    return names


def import_graph(root: Path, package: str) -> dict[str, set[str]]:
    """Module -> the package's modules it imports (anywhere in the file)."""
    modules = module_names(root, package)

    def resolve(name: str) -> str | None:
        while name and name not in modules:       # `from a.b import c` where c is a name in a.b
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        is_package = path.name == "__init__.py"
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                candidates = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = name if is_package else name.rpartition(".")[0]
                    for _ in range(node.level - 1):
                        anchor = anchor.rpartition(".")[0]
                    base = f"{anchor}.{base}" if base else anchor
                candidates = [f"{base}.{a.name}" for a in node.names]
            else:
                continue
            for candidate in candidates:
                if candidate == package or candidate.startswith(package + "."):
                    target = resolve(candidate)
                    if target and target != name:
                        targets.add(target)
        graph[name] = targets
    return graph


def layer_of(module: str, layers: list[dict[str, list[str]]]) -> tuple[int, str] | None:
    for rank, groups in enumerate(layers):
        for group, patterns in groups.items():
            if any(fnmatch.fnmatchcase(module, p) for p in patterns):
                return rank, group
    return None


def unplaced(graph: dict[str, set[str]], layers) -> list[str]:
    return sorted(m for m in graph if layer_of(m, layers) is None)


def upward_imports(graph: dict[str, set[str]], layers) -> list[str]:
    """Every import of a group of the same or a higher rank than the importer's own group."""
    bad = []
    for module, targets in sorted(graph.items()):
        here = layer_of(module, layers)
        for target in sorted(targets):
            there = layer_of(target, layers)
            if here is None or there is None or there[1] == here[1] or there[0] < here[0]:
                continue
            bad.append(f"{module} ({here[1]}) imports {target} ({there[1]})")
    return bad


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


# --- the bench ---------------------------------------------------------------------------------
BENCH = import_graph(Path(bench.__file__).parent, "bench")


def test_the_graph_sees_the_bench():
    # A checker that reads nothing passes everything: make sure it reads real arrows.
    assert "bench.gnc.cwh" in BENCH["bench.controller.factory"]
    assert "bench.runtime.deadline" in BENCH["bench.plant.stepping"]
    assert "bench.bus.can.protocol" in BENCH["bench.bus.can.board"]      # `from bench.bus.can import protocol`
    # The scenario reads each part's section schema; the launcher is a package, one concern a module.
    assert {"bench.config.controller", "bench.config.plant", "bench.bus.can.config"} <= BENCH["bench.scenario"]
    assert {"bench.launcher.children", "bench.launcher.follow"} <= BENCH["bench.launcher.run"]


def test_every_module_has_a_layer():
    assert unplaced(BENCH, LAYERS) == [], "add the module to LAYERS in tests/test_layers.py"


def test_no_module_imports_a_peer_or_a_higher_layer():
    assert upward_imports(BENCH, LAYERS) == []


def test_no_import_cycles():
    assert cycles(BENCH) == []


# --- the checker catches what it is for --------------------------------------------------------
def _package(tmp_path: Path, files: dict[str, str]) -> dict[str, set[str]]:
    root = tmp_path / "fake"
    for relative, text in {"__init__.py": "", **files}.items():
        path = root / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return import_graph(root, "fake")


FAKE_LAYERS = [
    {"gnc": ["fake", "fake.gnc", "fake.gnc.*"]},
    {"plant": ["fake.plant", "fake.plant.*"], "estimator": ["fake.estimator", "fake.estimator.*"]},
    {"controller": ["fake.controller", "fake.controller.*"]},
]


def test_checker_flags_a_lower_layer_importing_a_higher_one(tmp_path):
    graph = _package(tmp_path, {
        "gnc/__init__.py": "",
        "gnc/lqr.py": "def dlqr():\n    from fake.controller.node import run  # lazy still counts\n",
        "controller/__init__.py": "",
        "controller/node.py": "from fake.gnc import lqr\n\ndef run():\n    pass\n",
    })
    assert graph["fake.controller.node"] == {"fake.gnc.lqr"}
    assert upward_imports(graph, FAKE_LAYERS) == ["fake.gnc.lqr (gnc) imports fake.controller.node (controller)"]
    assert cycles(graph) == [["fake.controller.node", "fake.gnc.lqr"]]


def test_checker_flags_peers_and_relative_imports(tmp_path):
    graph = _package(tmp_path, {
        "plant/__init__.py": "",
        "plant/model.py": "from ..estimator import kalman\nfrom . import sensors\n",
        "plant/sensors.py": "",
        "estimator/__init__.py": "",
        "estimator/kalman.py": "",
        "planner.py": "",
    })
    assert graph["fake.plant.model"] == {"fake.estimator.kalman", "fake.plant.sensors"}
    assert upward_imports(graph, FAKE_LAYERS) == ["fake.plant.model (plant) imports fake.estimator.kalman (estimator)"]
    assert unplaced(graph, FAKE_LAYERS) == ["fake.planner"]


@pytest.mark.parametrize("module", ["bench.config.plant", "bench.bus.can.config", "bench.gnc.mpc"])
def test_layer_map_places_part_schemas_as_documented(module):
    # Part schemas sit in bench.config, a layer below the scenario; the bus's own sits with the bus.
    expected = {"bench.config.plant": "config", "bench.bus.can.config": "bus", "bench.gnc.mpc": "gnc"}
    assert layer_of(module, LAYERS)[1] == expected[module]


@pytest.mark.parametrize("module", ["bench.config.controller", "bench.config.estimator", "bench.config.plant"])
def test_part_schemas_sit_below_the_scenario(module):
    assert module in BENCH
    assert layer_of(module, LAYERS)[0] < layer_of("bench.scenario", LAYERS)[0]


@pytest.mark.parametrize("module, group", [("bench.scenario", "scenario"), ("bench.config.controller", "config"),
                                           ("bench.launcher", "launcher"), ("bench.launcher.run", "launcher"),
                                           ("bench.launcher.stats", "launcher")])
def test_layer_map_places_the_scenario_and_the_launcher_package(module, group):
    # Every module of the launcher package sits in the launcher's layer (not unplaced, not a lower one).
    assert module in BENCH
    assert layer_of(module, LAYERS)[1] == group
