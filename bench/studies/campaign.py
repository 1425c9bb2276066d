"""Monte Carlo campaigns (seed 001): a grid of scenario variations times N seeds, one row per run.

A spec (TOML) names a base scenario and five axes; each axis value is a *scenario patch* (a table
merged into the base scenario), so any scenario field can be an axis:

    name = "seed001"
    base_scenario = "rendezvous_lqr"      # built-in name or TOML path
    seeds = 30                             # run.seed = first_seed .. first_seed + seeds - 1
    mode = "in-process"                    # or "processes" (a full `bench run` per case)
    [controllers.lqr]   controller = { type = "lqr" }
    [dynamics.cwh]      plant = { dynamics = "cwh" }
    [knowledge.truth]   estimator = { mode = "truth" }
    [initial_conditions.A]  plant = { initial_condition = "A" }
        sample_position_std_m = 500.0      # per-seed dispersion, drawn into plant.initial_state_m_mps
    [faults.none]

Keys starting with `sample_` are per-seed draws, not scenario fields: `sample_position_std_m`,
`sample_velocity_std_mps` (initial-state dispersion, Cartesian LVLH, common to every cell for a
given seed so cells are compared on the same draws) and `sample_radius_error_std` (the flight
side's believed orbit-radius error, onboard.believed_radius_error).

A case is named by its case id, every axis value and the seed in full
(`LQR/nonlinear/noisy_sensor_and_orbit/A/none/seed30`); errors and rows name it so. The scenario
name (at most 40 characters, the bench's name rule) is the campaign and the axis values that vary,
shortened with a hash of the whole id only where that is still too long; the scenario's
description carries the full case id.

Every case's scenario is expanded and validated before anything runs, and stored in its row
(`scenario_json`), so a row is re-run exactly with `bench run` on that JSON. A case runs in a
worker (local process pool by default, Ray with `engine="ray"`), under a wall-clock timeout; an
exception or a timeout is a row with status "error"/"timeout" and the message, never a lost case.

Rows are appended to `<out>.parts/` as small Parquet files while the campaign runs (atomically,
by rename), and merged into `<out>` in case order at the end: a killed campaign re-run with the
same output skips every case already in a part and produces the same file.

The parts: running the cases (campaign_engines.py: run_case, the local pool, Ray), the results
file (campaign_results.py).
"""
from __future__ import annotations

import copy
import importlib
import itertools
import os
import time
import tomllib
import zlib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Annotated, Iterable

import msgspec
import numpy as np

from bench.bus import toml_input
from bench.scenario import ScenarioError, load_scenario, parse_scenario, scenario_to_toml_dict
from bench.studies.campaign_engines import CELL_COLUMNS, RUNNERS, Case, run_local, run_ray
from bench.studies.campaign_results import ResultsWriter, finalise, read_rows, seed001_schema

AXES = ("controllers", "dynamics", "knowledge", "initial_conditions", "faults")
BUILTIN_PACKAGE = "bench.studies.campaigns"
MODES = tuple(RUNNERS)
# Other kinds of spec (a TOML's `kind`), each a module with parse_spec, expand and schema. Found by
# name, as the runners are: such a module builds on this one (cases, engines, results file).
SPEC_KINDS = {"attitude_faults": "bench.studies.fault_campaign"}


def _spec_kind(spec) -> object:
    """The module of a spec that is not seed 001's kind."""
    return importlib.import_module(SPEC_KINDS[spec.kind])


class CampaignError(ValueError):
    """A spec that cannot run, naming the field and the problem."""


class CampaignSpec(msgspec.Struct, forbid_unknown_fields=True):
    name: str
    controllers: dict[str, dict]
    dynamics: dict[str, dict]
    knowledge: dict[str, dict]
    initial_conditions: dict[str, dict]
    faults: dict[str, dict] = msgspec.field(default_factory=lambda: {"none": {}})
    description: str = ""
    base_scenario: str = "rendezvous_lqr"
    seeds: Annotated[int, msgspec.Meta(ge=1)] = 30
    first_seed: Annotated[int, msgspec.Meta(ge=0)] = 1
    # "in-process" (bench.sim), "processes" (bench run per case), or "package.module:function"
    # taking the scenario and returning a metrics dict (other loops, tests).
    mode: str = "in-process"
    steps: Annotated[int, msgspec.Meta(ge=1)] | None = None          # overrides run.steps
    case_timeout_s: Annotated[float, msgspec.Meta(gt=0)] = 900.0


# ------------------------------------------------------------------------------------------------
# Spec and expansion
# ------------------------------------------------------------------------------------------------
def builtin_specs() -> list[str]:
    root = resources.files(BUILTIN_PACKAGE)
    return sorted(p.name[: -len(".toml")] for p in root.iterdir() if p.name.endswith(".toml"))


