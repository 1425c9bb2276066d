"""CAN transports: driver-to-board latency and sustained frames per second, per transport.

    .venv/bin/python benchmarks/bench_can.py            # zenoh (two processes) vs virtual, then
                                                        # socketcan/zenoh/virtual inside UML
    .venv/bin/python benchmarks/bench_can.py --no-uml   # host figures only

Latency: the flight-side driver (MagnetorquerDriver.command) sends COMMANDS magnetorquer commands,
one every PERIOD; the virtual board (MagnetorquerBoard.run, its own process) applies them. One-way
latency = the board's applied stamp minus the driver's stamp just before command(), both on
CLOCK_MONOTONIC, which every process on one kernel shares. It includes the DBC encoding and E2E
protection in the driver and the decoding and E2E check in the board, as in a run.

Throughput: one process sends FRAMES 8-byte frames back to back, another receives; frames/s is
what the receiver got per second between its first and last frame. Frames a receiver never got
are reported (a SocketCAN socket drops when its reader falls behind; zenoh blocks the sender).

The baseline is python-can's in-process `virtual` bus (driver and board threads in one process),
measured in the same run on the same machine; ratios are against it. Inside user-mode Linux every
system call of the guest traps to the UML kernel, so absolute figures there are far slower than
the host's; compare transports within the UML table only (UML's clock follows the host's).
"""
from __future__ import annotations

import argparse
import json
import select
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import can
import numpy as np

from bench.bus.can import protocol as p
from bench.bus.can.board import MagnetorquerBoard
from bench.bus.can.config import BoardConfig, DriverConfig
from bench.bus.can.driver import MagnetorquerDriver
from bench.bus.can.transport import default_transport, open_can_bus
from bench.bus.session import SessionOptions, free_loopback_port, loopback_endpoint

REPO = Path(__file__).resolve().parents[1]
RUN_IN_UML = REPO / "tools" / "uml" / "run-in-uml.sh"
CHANNEL = "vcan0"
COMMANDS = 500
PERIOD_S = 0.004
FRAMES = 20_000
ROUNDS = 3
THROUGHPUT_ID = 0x321
DONE_ID = 0x7FE
PEER_WAIT_S = 10.0
IDLE_S = 2.0          # a receiver that hears nothing this long stops
UML_TIMEOUT_S = 240


# --- the two ends, each usable in a thread (virtual) or its own process ----------------------
def board_side(bus: can.BusABC, commands: int, ready: threading.Event | None = None) -> dict:
    """Run the virtual board until it has applied `commands` commands (or goes idle)."""
    applied: list[tuple[int, int]] = []
    stop = threading.Event()

    def on_applied(cmd) -> None:
        applied.append((cmd.alive_counter, cmd.applied_ns))
        if len(applied) >= commands:
            stop.set()

    # Command timeout well above the pacing: the benchmark must not measure the safe state.
    board = MagnetorquerBoard(bus, BoardConfig(command_timeout_s=1.0), p.Protocol(), on_applied=on_applied)
    worker = threading.Thread(target=board.run, args=(stop,), daemon=True)
    worker.start()
    if ready is not None:
        ready.set()
    deadline = time.monotonic() + PEER_WAIT_S + commands * PERIOD_S * 4
    while not stop.is_set() and time.monotonic() < deadline:
        stop.wait(0.05)
    stop.set()
    worker.join(timeout=2)
    return {"applied": applied, "rejected": dict(board.rejected)}


def driver_side(bus: can.BusABC, commands: int) -> list[tuple[int, int]]:
    """Send `commands` commands, one every PERIOD_S; returns (alive counter, sent ns) each."""
    driver = MagnetorquerDriver(bus, DriverConfig(), BoardConfig(), p.Protocol())
    # CiA 301: the board applies commands only once started; the driver, its NMT master, starts
    # it when it hears a boot-up or pre-operational heartbeat.
    deadline = time.monotonic() + PEER_WAIT_S
    while driver.health().nmt_state != p.NMT_OPERATIONAL and time.monotonic() < deadline:
        driver.poll(timeout_s=0.05)
    sent = []
    next_s = time.monotonic()
    for i in range(commands):
        dipole = [0.1 * ((i % 3) == axis) * (1 if i % 2 else -1) for axis in range(3)]
        t_ns = time.monotonic_ns()
        counter = driver.command(dipole)
        sent.append((counter, t_ns))
        next_s += PERIOD_S
        time.sleep(max(0.0, next_s - time.monotonic()))
        while bus.recv(timeout=0.0) is not None:   # the board's telemetry: keep our queue short
            pass
    return sent


def sink_side(bus: can.BusABC, frames: int, ready: threading.Event | None = None) -> dict:
    """Count throughput frames until `frames` arrived or the bus went quiet; then say done."""
    if ready is not None:
        ready.set()
    received, first_ns, last_ns = 0, None, None
    while received < frames:
        msg = bus.recv(timeout=IDLE_S if received else PEER_WAIT_S)
        if msg is None:
            break
        if msg.arbitration_id != THROUGHPUT_ID:
            continue
        last_ns = time.monotonic_ns()
        first_ns = first_ns or last_ns
        received += 1
    bus.send(can.Message(arbitration_id=DONE_ID, is_extended_id=False))
    return {"received": received, "first_ns": first_ns, "last_ns": last_ns}


