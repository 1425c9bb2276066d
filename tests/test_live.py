"""Live operation on the whole bench (issue 48): a real-time attitude run with `--live`, watched by a
Foxglove WebSocket client written from the protocol's specification (tests/foxglove_ws_client.py,
the `websockets` package, not foxglove-sdk's client), a fault injected through the live view's
service and a second by `bench inject` from another process; the run's metrics then show both on
simulated time with what detected them. Injections without the run's key (no key, another key, a
replayed request, a service call without the token) are refused and counted; a run without
--allow-live-faults refuses every injection."""
from __future__ import annotations

import asyncio
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import msgspec
import pytest

from bench.bus import data_auth
from bench.bus import fault_command as fc
from bench.bus.presence import PresenceQuery
from bench.bus.session import SessionOptions, free_loopback_port, open_session
from bench.live.node import service_token

from conftest import REPO, run_bench_cli
from foxglove_ws_client import FoxgloveClient

SCENARIO = "attitude_detumble_rt"     # real time at 1x, B-dot over the CAN bus; 10 Hz steps
STEPS = 250                           # 25 s of simulated (and wall) time: room for a loaded host's slow `bench inject`
# Channels with a message at least every step (or every frame): each must bring 10 or more.
DENSE = ["truth/attitude", "estimate/attitude", "sense/gyro", "command/dipole", "actuator/mtq", "can/flight",
         "can/board", "/tf", "live/attitude_error", "live/estimate_error", "live/criteria"]
LAYOUT = REPO / "docs" / "foxglove" / "live_layout.json"
ONLY_WHEN_IT_HAPPENS = {"event/deadline"}     # published on a deadline miss only


def start_run(runs_dir: Path, run_id: str, port: int, *extra: str, steps: int = STEPS) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "bench.cli", "run", SCENARIO, "--steps", str(steps), "--live", str(port),
                             "--run-id", run_id, "--runs-dir", str(runs_dir), "--no-progress", "--no-report", *extra],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


async def connect(port: int, run: subprocess.Popen, timeout_s: float = 90.0) -> FoxgloveClient:
    deadline = time.monotonic() + timeout_s
    while True:
        assert run.poll() is None, run.communicate()
        try:
            return await FoxgloveClient(f"ws://127.0.0.1:{port}").__aenter__()
        except OSError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.1)


def inject(runs_dir: Path, run_id: str, *args: str) -> subprocess.CompletedProcess:
    return run_bench_cli("inject", run_id, *args, "--runs-dir", str(runs_dir), timeout_s=60)


def finish(run: subprocess.Popen) -> str:
    out, err = run.communicate(timeout=120)
    assert run.returncode in (0, 1), err       # 1: the scenario's verdict may fail on a short run
    return err


def replay_a_signed_request(runs_dir: Path, run_id: str) -> tuple[fc.FaultReply, fc.FaultReply]:
    """A request signed under the run's key (a fault scripted faults could not have: refused as invalid
    once its tag is taken), then the very same bytes again, as a recording of it would be."""
    run_dir = runs_dir / run_id
    key = data_auth.read_key_file(run_dir / data_auth.KEY_FILE)
    hub = json.loads((run_dir / "contract.json").read_text())["zenoh"]["connect"]
    request = fc.new_request(run_id, "flood")                       # no duration_s: invalid
    tag = data_auth.Signer(key, "inject")(fc.key_expr(run_id), msgspec.json.encode(request))
    session = open_session(SessionOptions(connect=(hub,)))
    try:
        PresenceQuery(session, run_id, key).wait_ready(["canbus"], 10.0)
        first, _ = fc.request_fault(session, request, key, "inject", signer=lambda where, payload: tag)
        second, _ = fc.request_fault(session, request, key, "inject", signer=lambda where, payload: tag)
    finally:
        session.close()
    return first, second


