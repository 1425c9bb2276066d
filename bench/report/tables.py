"""A run's results as tables: steps.parquet (one row per step) and can_frames.parquet (one row per frame).

`pandas.read_parquet(run_dir / "steps.parquet")` gives one row per step with one named column per
component, the unit at the end of each name and in the schema (field metadata "unit", and the
table's "bench" metadata with every column's unit and source array):

- Row k is step k of the plant: `t_s` (simulated time of the step's start), the state at t_k, and
  what acted over [t_k, t_k+1) with its stamps. The rendezvous plant keeps the state after its last
  step too (N+1 states for N commands): that state is one more row, whose per-step columns are
  empty (NaN for floats, -1 for integer stamps). The attitude plant keeps N of each: N rows.
- Names: `state_m_mps` -> x_m, y_m, z_m, vx_mps, vy_mps, vz_mps; `att_q_wxyz` -> q_w .. q_z; an
  (N, 3) array `<what>_<unit>` -> `<what>_x_<unit>` .. `<what>_z_<unit>` (`att_omega_radps` ->
  omega_x_radps); the `att_` prefix goes (every row is the plant's); `att_time_s` is `t_s`; tesla
  is `_T` (`att_field_body_t` -> field_body_x_T).
- Stamps `stamp_<stage>_ns` stay integers (monotonic ns, exact) with -1 where the stage is absent,
  as in trajectory.npz. The plant sizes its stamp arrays for the scenario's steps: a partial run's
  rows stop at the steps it ran.
- Per-run numbers of trajectory.npz (0-d arrays such as plant_missed_steps) go into the metadata
  ("run"), and arrays that are not per step (`mtq_*`: one row per board report) are left out and
  named there ("left_out").

`can_frames.parquet`, when the run has a can.log (candump capture of the bus model): one row per
captured frame, with its capture time (`timestamp_s`, the capture's own stamp, s), channel, id,
flags, data in hex, DBC name, direction (DBC sender -> receivers, "OBC->MTQ" is the flight side to
the board), whether it decodes as a frame of the protocol, its E2E CRC verdict, and its signals as
JSON text. Its times, named by their clock (the table's "bench" metadata `time_columns` says so too):
- `sim_time_s`: the run's simulated time of the frame (the time base of steps.parquet's `t_s`),
  monotone, clipped to the run's span [first t_s, last t_s + one step]: the board's boot frames come before
  step 0 and its safe-state frames after the last step (`in_run` says which frames are inside);
- `step`: the row of steps.parquet the frame falls in (the last step with t_s <= sim_time_s), to
  join the two tables on;
- `wall_time_s`: the wall clock (Unix epoch s) at which the bus model passed the frame, NaN where
  the bus ran on simulated time (lock-step with bus faults: there the capture stamp is bus time,
  simulated time + 1000 s, and no frame has a wall time);
- `timestamp_s`: candump's stamp as written in can.log (one of the two above, by the bus's clock).
"""
from __future__ import annotations

import json
from pathlib import Path

import can
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from bench.bus.can import protocol as can_protocol
from bench.recorder import can_frame_signals
from bench.scenario import ScenarioError, load_scenario

STEPS_FILE = "steps.parquet"
CAN_FRAMES_FILE = "can_frames.parquet"
TRAJECTORY_FILE = "trajectory.npz"
CAN_LOG_FILE = "can.log"
METADATA_KEY = b"bench"

TIME_ARRAYS = ("t_s", "att_time_s")        # the step times of the rendezvous and attitude plants
NOT_PER_STEP_PREFIXES = ("mtq_",)           # the board's reports: one row per report, not per step
DROPPED_PREFIX = "att_"
ABSENT_INT = -1                             # trajectory.npz's mark of an absent stamp or counter
# Unit suffixes of the bench's names (README: names carry their units) and what they mean.
UNITS = {"s": "s", "ns": "ns", "m": "m", "mps": "m/s", "n": "N", "nm": "N m", "am2": "A m^2",
         "radps": "rad/s", "t": "T", "a": "A"}
# A unit written otherwise in a column's name than in the bench's array names: tesla is T (`_t`
# reads as time).
COLUMN_SUFFIX = {"t": "T"}
SPECIAL_COMPONENTS = {
    "state_m_mps": (("x_m", "m"), ("y_m", "m"), ("z_m", "m"), ("vx_mps", "m/s"), ("vy_mps", "m/s"), ("vz_mps", "m/s")),
    "att_q_wxyz": (("q_w", "1"), ("q_x", "1"), ("q_y", "1"), ("q_z", "1")),
}
AXES = ("x", "y", "z")