def source_side(bus: can.BusABC, frames: int) -> dict:
    """Send `frames` frames as fast as the transport takes them; wait for the sink's done."""
    msg = can.Message(arbitration_id=THROUGHPUT_ID, is_extended_id=False, data=bytes(8))
    retries = 0
    start_ns = time.monotonic_ns()
    for i in range(frames):
        msg.data[:4] = i.to_bytes(4, "little")
        while True:
            try:
                bus.send(msg)
                break
            except can.CanOperationError:   # SocketCAN: transmit queue full (ENOBUFS); try again
                retries += 1
                time.sleep(0)
    sent_ns = time.monotonic_ns() - start_ns
    deadline = time.monotonic() + PEER_WAIT_S + IDLE_S
    while time.monotonic() < deadline:
        done = bus.recv(timeout=0.5)
        if done is not None and done.arbitration_id == DONE_ID:
            break
    return {"send_s": sent_ns / 1e9, "retries": retries}


# --- one transport ---------------------------------------------------------------------------
def child(role: str, transport: str, run_id: str, endpoint: str | None, count: int) -> int:
    """A benchmark process: board or sink; prints 'ready' and then one JSON line."""
    options = SessionOptions(connect=(endpoint,)) if endpoint else None
    with open_can_bus(transport, CHANNEL, run_id=run_id, session_options=options) as bus:
        if transport == "zenoh" and not bus.wait_for_peers(1, PEER_WAIT_S):
            raise SystemExit("no peer on the zenoh channel")
        print("ready", flush=True)
        result = board_side(bus, count) if role == "board" else sink_side(bus, count)
        time.sleep(0.2 if transport == "zenoh" else 0)   # let the done frame leave before the session closes
    print(json.dumps(result), flush=True)
    return 0


def across_processes(transport: str, role: str, count: int, own_side) -> tuple[dict, object]:
    """Start the other end as a process, run our end here, return (its result, ours)."""
    run_id = f"canbench-{uuid.uuid4().hex[:8]}"
    endpoint = loopback_endpoint(free_loopback_port()) if transport == "zenoh" else None
    options = SessionOptions(listen=(endpoint,)) if endpoint else None
    with open_can_bus(transport, CHANNEL, run_id=run_id, session_options=options) as bus:
        command = [sys.executable, __file__, "--role", role, "--transport", transport, "--run-id", run_id,
                   "--count", str(count)] + (["--endpoint", endpoint] if endpoint else [])
        peer = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            # Bounded wait for "ready": a child that hangs while starting must not hang us.
            started, _, _ = select.select([peer.stdout], [], [], PEER_WAIT_S + 20)
            if not started or peer.stdout.readline().strip() != "ready":
                raise RuntimeError(f"{role} process did not start: {peer.stderr.read()[-2000:]}")
            if transport == "zenoh" and not bus.wait_for_peers(1, PEER_WAIT_S):
                raise RuntimeError("the zenoh peer never appeared")
            ours = own_side(bus, count)
            out, err = peer.communicate(timeout=PEER_WAIT_S + count * PERIOD_S * 4 + 30)
        finally:
            if peer.poll() is None:
                peer.kill()
                peer.wait()
    if peer.returncode != 0:
        raise RuntimeError(f"{role} process failed ({peer.returncode}): {err[-2000:]}")
    return json.loads(out.strip().splitlines()[-1]), ours


def in_one_process(role: str, count: int, own_side) -> tuple[dict, object]:
    """The virtual baseline: the other end in a thread of this process."""
    run_id = f"canbench-{uuid.uuid4().hex[:8]}"
    with open_can_bus("virtual", CHANNEL, run_id=run_id) as ours_bus, \
            open_can_bus("virtual", CHANNEL, run_id=run_id) as theirs_bus:
        result: dict = {}
        ready = threading.Event()
        side = board_side if role == "board" else sink_side
        worker = threading.Thread(target=lambda: result.update(side(theirs_bus, count, ready)), daemon=True)
        worker.start()
        ready.wait(PEER_WAIT_S)
        ours = own_side(ours_bus, count)
        worker.join(timeout=PEER_WAIT_S + count * PERIOD_S * 4 + 30)
    return result, ours


def measure_once(transport: str, commands: int, frames: int) -> dict:
    run = in_one_process if transport == "virtual" else (lambda *a: across_processes(transport, *a))
    board, sent = run("board", commands, driver_side)
    applied = board["applied"]
    pairs = [(s, a) for s, a in zip(sent, applied) if s[0] == a[0]]
    sink, source = run("sink", frames, source_side)
    span_s = ((sink["last_ns"] or 0) - (sink["first_ns"] or 0)) / 1e9
    return {
        "latency_us": [(a[1] - s[1]) / 1e3 for s, a in pairs],
        "commands_sent": len(sent), "commands_applied": len(applied), "commands_unpaired": len(sent) - len(pairs),
        "frames_sent": frames, "frames_received": sink["received"],
        "frames_per_s": (sink["received"] - 1) / span_s if span_s > 0 else float("nan"),
        "send_retries": source["retries"],
    }