def load_spec(name_or_path: str | Path) -> CampaignSpec:
    """A built-in spec by name (`seed001`) or a TOML file."""
    text_name = str(name_or_path)
    path = Path(text_name)
    if path.suffix == ".toml" or path.exists():
        if not path.is_file():
            raise CampaignError(f"campaign spec {text_name!r} does not exist")
        text, source = path.read_text(), str(path)
    elif text_name in builtin_specs():
        text, source = resources.files(BUILTIN_PACKAGE).joinpath(f"{text_name}.toml").read_text(), f"built-in {text_name!r}"
    else:
        raise CampaignError(f"no campaign spec file or built-in named {text_name!r} (built-ins: {', '.join(builtin_specs())})")
    try:
        data = tomllib.loads(text)
    except ValueError as exc:     # TOMLDecodeError (a key given twice too), or an integer too long to convert
        raise CampaignError(f"{source}: {toml_input.field(exc, text)}: {toml_input.problem(exc)}") from None
    if "kind" in data:
        if data["kind"] not in SPEC_KINDS:
            raise CampaignError(f"{source}: kind: {data['kind']!r} is not one of {', '.join(SPEC_KINDS)}")
        return importlib.import_module(SPEC_KINDS[data["kind"]]).parse_spec(data, source)
    return parse_spec(data, source)


def parse_spec(data: dict, source: str = "<spec>") -> CampaignSpec:
    try:
        spec = msgspec.convert(data, CampaignSpec)
    except msgspec.ValidationError as exc:
        raise CampaignError(f"{source}: {exc}") from None
    for axis in AXES:
        if not getattr(spec, axis):
            raise CampaignError(f"{source}: {axis}: needs at least one entry")
        for name in getattr(spec, axis):
            # Case ids join the names with '/': a name holding one would make two cases one id.
            if not name.strip() or "/" in name:
                raise CampaignError(f"{source}: {axis}.{name!r}: a name must be non-empty and without '/'")
    if spec.mode not in MODES and ":" not in spec.mode:
        raise CampaignError(f"{source}: mode: {spec.mode!r} is not one of {', '.join(MODES)} or 'package.module:function'")
    return spec


def _merge(base: dict, patch: dict) -> dict:
    """Deep merge of plain data: tables merge, everything else replaces."""
    out = copy.deepcopy(base)
    for key, value in patch.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def _stream(seed: int, label: str) -> np.random.Generator:
    """An independent generator per (seed, what is drawn): same draws whatever else the grid holds."""
    return np.random.default_rng([seed, zlib.crc32(label.encode())])


_SAMPLE_KEYS = {"sample_position_std_m", "sample_velocity_std_mps", "sample_radius_error_std"}


def _apply_samples(scenario: dict, samples: dict, seed: int, axis_value: str, source: str) -> dict:
    unknown = set(samples) - _SAMPLE_KEYS
    if unknown:
        raise CampaignError(f"{axis_value}: unknown per-seed draw(s) {', '.join(sorted(unknown))} "
                            f"(known: {', '.join(sorted(_SAMPLE_KEYS))})")
    position_std = float(samples.get("sample_position_std_m", 0.0))
    velocity_std = float(samples.get("sample_velocity_std_mps", 0.0))
    if position_std or velocity_std:
        parsed = parse_scenario(scenario, source)
        x0 = parsed.initial_state_m_mps()
        # Drawn per seed and initial-condition set only: every cell sees the same dispersed states.
        rng = _stream(seed, f"initial_state/{axis_value}")
        x0 = x0 + np.concatenate([position_std * rng.standard_normal(3), velocity_std * rng.standard_normal(3)])
        scenario = _merge(scenario, {"plant": {"initial_state_m_mps": [float(v) for v in x0]}})
    radius_std = float(samples.get("sample_radius_error_std", 0.0))
    if radius_std:
        rng = _stream(seed, "believed_radius_error")
        error = float(np.clip(radius_std * rng.standard_normal(), -0.2, 0.2))
        scenario = _merge(scenario, {"onboard": {"believed_radius_error": error}})
    return scenario