class TableError(ValueError):
    """trajectory.npz is not a table of steps (no time array, or arrays that cannot be rows)."""


def write_tables(run_dir: str | Path) -> list[Path]:
    """steps.parquet from trajectory.npz and can_frames.parquet from can.log, those that the run
    has the source of; returns the paths written."""
    run_dir = Path(run_dir)
    written = []
    arrays: dict[str, np.ndarray] = {}
    if (run_dir / TRAJECTORY_FILE).is_file():
        with np.load(run_dir / TRAJECTORY_FILE) as npz:
            arrays = {k: npz[k] for k in npz.files}
        pq.write_table(steps_table(arrays), run_dir / STEPS_FILE)
        written.append(run_dir / STEPS_FILE)
    if (run_dir / CAN_LOG_FILE).is_file():
        table = can_frames_table(run_dir / CAN_LOG_FILE, _protocol(run_dir))
        pq.write_table(with_frame_times(table, run_dir, arrays), run_dir / CAN_FRAMES_FILE)
        written.append(run_dir / CAN_FRAMES_FILE)
    return written


# --- steps ----------------------------------------------------------------------------------------
def _unit_of(name: str) -> tuple[str, str]:
    """(name without its unit suffix, unit suffix) of `omega_radps`; (name, "") when it has none."""
    base, _, suffix = name.rpartition("_")
    if base and suffix in UNITS:
        return base, suffix
    return name, ""


def component_columns(name: str, array: np.ndarray) -> list[tuple[str, str, str, np.ndarray]]:
    """(column, unit, source, values) for each component of one per-step array."""
    short = "t_s" if name in TIME_ARRAYS else name.removeprefix(DROPPED_PREFIX)
    if array.ndim == 1:
        _, suffix = _unit_of(short)
        if suffix in COLUMN_SUFFIX:
            short = short[: -len(suffix)] + COLUMN_SUFFIX[suffix]
        return [(short, UNITS.get(suffix, "1"), name, array)]
    flat = array.reshape(array.shape[0], -1)
    if name in SPECIAL_COMPONENTS and flat.shape[1] == len(SPECIAL_COMPONENTS[name]):
        return [(col, unit, f"{name}[:, {i}]", flat[:, i]) for i, (col, unit) in enumerate(SPECIAL_COMPONENTS[name])]
    base, suffix = _unit_of(short)
    suffix = COLUMN_SUFFIX.get(suffix, suffix)
    labels = AXES if flat.shape[1] == 3 else tuple(str(i) for i in range(flat.shape[1]))
    return [(f"{base}_{label}_{suffix}" if suffix else f"{base}_{label}", UNITS.get(suffix.lower(), "1"), f"{name}[:, {i}]",
             flat[:, i]) for i, label in enumerate(labels)]


def _padded(values: np.ndarray, n_rows: int) -> pa.Array:
    """values as a column of n_rows: truncated (preallocated stamps of a partial run) or padded
    with the empty value of its type (NaN, -1, null) in the rows it has no value for."""
    values = values[:n_rows]
    pad = n_rows - len(values)
    if values.dtype.kind == "f":
        return arrow_column(np.concatenate([values, np.full(pad, np.nan)]), pa.float64())
    if values.dtype.kind in "iu":
        return arrow_column(np.concatenate([values.astype(np.int64), np.full(pad, ABSENT_INT, dtype=np.int64)]), pa.int64())
    if values.dtype.kind == "b":
        return arrow_column(values.tolist() + [None] * pad, pa.bool_())
    raise TableError(f"trajectory array of dtype {values.dtype} cannot be a column")


# pa.array() asks pandas whether its input is a pandas object, and so imports pandas wherever it is
# installed (about 0.2 s of a report's 3-4 s: benchmarks/bench_report.py). `arrow_column` builds the
# same arrays from their buffers.
def _bitmap(flags) -> pa.Buffer:
    return pa.py_buffer(np.packbits(np.asarray(flags, dtype=bool), bitorder="little"))