def measure(transports: list[str], commands: int, frames: int, rounds: int) -> list[dict]:
    """Each transport `rounds` times, interleaved, so that load from elsewhere on a shared machine
    falls on every transport alike. Latency percentiles over all samples; frames/s the median round."""
    runs: dict[str, list[dict]] = {t: [] for t in transports}
    for _ in range(rounds):
        for transport in transports:
            runs[transport].append(measure_once(transport, commands, frames))
    results = []
    for transport, each in runs.items():
        latency_us = np.array([x for r in each for x in r["latency_us"]])
        total = {k: sum(r[k] for r in each) for k in
                 ("commands_sent", "commands_applied", "commands_unpaired", "frames_sent", "frames_received")}
        results.append({
            "transport": transport, **total,
            "latency_median_us": float(np.median(latency_us)) if latency_us.size else None,
            "latency_p99_us": float(np.percentile(latency_us, 99)) if latency_us.size else None,
            "frames_per_s": float(np.median([r["frames_per_s"] for r in each])),
            "frames_per_s_rounds": [round(r["frames_per_s"]) for r in each],
        })
    return results


# --- report ----------------------------------------------------------------------------------
def table(results: list[dict], title: str) -> str:
    base = next((r for r in results if r["transport"] == "virtual"), None)
    lines = [title,
             f"{'transport':<10} {'median us':>10} {'p99 us':>10} {'x virtual':>9} {'frames/s':>10} {'x virtual':>9}"
             f" {'lost':>6}  commands applied/sent"]
    for r in results:
        lat_ratio = r["latency_median_us"] / base["latency_median_us"] if base and r["latency_median_us"] else float("nan")
        fps_ratio = r["frames_per_s"] / base["frames_per_s"] if base and r["frames_per_s"] else float("nan")
        lines.append(
            f"{r['transport']:<10} {r['latency_median_us'] or float('nan'):>10.0f} {r['latency_p99_us'] or float('nan'):>10.0f}"
            f" {lat_ratio:>9.2f} {r['frames_per_s'] or float('nan'):>10.0f} {fps_ratio:>9.2f}"
            f" {r['frames_sent'] - r['frames_received']:>6}  {r['commands_applied']}/{r['commands_sent']}"
            + (f" ({r['commands_unpaired']} unpaired)" if r["commands_unpaired"] else "")
            + f"  frames/s per round {r['frames_per_s_rounds']}"
        )
    return "\n".join(lines)


def run_in_uml(args: argparse.Namespace) -> str:
    if not Path("/usr/bin/linux.uml").exists():
        return "inside user-mode Linux: not measured (user-mode-linux is not installed)"
    command = ["bash", str(RUN_IN_UML), "--timeout", str(UML_TIMEOUT_S), "--mem", "512M", "--",
               sys.executable, __file__, "--no-uml", "--transports", args.uml_transports,
               "--commands", str(args.commands), "--frames", str(args.frames), "--rounds", str(args.rounds), "--title",
               "inside user-mode Linux (kernel vcan; guest syscalls trap to UML: compare within this table)"]
    proc = subprocess.run(command, capture_output=True, text=True, cwd=REPO, timeout=UML_TIMEOUT_S + 30)
    if proc.returncode != 0:
        return f"inside user-mode Linux: failed (exit {proc.returncode}):\n{(proc.stdout + proc.stderr)[-2000:]}"
    return proc.stdout.strip()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--transports", default="zenoh,virtual")
    parser.add_argument("--commands", type=int, default=COMMANDS)
    parser.add_argument("--frames", type=int, default=FRAMES)
    parser.add_argument("--rounds", type=int, default=ROUNDS)
    parser.add_argument("--no-uml", action="store_true", help="do not also measure inside user-mode Linux")
    parser.add_argument("--uml-transports", default="socketcan,virtual",
                        help="zenoh can be added, but on UML's one emulated CPU its runtime threads fall "
                             "behind a 250 Hz command stream (latency grows to seconds): not a transport figure")
    parser.add_argument("--title", default="host")
    # internal: the other end of a cross-process measurement
    parser.add_argument("--role", choices=("board", "sink"))
    parser.add_argument("--transport")
    parser.add_argument("--run-id")
    parser.add_argument("--endpoint")
    parser.add_argument("--count", type=int)
    args = parser.parse_args()
    if args.role:
        return child(args.role, args.transport, args.run_id, args.endpoint, args.count)

    transports = args.transports.split(",")
    title = (f"{args.title}: default transport {default_transport()}; {args.rounds} rounds of {args.commands} "
             f"commands every {PERIOD_S * 1e3:.0f} ms driver->board and {args.frames} frames back to back")
    print(table(measure(transports, args.commands, args.frames, args.rounds), title), flush=True)
    if not args.no_uml:
        print()
        print(run_in_uml(args))
    return 0


if __name__ == "__main__":
    sys.exit(main())
