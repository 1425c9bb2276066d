"""Recordings and tables of real runs, read by independent code: the `mcap` package's reader with
`jsonschema` and cantools for the recording, pandas for the Parquet tables (issue 22).

Two runs through `bench run` (lock-step): the default rendezvous in full (288 steps of 600 s, the
48 h of seed 003) and the first 2 s of `attitude_quick` (the attitude loop through the CAN bus).
"""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys

import cantools
import jsonschema
import numpy as np
import pandas as pd
import pytest
from mcap.reader import make_reader

from bench.scenario import load_scenario
from conftest import REPO, run_bench_cli

RENDEZVOUS_STEPS = 288          # rendezvous_lqr's own: 288 x 600 s = 48 h
RENDEZVOUS_STEP_S = 600.0
ATTITUDE_STEPS = 20
ATTITUDE_STEP_S = load_scenario("attitude_quick").step_s     # 1 s: 20 s simulated
# the command frame of the default (SecOC) profile: the authenticated command
COMMAND_FRAME = "MTQ_CMD_AUTH"
DBC = "bench/bus/can/mtq.dbc"


def bench_run(runs, *args: str):
    result = run_bench_cli("run", *args, "--mode", "lock-step", "--runs-dir", str(runs), "--no-progress", timeout_s=180)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]


@pytest.fixture(scope="module")
def rendezvous_run(tmp_path_factory):
    runs = tmp_path_factory.mktemp("runs")
    bench_run(runs, "rendezvous_lqr", "--run-id", "rdv")
    return runs / "rdv"


@pytest.fixture(scope="module")
def attitude_run(tmp_path_factory):
    runs = tmp_path_factory.mktemp("runs")
    bench_run(runs, "attitude_quick", "--steps", str(ATTITUDE_STEPS), "--run-id", "att")
    return runs / "att"