def arrow_column(values, type_: pa.DataType) -> pa.Array:
    """pa.array(values, type=type_) for float64, int64, bool and string columns (None: null; only
    bool and string columns take it)."""
    n = len(values)
    if pa.types.is_string(type_) or pa.types.is_boolean(type_):
        valid = np.fromiter((v is not None for v in values), dtype=bool, count=n)
        validity = None if valid.all() else _bitmap(valid)
        if pa.types.is_boolean(type_):
            return pa.Array.from_buffers(type_, n, [validity, _bitmap([bool(v) for v in values])])
        encoded = [v.encode() if v is not None else b"" for v in values]
        offsets = np.zeros(n + 1, dtype=np.int32)
        np.cumsum([len(b) for b in encoded], out=offsets[1:])
        return pa.Array.from_buffers(type_, n, [validity, pa.py_buffer(offsets), pa.py_buffer(b"".join(encoded))])
    dtype = {pa.float64(): np.float64, pa.int64(): np.int64}.get(type_)
    if dtype is None:
        raise TypeError(f"no column of {type_}")
    return pa.Array.from_buffers(type_, n, [None, pa.py_buffer(np.ascontiguousarray(values, dtype=dtype))])


def steps_table(arrays: dict[str, np.ndarray]) -> pa.Table:
    """One row per step of trajectory.npz's arrays (see the module docstring)."""
    time_name = next((n for n in TIME_ARRAYS if n in arrays), None)
    if time_name is None:
        raise TableError(f"trajectory.npz has no time array ({' or '.join(TIME_ARRAYS)}); it has {sorted(arrays)}")
    n_rows = len(arrays[time_name])
    columns: dict[str, pa.Array] = {}
    units: dict[str, str] = {}
    sources: dict[str, str] = {}
    run: dict[str, object] = {}
    left_out: dict[str, list[int]] = {}
    # The time first, then the plant's arrays in the order it wrote them, the stamps last.
    for name in sorted(arrays, key=lambda n: (n != time_name, n.startswith("stamp_"))):
        array = arrays[name]
        if array.ndim == 0:
            run[name] = array.item()
            continue
        if name.startswith(NOT_PER_STEP_PREFIXES) or len(array) < n_rows - 1:
            left_out[name] = list(array.shape)
            continue
        for column, unit, source, values in component_columns(name, array):
            if column in columns:
                raise TableError(f"trajectory.npz: {source} and {sources[column]} would both be column {column!r}")
            columns[column], units[column], sources[column] = _padded(values, n_rows), unit, source
    fields = [pa.field(c, columns[c].type, metadata={"unit": units[c], "source": sources[c]}) for c in columns]
    metadata = {"rows": f"one per step k of the plant, t_s = its simulated time; {n_rows} rows",
                "empty": "NaN (floats) or -1 (integer stamps and counters) where a row has no value",
                "units": units, "sources": sources, "run": run, "left_out": left_out}
    schema = pa.schema(fields, metadata={METADATA_KEY: json.dumps(metadata, default=str).encode()})
    return pa.Table.from_arrays(list(columns.values()), schema=schema)


# --- CAN frames -----------------------------------------------------------------------------------
def _protocol(run_dir: Path) -> can_protocol.Protocol:
    """The run's protocol (node id, command profile) to name and decode frames; the DBC's defaults
    for a run directory without a readable scenario or without [can]."""
    try:
        config = getattr(load_scenario(run_dir / "scenario.json"), "can", None)
    except (ScenarioError, OSError):
        config = None
    return can_protocol.Protocol(config.node_id, config.security.profile) if config is not None else can_protocol.Protocol()


