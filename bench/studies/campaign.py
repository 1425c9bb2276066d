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
"""
from __future__ import annotations

import copy
import importlib
import itertools
import json
import os
import signal
import threading
import time
import tomllib
import zlib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Annotated, Callable, Iterable

import msgspec
import numpy as np

from bench.bus import toml_input
from bench.scenario import ScenarioError, load_scenario, parse_scenario, scenario_to_toml_dict

AXES = ("controllers", "dynamics", "knowledge", "initial_conditions", "faults")
CELL_COLUMNS = ("controller", "dynamics", "knowledge", "initial_conditions", "fault")
BUILTIN_PACKAGE = "bench.studies.campaigns"
# The case functions live with what they run (the in-process loop, the launcher), above this
# layer; they are found by name, as `bench.cli` finds subcommands.
RUNNERS = {"in-process": "bench.sim:campaign_case", "processes": "bench.launcher:campaign_case"}
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


@dataclass(frozen=True)
class Case:
    case_id: str
    index: int                      # position in the spec's expansion: the results file's order
    cell: dict                      # axis column -> value name
    seed: int
    scenario: dict                  # the full scenario, plain data
    mode: str
    timeout_s: float


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
# Running one case (in a worker)
# ------------------------------------------------------------------------------------------------
class CaseTimeout(BaseException):
    """Raised in the worker's main thread when a case overruns its wall-clock budget. A
    BaseException so that code under test catching Exception does not swallow it."""


def _runner(mode: str) -> Callable:
    """The case function (imported before the case's clock starts: imports take seconds)."""
    module, _, function = RUNNERS.get(mode, mode).partition(":")
    return getattr(importlib.import_module(module), function)


class _Alarm:
    """SIGALRM after timeout_s in the main thread (where pool and Ray workers run their tasks)."""

    def __init__(self, timeout_s: float):
        self.timeout_s = timeout_s
        self.armed = threading.current_thread() is threading.main_thread() and hasattr(signal, "setitimer")

    def _fire(self, _signum, _frame):
        raise CaseTimeout()

    def __enter__(self):
        if self.armed:
            self.previous = signal.signal(signal.SIGALRM, self._fire)
            signal.setitimer(signal.ITIMER_REAL, self.timeout_s)
        return self

    def __exit__(self, *exc):
        if self.armed:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, self.previous)
        return False


def run_case(case: Case) -> dict:
    """One row: the case's columns, its metrics or its error. Never raises for a case's failure."""
    row = {"case_id": case.case_id, "case_index": case.index, **case.cell, "seed": case.seed,
           "scenario_json": json.dumps(case.scenario, sort_keys=True), "status": "ok", "error": ""}
    start = time.perf_counter()
    try:
        runner = _runner(case.mode)
        scenario = parse_scenario(case.scenario, case.case_id)
        with _Alarm(case.timeout_s):
            row.update(runner(scenario))
    except CaseTimeout:
        row.update(status="timeout", error=f"timed out after {case.timeout_s:g} s")
    except Exception as exc:            # a case's failure is a row, whatever it was
        row.update(status="error", error=f"{type(exc).__name__}: {exc}")
    row["wall_time_s"] = time.perf_counter() - start
    return row


# ------------------------------------------------------------------------------------------------
# Results file
# ------------------------------------------------------------------------------------------------
def schema_for(spec):
    """The results file's columns for a spec: seed 001's metrics, or a fault campaign's."""
    if isinstance(spec, CampaignSpec):
        return _schema()
    return _spec_kind(spec).schema()


def _schema():
    import pyarrow as pa

    from bench.gnc.cwh import RendezvousParams
    from bench.studies.campaign_metrics import run_metrics

    sample = run_metrics(np.zeros((2, 6)), np.zeros((1, 3)), RendezvousParams.from_reference(), [0.0], [0], [True])
    types = {bool: pa.bool_(), int: pa.int64(), float: pa.float64()}
    fields = [("case_id", pa.string()), ("case_index", pa.int64())] + [(c, pa.string()) for c in CELL_COLUMNS]
    fields += [("seed", pa.int64()), ("status", pa.string()), ("error", pa.string())]
    fields += [(k, types[type(v)]) for k, v in sample.items()]
    fields += [("wall_time_s", pa.float64()), ("scenario_json", pa.string())]
    return pa.schema(fields)