def read_mcap(path):
    """(metadata by name, [(schema, channel, message)]) with the mcap package's reader."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        return metadata, list(reader.iter_messages())


def check_every_channel_decodes_with_its_schema(messages) -> dict[str, list[dict]]:
    """Every message is JSON valid against the JSON schema its channel names; bodies by topic."""
    bodies: dict[str, list[dict]] = {}
    validators = {}
    for schema, channel, message in messages:
        assert schema is not None, f"{channel.topic} has no schema"
        assert (schema.encoding, channel.message_encoding) == ("jsonschema", "json"), channel.topic
        if schema.id not in validators:
            validators[schema.id] = jsonschema.Draft202012Validator(json.loads(schema.data))
        body = json.loads(message.data)
        validators[schema.id].validate(body)
        bodies.setdefault(channel.topic, []).append(body)
    return bodies


# --- recordings ----------------------------------------------------------------------------------
def test_a_48_h_rendezvous_recording_spans_48_h_of_log_time(rendezvous_run):
    metadata, messages = read_mcap(rendezvous_run / "recording.mcap")
    bodies = check_every_channel_decodes_with_its_schema(messages)
    log_times_s = np.array([m.log_time for _, _, m in messages]) / 1e9
    assert log_times_s.min() == 0.0
    assert log_times_s.max() == pytest.approx(RENDEZVOUS_STEPS * RENDEZVOUS_STEP_S)     # 172 800 s
    # Each stepped message sits at its own header's simulated time; the publish time is the wall
    # clock: the whole run took seconds, not hours.
    for schema, channel, message in messages:
        if channel.topic in ("truth", "command/thrust", "status/step"):
            assert message.log_time == round(json.loads(message.data)["header"]["sim_time_s"] * 1e9)
    publish_s = np.array([m.publish_time for _, _, m in messages]) / 1e9
    assert 0 < publish_s.max() - publish_s.min() < 600
    assert len(bodies["truth"]) == RENDEZVOUS_STEPS
    scenario = json.loads(metadata["scenario"]["scenario_json"])
    assert metadata["scenario"]["name"] == scenario["name"] == "rendezvous_lqr"
    assert scenario == json.loads((rendezvous_run / "scenario.json").read_text())


def test_attitude_recording_decodes_can_frames_with_the_dbc(attitude_run):
    metadata, messages = read_mcap(attitude_run / "recording.mcap")
    bodies = check_every_channel_decodes_with_its_schema(messages)
    log_times_s = np.array([m.log_time for _, _, m in messages]) / 1e9
    assert log_times_s.min() == 0.0 and log_times_s.max() == pytest.approx(ATTITUDE_STEPS * ATTITUDE_STEP_S)
    assert metadata["scenario"]["name"] == "attitude_quick"
    # The scenario as it ran, but the bus's SecOC key stays out of a file meant to be shared.
    scenario = json.loads(metadata["scenario"]["scenario_json"])
    ran = json.loads((attitude_run / "scenario.json").read_text())
    assert scenario["can"]["security"]["key_hex"] == "(left out)" != ran["can"]["security"]["key_hex"]
    scenario["can"]["security"]["key_hex"] = ran["can"]["security"]["key_hex"]
    assert scenario == ran
    db = cantools.database.load_file(DBC)
    frames = bodies["can/flight"] + bodies["can/board"]
    names = {f["name"] for f in frames}
    assert {COMMAND_FRAME, "MTQ_TLM_DIPOLE", "MTQ_HEARTBEAT"} <= names
    for frame in frames:
        expected = db.get_message_by_frame_id(frame["id"])
        assert frame["name"] == expected.name
        assert frame["direction"] == ("OBC->MTQ" if expected.senders == ["OBC"] else "MTQ->OBC")
        decoded = expected.decode(bytes.fromhex(frame["data"]), decode_choices=False)
        assert frame["signals"] == pytest.approx(decoded), frame
        assert 0.0 <= frame["sim_time_s"] <= ATTITUDE_STEPS * ATTITUDE_STEP_S
    commands = [f for f in frames if f["name"] == COMMAND_FRAME and f["channel"] == "flight"]
    assert any(abs(f["signals"]["DipoleX"]) > 0 for f in commands)    # B-dot commands a dipole


# --- tables --------------------------------------------------------------------------------------
def test_rendezvous_steps_table_matches_the_trajectory(rendezvous_run):
    steps = pd.read_parquet(rendezvous_run / "steps.parquet")
    with np.load(rendezvous_run / "trajectory.npz") as npz:
        t_s, state, thrust = npz["t_s"], npz["state_m_mps"], npz["thrust_n"]
        stamps = {k: npz[k] for k in npz.files if k.startswith("stamp_")}
    # N + 1 rows: the state after the last step is the last row, with no command.
    assert len(steps) == len(t_s) == RENDEZVOUS_STEPS + 1 == len(thrust) + 1
    np.testing.assert_array_equal(steps["t_s"], t_s)
    np.testing.assert_array_equal(steps[["x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"]].to_numpy(), state)
    np.testing.assert_array_equal(steps[["thrust_x_n", "thrust_y_n", "thrust_z_n"]].to_numpy()[:-1], thrust)
    assert steps[["thrust_x_n", "thrust_y_n", "thrust_z_n"]].iloc[-1].isna().all()
    for name, values in stamps.items():
        assert steps[name].dtype == np.int64
        np.testing.assert_array_equal(steps[name].to_numpy()[:-1], values[:RENDEZVOUS_STEPS])
        assert steps[name].iloc[-1] == -1


def test_attitude_steps_and_can_frames_tables(attitude_run):
    steps = pd.read_parquet(attitude_run / "steps.parquet")
    with np.load(attitude_run / "trajectory.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    assert len(steps) == ATTITUDE_STEPS == len(arrays["att_time_s"])
    np.testing.assert_array_equal(steps["t_s"], arrays["att_time_s"])
    np.testing.assert_array_equal(steps[["q_w", "q_x", "q_y", "q_z"]].to_numpy(), arrays["att_q_wxyz"])
    for column, (name, axis) in {"omega_y_radps": ("att_omega_radps", 1),
                                 "dipole_commanded_z_am2": ("att_dipole_commanded_am2", 2),
                                 "dipole_applied_x_am2": ("att_dipole_applied_am2", 0),
                                 "field_body_z_T": ("att_field_body_t", 2)}.items():
        np.testing.assert_array_equal(steps[column].to_numpy(), arrays[name][:, axis], err_msg=column)
    np.testing.assert_array_equal(steps["stamp_sensed_ns"].to_numpy(), arrays["stamp_sensed_ns"])
    np.testing.assert_array_equal(steps["alive_counter"].to_numpy(), arrays["att_alive_counter"])
    import pyarrow.parquet as pq
    schema = pq.read_schema(attitude_run / "steps.parquet")
    assert schema.field("omega_x_radps").metadata[b"unit"] == b"rad/s"
    assert json.loads(schema.metadata[b"bench"])["units"]["dipole_commanded_x_am2"] == "A m^2"

    frames = pd.read_parquet(attitude_run / "can_frames.parquet")
    log_lines = [line for line in (attitude_run / "can.log").read_text().splitlines() if line.strip()]
    assert len(frames) == len(log_lines) > 0
    db = cantools.database.load_file(DBC)
    # The first classic frame, "(timestamp) channel ID#DATA [T|R]": which frame the log starts with
    # depends on the start-up order (a CAN FD frame, "ID##<flags>DATA", may come first).
    i = next(i for i, line in enumerate(log_lines) if "##" not in line)
    first = log_lines[i].split()
    frame_id, data = first[2].split("#")
    assert frames["timestamp_s"].iloc[i] == pytest.approx(float(first[0].strip("()")))
    assert frames["id"].iloc[i] == int(frame_id, 16) and frames["data"].iloc[i] == data.lower()
    assert frames["name"].iloc[i] == db.get_message_by_frame_id(int(frame_id, 16)).name
    assert set(frames["direction"]) <= {"OBC->MTQ", "MTQ->OBC"}
    assert (frames["name"] == COMMAND_FRAME).sum() > 0


# --- the Foxglove layout -------------------------------------------------------------------------
LAYOUT = "docs/foxglove/attitude_layout.json"
# topic, optional {field=="value"} filter, then .field and [index] parts (Foxglove's message path syntax)
MESSAGE_PATH = re.compile(r'^(?P<topic>[A-Za-z0-9_/-]+)(\{(?P<key>\w+)=="(?P<value>[^"]*)"\})?(?P<rest>(\.\w+|\[\d+\])+)$')
ONLY_WHEN_IT_HAPPENS = {"event/deadline"}     # published on a deadline miss only


def resolve(body, rest: str):
    for name, index in re.findall(r"\.(\w+)|\[(\d+)\]", rest):
        body = body[name] if name else body[int(index)]
    return body


def test_the_foxglove_layout_plots_fields_the_recording_has(attitude_run):
    layout = json.loads((REPO / LAYOUT).read_text())
    _, messages = read_mcap(attitude_run / "recording.mcap")
    bodies = check_every_channel_decodes_with_its_schema(messages)
    paths = [p["value"] for panel in layout["configById"].values() for p in panel["paths"]]
    assert len(paths) >= 20
    for path in paths:
        match = MESSAGE_PATH.match(path)
        assert match, f"{path} is not a message path of the form the layout uses"
        topic = match["topic"]
        if topic in ONLY_WHEN_IT_HAPPENS and topic not in bodies:
            continue
        selected = [b for b in bodies[topic] if match["key"] is None or b.get(match["key"]) == match["value"]]
        assert selected, path
        values = [resolve(b, match["rest"]) for b in selected]
        assert all(isinstance(v, (int, float, bool, str)) for v in values), path


@pytest.mark.parametrize("seed", range(5))
def test_columns_built_from_buffers_equal_pyarrows_own(seed):
    """The tables' columns (bench.report.tables.arrow_column, built from buffers so that writing a
    table does not import pandas) equal pa.array's for the same values, nulls and empties included."""
    import pyarrow as pa

    from bench.report.tables import arrow_column
    rng = np.random.default_rng(seed)
    n = int(rng.integers(0, 40))
    maybe_none = lambda v: None if rng.random() < 0.2 else v    # noqa: E731
    cases = [
        (rng.normal(size=n) * 10.0 ** rng.integers(-9, 9, size=n), pa.float64()),
        (np.array([np.nan, np.inf, -0.0] * (n // 3)), pa.float64()),
        (rng.integers(-2**62, 2**62, size=n), pa.int64()),
        ([maybe_none(bool(b)) for b in rng.integers(0, 2, size=n)], pa.bool_()),
        ([bool(b) for b in rng.integers(0, 2, size=n)], pa.bool_()),
        ([maybe_none("".join(rng.choice(list("ab0x_ωπ"), size=int(rng.integers(0, 6))))) for _ in range(n)], pa.string()),
    ]
    for values, type_ in cases:
        ours, theirs = arrow_column(values, type_), pa.array(values, type=type_)
        ours.validate(full=True)
        assert ours.type == theirs.type and ours.null_count == theirs.null_count
        if pa.types.is_floating(type_):     # bit for bit (NaN never equals NaN)
            assert ours.to_numpy().tobytes() == theirs.to_numpy().tobytes()
        else:
            assert ours.equals(theirs), (type_, values, ours, theirs)


def test_writing_the_tables_does_not_import_pandas(attitude_run, tmp_path):
    run_dir = shutil.copytree(attitude_run, tmp_path / "att")
    for table in ("steps.parquet", "can_frames.parquet"):
        (run_dir / table).unlink()
    code = ("import sys; from bench.report.tables import write_tables; "
            f"print(len(write_tables({str(run_dir)!r})), 'pandas' in sys.modules)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "2 False"