def test_a_live_run_is_watched_and_takes_faults_from_the_view_and_from_bench_inject(runs_dir, tmp_path):
    port, run_id = free_loopback_port(), "live-watch"
    run = start_run(runs_dir, run_id, port, "--allow-live-faults")

    async def watch() -> dict:
        client = await connect(port, run)
        try:
            assert await client.wait_for(lambda g: g.server_info and g.services and len(g.channels) >= len(DENSE), 10)
            topics = {c["topic"] for c in client.got.channels.values()}
            assert set(DENSE) | {"event/fault", "event/can", "event/deadline", "/events", "live/status"} <= topics
            assert {"time", "services"} <= set(client.got.server_info["capabilities"])
            by_topic = {c["topic"]: c for c in client.got.channels.values()}
            assert by_topic["truth/attitude"]["schemaName"] == "AttitudeTruth"        # the MCAP's schemas
            assert by_topic["/tf"]["schemaName"] == "foxglove.FrameTransform"
            assert by_topic["can/flight"]["schemaName"] == "bench.CanFrame"
            await client.subscribe(DENSE + ["event/fault", "/events"])
            assert await client.wait_for(lambda g: all(len(g.messages.get(t, ())) >= 10 for t in DENSE), 60), \
                {t: len(client.got.messages.get(t, ())) for t in DENSE}
            token = service_token(data_auth.read_key_file(runs_dir / run_id / data_auth.KEY_FILE))
            refused = await client.call("/inject_fault", {"token": "not-the-token", "kind": "drop", "duration_s": 1.0})
            taken = await client.call("/inject_fault", {"token": token, "kind": "drop", "duration_s": 1.0})
            assert taken["accepted"] and taken["authentic"] and taken["label"] == "0:drop", taken
            replays = await asyncio.to_thread(replay_a_signed_request, runs_dir, run_id)
            # bench inject from another process, with the run's key: a second fault.
            done = await asyncio.to_thread(inject, runs_dir, run_id, "corrupt", "--count", "30")
            assert done.returncode == 0, done.stderr
            assert "fault 1:corrupt taken" in done.stdout
            # Without the key, and with another one: refused, and the run says so.
            (tmp_path / "other" / run_id).mkdir(parents=True)
            shutil.copy(runs_dir / run_id / "contract.json", tmp_path / "other" / run_id)
            other_key = tmp_path / "other.key"
            other_key.write_text(data_auth.new_key().hex() + "\n")
            os.chmod(other_key, 0o600)
            unsigned, forged = await asyncio.gather(
                asyncio.to_thread(inject, tmp_path / "other", run_id, "drop", "--duration", "1"),
                asyncio.to_thread(inject, runs_dir, run_id, "drop", "--duration", "1", "--key-file", str(other_key)))
            assert await client.wait_for(lambda g: len(g.messages.get("event/fault", ())) >= 2, 10)
            times = list(client.got.times_ns)
            bodies = {t: [json.loads(m) for _, m in client.got.messages[t]] for t in DENSE + ["event/fault"]
                      if t not in ("/tf", "/events")}
            return {"bodies": bodies, "refused": refused, "taken": taken, "unsigned": unsigned, "forged": forged, "replays": replays,
                    "windows": [json.loads(m) for _, m in client.got.messages["event/fault"]],
                    "log_times": [t for t, _ in client.got.messages["truth/attitude"]], "times": times}
        finally:
            await client.__aexit__(None, None, None)

    try:
        seen = asyncio.run(watch())
    finally:
        err = finish(run)
    assert "live view: ws://127.0.0.1:" in err and "bench inject live-watch" in err

    assert seen["refused"] == {"accepted": False, "reason": "forged", "authentic": False,
                               "detail": "no valid token (the one `bench run` printed)"}
    assert seen["unsigned"].returncode == 1 and "refused (forged)" in seen["unsigned"].stderr
    assert seen["forged"].returncode == 1 and "refused (forged)" in seen["forged"].stderr
    first, second = seen["replays"]
    assert first.reason == fc.INVALID and second.reason == fc.REPLAYED
    # The server's time and every message's log time are the run's simulated time (10 Hz steps).
    assert all(abs(t / 1e8 - round(t / 1e8)) < 1e-3 for t in seen["log_times"])
    assert seen["times"] == sorted(seen["times"]) and seen["times"][-1] <= STEPS * 1e8
    assert [(w["label"], w["live"], w["requested_by"]) for w in seen["windows"]] == [
        ("0:drop", True, "live"), ("1:corrupt", True, "inject")]
    assert_the_live_layout_reads_what_the_view_sent(seen["bodies"])

    run_dir = runs_dir / run_id
    metrics = json.loads((run_dir / "metrics.json").read_text())
    faults = metrics["can_bus"]["faults"]
    assert [(f["name"], f["live"]) for f in faults] == [("drop", True), ("corrupt", True)]
    drop, corrupt = faults
    assert drop["start_sim_s"] == pytest.approx(seen["taken"]["start_sim_s"], abs=0.2)
    assert drop["end_sim_s"] - drop["start_sim_s"] == pytest.approx(1.0, abs=0.05)
    assert 0 < drop["start_sim_s"] < corrupt["start_sim_s"] < STEPS * 0.1
    # What detected each: the board's command timeout (drops), its E2E check (corrupted commands).
    assert drop["detected"] and drop["first_detection"] == "board_command_timeout", drop
    assert corrupt["detected"] and corrupt["first_detection"] == "command_rejected", corrupt
    assert 0 <= drop["detection_latency_s"] < 1.0 and 0 <= corrupt["detection_latency_s"] < 1.0
    live = metrics["can_bus"]["live_faults"]
    assert live == {"allowed": True, "taken": 2, "refused": {"forged": 2, "invalid": 1, "replayed": 1},
                    "requested_by": ["inject", "live"]}
    assert metrics["process_stats"]["canbus"]["unauthentic"] == {"forged": {"control/fault": 2},
                                                                  "replayed": {"control/fault": 1}}
    # Injected faults act as scripted ones: the injector's records name them.
    records = [json.loads(line) for line in (run_dir / "can" / "injections.jsonl").read_text().splitlines()]
    assert {r["fault"] for r in records} == {"0:drop", "1:corrupt"}
    watched = json.loads((run_dir / "live.json").read_text())
    assert watched["service_calls"] == {"forged": 1, "accepted": 1}
    assert watched["dropped"] == {}