def parts_dir(out: Path) -> Path:
    return out.with_name(out.name + ".parts")


class ResultsWriter:
    """Appends rows as numbered part files (written to a temporary name, then renamed)."""

    def __init__(self, out: Path, flush_every: int, flush_interval_s: float = 5.0, schema=None):
        self.out, self.dir = out, parts_dir(out)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.flush_every, self.flush_interval_s = max(1, flush_every), flush_interval_s
        self.pending: list[dict] = []
        self.last_flush = time.monotonic()
        self.schema = schema if schema is not None else _schema()
        self.next_part = 1 + max((int(p.stem.split("-")[1]) for p in self.dir.glob("part-*.parquet")), default=0)

    def add(self, row: dict) -> None:
        self.pending.append(row)
        if len(self.pending) >= self.flush_every or time.monotonic() - self.last_flush > self.flush_interval_s:
            self.flush()

    def flush(self) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        if not self.pending:
            return
        table = pa.Table.from_pylist(self.pending, schema=self.schema)
        final = self.dir / f"part-{self.next_part:06d}.parquet"
        tmp = final.with_suffix(".tmp")
        pq.write_table(table, tmp)
        os.replace(tmp, final)
        self.next_part += 1
        self.pending = []
        self.last_flush = time.monotonic()


def read_rows(out: Path) -> list[dict]:
    """Rows already in the results file and its parts (a later row of a case replaces an earlier)."""
    import pyarrow.parquet as pq

    rows: dict[str, dict] = {}
    sources = ([out] if out.is_file() else []) + sorted(parts_dir(out).glob("part-*.parquet"))
    for path in sources:
        for row in pq.read_table(path).to_pylist():
            rows[row["case_id"]] = row
    return list(rows.values())