def expand(spec) -> list[Case]:
    """Every case of the grid, validated, in a fixed order (axes in spec order, seeds innermost)."""
    if not isinstance(spec, CampaignSpec):              # another kind (SPEC_KINDS)
        return _spec_kind(spec).expand(spec)
    base = scenario_to_toml_dict(load_scenario(spec.base_scenario))
    if spec.steps is not None:
        base = _merge(base, {"run": {"steps": spec.steps}})
    cases = []
    axes = [list(getattr(spec, axis).items()) for axis in AXES]
    # Axes with one value say nothing about which case a scenario is: left out of its name.
    varying = [len(values) > 1 for values in axes]
    for combo in itertools.product(*axes):
        cell = {column: name for column, (name, _) in zip(CELL_COLUMNS, combo)}
        for seed in range(spec.first_seed, spec.first_seed + spec.seeds):
            scenario = base
            samples: dict[str, tuple[dict, str]] = {}
            for axis, (name, patch) in zip(AXES, combo):
                fields = {k: v for k, v in patch.items() if not k.startswith("sample_")}
                draws = {k: v for k, v in patch.items() if k.startswith("sample_")}
                scenario = _merge(scenario, fields)
                if draws:
                    samples[axis] = (draws, name)
            case_id = "/".join([*cell.values(), f"seed{seed}"])
            label = [name for name, varies in zip(cell.values(), varying) if varies] + [f"s{seed}"]
            scenario = _merge(scenario, {"name": scenario_name(spec.name, label), "run": {"seed": seed},
                                         "description": f"campaign {spec.name}, case {case_id}"})
            source = f"case {case_id}"
            try:
                # Draws go last: the initial condition set's base state may come from any patch.
                for axis, (draws, name) in samples.items():
                    scenario = _apply_samples(scenario, draws, seed, f"{axis}.{name}", source)
                scenario = scenario_to_toml_dict(parse_scenario(scenario, source))
            except ScenarioError as exc:
                raise CampaignError(str(exc)) from None
            cases.append(Case(case_id, len(cases), cell, seed, scenario, spec.mode, spec.case_timeout_s))
    names: dict[str, str] = {}
    for case in cases:
        other = names.setdefault(case.scenario["name"], case.case_id)
        if other != case.case_id:       # a hash collision: never seen, but a clash would mix run directories
            raise CampaignError(f"cases {other} and {case.case_id} get the same scenario name {case.scenario['name']!r}")
    return cases


# ------------------------------------------------------------------------------------------------
# Results file
# ------------------------------------------------------------------------------------------------
def schema_for(spec):
    """The results file's columns for a spec: seed 001's metrics, or a fault campaign's."""
    if isinstance(spec, CampaignSpec):
        return seed001_schema()
    return _spec_kind(spec).schema()


# ------------------------------------------------------------------------------------------------
# The campaign
# ------------------------------------------------------------------------------------------------
@dataclass
class CampaignOutcome:
    total: int
    skipped: int
    ran: int
    failed: int
    wall_s: float

    @property
    def runs_per_s(self) -> float:
        return self.ran / self.wall_s if self.wall_s > 0 else float("nan")


def run_campaign(spec: CampaignSpec, out: Path, *, engine: str = "local", workers: int | None = None,
                 address: str | None = None, show_progress: bool = True, flush_every: int = 16,
                 retry_failed: bool = False, cases: Iterable[Case] | None = None) -> CampaignOutcome:
    out = Path(out)
    if engine not in ("local", "ray"):
        raise CampaignError(f"engine must be 'local' or 'ray', got {engine!r}")
    workers = workers or max(1, os.cpu_count() or 1)
    if workers < 1:
        raise CampaignError(f"workers must be >= 1, got {workers}")
    cases = list(cases) if cases is not None else expand(spec)
    done = {r["case_id"]: r["status"] for r in read_rows(out)}
    todo = [c for c in cases if c.case_id not in done or (retry_failed and done[c.case_id] != "ok")]
    # Seed-major order: a campaign stopped early has the same number of seeds in every cell.
    todo.sort(key=lambda c: (c.seed, c.index))
    out.parent.mkdir(parents=True, exist_ok=True)
    schema = schema_for(spec)
    writer = ResultsWriter(out, flush_every, schema=schema)
    failed = 0
    start = time.monotonic()
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    columns = [TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
               TextColumn("{task.fields[rate]} runs/s"), TextColumn("{task.fields[failed]} failed"),
               TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn()]
    with Progress(*columns, disable=not show_progress) as progress:
        task = progress.add_task(spec.name, total=len(todo), rate="-", failed=0)

        def on_row(row: dict) -> None:
            nonlocal failed
            writer.add(row)
            failed += row["status"] != "ok"
            elapsed = time.monotonic() - start
            completed = progress.tasks[0].completed + 1
            progress.update(task, advance=1, rate=f"{completed / elapsed:.2f}", failed=failed)

        try:
            if engine == "local":
                run_local(todo, workers, on_row)
            else:
                run_ray(todo, workers, on_row, address)
        finally:
            writer.flush()
    wall_s = time.monotonic() - start
    finalise(out, {c.case_id: c.index for c in cases}, schema)
    return CampaignOutcome(len(cases), len(cases) - len(todo), len(todo), failed, wall_s)


def scenario_name(campaign: str, label: list[str]) -> str:
    """A scenario name for one case that passes the bench's name rule ([A-Za-z0-9_.-], at most 40
    characters): the campaign and `label` (the varying axis values and s<seed>) joined by '.';
    without the campaign where that is too long; shortened with a hash of the whole where even
    the label is. The full case id is in the case's `case_id` and the scenario's description."""
    import hashlib
    import re

    def clean(text: str) -> str:
        return re.sub(r"[^A-Za-z0-9_.-]", ".", text)

    full = clean(".".join([campaign, *label]))
    name = full
    if len(name) > 40:
        name = clean(".".join(label))
    if len(name) > 40:
        name = f"{name[:31]}-{hashlib.sha1(full.encode()).hexdigest()[:8]}"
    return name if name[0].isalnum() else f"c{name[1:]}"