def assert_the_live_layout_reads_what_the_view_sent(bodies: dict) -> None:
    """Every plotted path of docs/foxglove/live_layout.json names a field the live view sent (as
    tests/test_recording_tables.py checks the recording's layout against the MCAP)."""
    from test_recording_tables import MESSAGE_PATH, resolve

    layout = json.loads(LAYOUT.read_text())
    paths = [p["value"] for panel in layout["configById"].values() for p in panel.get("paths", [])]
    assert len(paths) >= 15
    for path in paths:
        match = MESSAGE_PATH.match(path)
        assert match, f"{path} is not a message path of the form the layout uses"
        if match["topic"] in ONLY_WHEN_IT_HAPPENS and match["topic"] not in bodies:
            continue
        selected = [b for b in bodies[match["topic"]] if match["key"] is None or b.get(match["key"]) == match["value"]]
        assert selected, path
        values = [resolve(b, match["rest"]) for b in selected]
        # B-dot has no target: its pointing error is null (docs/live.md)
        assert all(isinstance(v, (int, float, bool, str)) or (v is None and "pointing" in path) for v in values), path
    panels = {name.split("!")[0] for name in layout["configById"]}
    assert {"3D", "Plot", "Log", "CallService", "RawMessages", "StateTransitions"} <= panels
    assert layout["configById"]["Log!events"]["topicToRender"] == "/events"
    assert layout["configById"]["CallService!inject"]["serviceName"] == "/inject_fault"


def test_a_run_without_allow_live_faults_refuses_every_injection(runs_dir):
    port, run_id = free_loopback_port(), "live-closed"
    run = start_run(runs_dir, run_id, port, steps=150)

    async def try_to_inject() -> tuple[dict, subprocess.CompletedProcess]:
        client = await connect(port, run)
        try:
            assert await client.wait_for(lambda g: g.services, 10)
            await client.subscribe(["truth/attitude"])
            assert await client.wait_for(lambda g: len(g.messages.get("truth/attitude", ())) >= 10, 60)
            token = service_token(data_auth.read_key_file(runs_dir / run_id / data_auth.KEY_FILE))
            answer = await client.call("/inject_fault", {"token": token, "kind": "drop", "duration_s": 1.0})
            done = await asyncio.to_thread(inject, runs_dir, run_id, "board_power_loss", "--duration", "0.5")
            return answer, done
        finally:
            await client.__aexit__(None, None, None)

    try:
        answer, done = asyncio.run(try_to_inject())
    finally:
        err = finish(run)
    assert "live faults refused" in err
    assert not answer["accepted"] and answer["reason"] == fc.NOT_ALLOWED and answer["authentic"]
    assert done.returncode == 1 and "refused (not_allowed)" in done.stderr
    metrics = json.loads((runs_dir / run_id / "metrics.json").read_text())
    assert metrics["can_bus"]["faults"] == []
    assert metrics["can_bus"]["live_faults"] == {"allowed": False, "taken": 0, "refused": {"not_allowed": 2},
                                                 "requested_by": []}