def finalise(out: Path, case_order: dict[str, int] | None = None, schema=None) -> int:
    """Merge the parts into `out`, sorted by case order; remove the parts. Returns the row count."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    import shutil

    rows = read_rows(out)
    key = (lambda r: case_order.get(r["case_id"], len(case_order))) if case_order else (lambda r: r["case_index"])
    rows.sort(key=lambda r: (key(r), r["case_id"]))
    tmp = out.with_name(out.name + ".tmp")
    pq.write_table(pa.Table.from_pylist(rows, schema=schema if schema is not None else _schema()), tmp)
    os.replace(tmp, out)
    shutil.rmtree(parts_dir(out), ignore_errors=True)
    return len(rows)


# ------------------------------------------------------------------------------------------------
# Engines
# ------------------------------------------------------------------------------------------------
def _failed_row(case: Case, status: str, message: str) -> dict:
    return {"case_id": case.case_id, "case_index": case.index, **case.cell, "seed": case.seed,
            "scenario_json": json.dumps(case.scenario, sort_keys=True), "status": status, "error": message,
            "wall_time_s": float("nan")}


# A pool worker whose driver is gone (the kernel's parent-death signal missed: not Linux, or a
# worker stuck in C) notices within this and ends itself.
_PARENT_POLL_S = 0.5
# A worker asked to stop (SIGTERM) when the campaign is interrupted is killed after this.
_WORKER_STOP_S = 5.0
PR_SET_PDEATHSIG = 1          # linux/prctl.h


def _die_with_driver(driver_pid: int) -> None:
    """Pool worker initializer: the worker ends with the campaign command, however that ends.

    - Its own process group: Ctrl-C at a terminal signals the foreground group, which is then the
      command alone; the command stops the pool (one line, exit 130), no traceback per worker.
    - On Linux, SIGTERM from the kernel when the driver dies (prctl PR_SET_PDEATHSIG), also after
      SIGKILL; SIGTERM, not SIGKILL, so a `processes` case's launcher stops its nodes.
    - Everywhere, a thread that polls the parent pid, for where the signal is not available.
    The multiprocessing resource tracker ends by itself once no worker holds its pipe.
    """
    os.setpgid(0, 0)
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    except (OSError, AttributeError):
        pass                                    # not Linux: the thread below still notices
    if os.getppid() != driver_pid:              # the driver died before prctl took effect
        os._exit(1)
    threading.Thread(target=_watch_driver, args=(driver_pid,), name="watch-driver", daemon=True).start()


def _watch_driver(driver_pid: int) -> None:
    while os.getppid() == driver_pid:
        time.sleep(_PARENT_POLL_S)
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(_WORKER_STOP_S)
    os._exit(1)


def _stop_pool(pool) -> None:
    """Interrupted: cancel what has not started, stop the workers running a case (SIGTERM, then
    SIGKILL), without waiting for their cases. ProcessPoolExecutor has no public way to stop a
    running task; its worker processes are in `_processes`."""
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)     # a second Ctrl-C: no traceback
    try:
        processes = list((getattr(pool, "_processes", None) or {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            process.terminate()
        deadline = time.monotonic() + _WORKER_STOP_S
        for process in processes:
            process.join(max(0.0, deadline - time.monotonic()))
            if process.is_alive():
                process.kill()
                process.join(1.0)
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)


def run_local(cases: list[Case], workers: int, on_row: Callable[[dict], None]) -> None:
    """A local process pool (spawned workers: no state inherited from the driver), whose workers
    end with the driver (`_die_with_driver`) and are stopped when it is interrupted."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    if workers == 1:
        for case in cases:
            on_row(run_case(case))
        return
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_die_with_driver, initargs=(os.getpid(),))
    try:
        futures = {pool.submit(run_case, case): case for case in cases}
        for future in as_completed(futures):
            try:
                row = future.result()
            except Exception as exc:            # the worker process itself died (not the case)
                row = _failed_row(futures[future], "error", f"worker died: {type(exc).__name__}: {exc}")
            on_row(row)
    except BaseException:                       # Ctrl-C (KeyboardInterrupt), SIGTERM handlers, bugs
        _stop_pool(pool)
        raise
    pool.shutdown(wait=True)


# On this 24 GiB machine Ray would reserve 30 % of memory for its object store; a campaign passes
# a scenario dict in and a row of numbers out per task, so 256 MiB is plenty.
RAY_OBJECT_STORE_BYTES = 256 * 1024**2
RAY_WAIT_S = 0.5


def run_ray(cases: list[Case], workers: int, on_row: Callable[[dict], None], address: str | None) -> None:
    """Ray tasks, one per case. Connects to `address`, or to this process's running Ray, or
    starts a local one with `workers` CPUs (and shuts down only what it started)."""
    import ray

    started_here = False
    if not ray.is_initialized():
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            # address="local": a new cluster of our own, never one somebody else started on this host.
            ray.init(address="local", num_cpus=workers, object_store_memory=RAY_OBJECT_STORE_BYTES,
                     include_dashboard=False, log_to_driver=False)
        started_here = True
    pending: dict = {}
    try:
        # max_retries=0: a case that kills its worker is a failed row, not a silent re-run.
        remote_case = ray.remote(num_cpus=1, max_retries=0)(run_case)
        pending = {remote_case.remote(case): case for case in cases}
        while pending:
            # With a timeout: a ray.wait that blocks for a whole case never lets Python act on Ctrl-C.
            done, _ = ray.wait(list(pending), num_returns=1, timeout=RAY_WAIT_S)
            for ref in done:
                case = pending.pop(ref)
                try:
                    row = ray.get(ref)
                except Exception as exc:         # worker crash, node loss
                    row = _failed_row(case, "error", f"ray task failed: {type(exc).__name__}: {exc}")
                on_row(row)
    except BaseException:                # interrupted: stop the cases still running or queued
        for ref in pending:
            try:
                ray.cancel(ref, force=True)
            except Exception:            # noqa: BLE001 - already finished or its worker gone
                pass
        raise
    finally:
        if started_here:
            ray.shutdown()


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