def with_frame_times(table: pa.Table, run_dir: Path, arrays: dict[str, np.ndarray]) -> pa.Table:
    """The frames' table with its times named by their clock (module docstring): `sim_time_s`,
    `in_run`, `step` and `wall_time_s` after `timestamp_s`, and the metadata that says which is which.
    Without the run's steps or its bus model's report, the table as it is, its metadata saying so."""
    from bench.report import canbus
    from bench.report.timebase import RunClock

    metadata = json.loads(table.schema.metadata[METADATA_KEY])
    # from the buffer: ChunkedArray.to_numpy asks for pandas (see arrow_column)
    chunks = table.column("timestamp_s").chunks
    stamps = np.concatenate([np.frombuffer(c.buffers()[1], dtype=np.float64, count=len(c), offset=c.offset * 8)
                             for c in chunks]) if chunks else np.zeros(0)
    scenario = None
    try:
        scenario = load_scenario(run_dir / "scenario.json")
    except (ScenarioError, OSError):
        pass
    times = arrays.get("att_time_s", arrays.get("t_s"))
    clock = RunClock.from_run(arrays, scenario) if times is not None else None
    sim_s = canbus.capture_sim_s(run_dir, clock, stamps) if times is not None else None
    on_sim_bus = canbus._bus_model_report(run_dir).get("clock") == "simulated"
    capture_clock = ("bus time of a bus on simulated time: simulated s + 1000 s" if on_sim_bus
                     else "wall clock (Unix epoch s) of the bus model")
    metadata["units"]["timestamp_s"] = f"s (can.log's stamp: {capture_clock})"
    if sim_s is None or len(times) == 0:
        metadata["time_columns"] = {"timestamp_s": capture_clock, "sim_time_s": "absent: no steps or bus model report"}
        return table.replace_schema_metadata({METADATA_KEY: json.dumps(metadata).encode()})
    times = np.asarray(times, dtype=float)
    # the run's span: from its first step's start to its last step's end (one step after its start)
    lo, hi = float(times[0]), float(times[-1] + (times[-1] - times[-2] if len(times) > 1 else 0.0))
    in_run = (sim_s >= lo) & (sim_s <= hi)
    # one bus, frames in capture order: monotone already; the running maximum keeps it so exactly
    clipped = np.maximum.accumulate(np.clip(sim_s, lo, hi)) if sim_s.size else sim_s
    step = np.clip(np.searchsorted(times, clipped, side="right") - 1, 0, len(times) - 1).astype(np.int64)
    wall = canbus.capture_wall_s(run_dir, stamps)
    units = {"sim_time_s": "s (simulated time of the run, as steps.parquet t_s)", "in_run": "1",
             "step": "1 (row of steps.parquet)", "wall_time_s": "s (wall clock, Unix epoch; NaN: bus on simulated time)"}
    metadata["units"].update(units)
    metadata["time_columns"] = {
        "sim_time_s": f"the run's simulated time, clipped to the run's span [{lo:g}, {hi:g}] s, monotone",
        "in_run": "the frame's simulated time lies within the steps (not the boot before or the safe state after)",
        "step": "steps.parquet row (step k with t_s <= sim_time_s < t_s of k+1): join on it",
        "wall_time_s": "wall clock (Unix epoch s); NaN where the bus ran on simulated time",
        "timestamp_s": capture_clock}
    position = table.schema.get_field_index("timestamp_s") + 1
    for name, values, type_ in (("wall_time_s", wall, pa.float64()), ("step", step, pa.int64()),
                                ("in_run", in_run.tolist(), pa.bool_()), ("sim_time_s", clipped, pa.float64())):
        table = table.add_column(position, pa.field(name, type_, metadata={"unit": units[name]}), arrow_column(values, type_))
    return table.replace_schema_metadata({METADATA_KEY: json.dumps(metadata).encode()})


def can_frames_table(path: Path, protocol: can_protocol.Protocol) -> pa.Table:
    rows: dict[str, list] = {k: [] for k in (
        "timestamp_s", "channel", "id", "id_hex", "is_extended_id", "is_fd", "is_error_frame", "is_remote_frame",
        "dlc", "data", "name", "direction", "decoded", "crc_ok", "signals")}
    for msg in can.CanutilsLogReader(str(path)):
        described = can_frame_signals(protocol, msg)
        values = {"timestamp_s": float(msg.timestamp), "channel": str(msg.channel), "id": int(msg.arbitration_id),
                  "id_hex": f"0x{msg.arbitration_id:03X}", "is_extended_id": bool(msg.is_extended_id),
                  "is_fd": bool(msg.is_fd), "is_error_frame": bool(msg.is_error_frame),
                  "is_remote_frame": bool(msg.is_remote_frame), "dlc": int(msg.dlc),
                  "data": bytes(msg.data or b"").hex(), **described, "signals": json.dumps(described["signals"])}
        for key, column in rows.items():
            column.append(values[key])
    types = {"timestamp_s": pa.float64(), "id": pa.int64(), "dlc": pa.int64(), "crc_ok": pa.bool_(),
             "is_extended_id": pa.bool_(), "is_fd": pa.bool_(), "is_error_frame": pa.bool_(),
             "is_remote_frame": pa.bool_(), "decoded": pa.bool_()}
    units = {"timestamp_s": "s (capture clock: wall clock of the bus model)", "signals": "DBC physical units"}
    fields = [pa.field(k, types.get(k, pa.string()), metadata={"unit": units.get(k, "1")}) for k in rows]
    metadata = {"rows": f"one per frame of {path.name} (candump capture of the bus model)", "units": units,
                "direction": "DBC sender -> receivers: OBC is the flight side (driver), MTQ the board",
                "signals": "JSON object of the DBC signals; {} when the frame does not decode"}
    schema = pa.schema(fields, metadata={METADATA_KEY: json.dumps(metadata).encode()})
    return pa.Table.from_arrays([arrow_column(v, f.type) for v, f in zip(rows.values(), fields)], schema=schema)
