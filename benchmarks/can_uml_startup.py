"""How long a CAN bench node takes to start inside user-mode Linux (one emulated CPU).

    .venv/bin/python benchmarks/can_uml_startup.py                       # this checkout, 5 starts
    .venv/bin/python benchmarks/can_uml_startup.py --tree /tmp/old-tree  # another checkout of the bench
    .venv/bin/python benchmarks/can_uml_startup.py --busy 2              # with both host cores busy
    .venv/bin/python benchmarks/can_uml_startup.py --mem 1024M           # the guest's memory

One UML boot; inside it, for each repeat: `bench node --help` (the CLI's own start-up), and
`bench node mtq` on a socketcan scenario, timed from its spawn to the board's first heartbeat on
the kernel's vcan1 (what bench.runtime.can_bench.CanBench waits for, bounded by its
STARTUP_TIMEOUT_S). --tree runs another checkout's `bench` (PYTHONPATH and working directory), so
two versions are compared on the same host in the same way. Prints the figures and the median.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
HEARTBEAT_WAIT_S = 180.0


def guest(tree: Path, repeats: int) -> dict:
    """Inside UML: the figures for `tree`'s bench."""
    sys.path.insert(0, str(tree))
    os.chdir(tree)
    import can

    from bench.bus.can import protocol as p
    from bench.bus.session import SessionOptions, free_loopback_port, loopback_endpoint, open_session
    from bench.runtime.can_bench import write_scenario
    from bench.runtime.process import start_node

    import bench
    assert Path(bench.__file__).resolve().is_relative_to(tree.resolve()), f"bench imported from {bench.__file__}"
    heartbeat_id = p.Protocol().frame_ids[p.HEARTBEAT]
    work = Path("/dev/shm/can-uml-startup")
    work.mkdir(parents=True, exist_ok=True)
    scenario = write_scenario(work / "scenario", {"transport": "socketcan", "flight_channel": "vcan0",
                                                  "board_channel": "vcan1"})
    hub = loopback_endpoint(free_loopback_port())
    session = open_session(SessionOptions(listen=(hub,)))
    bus = can.Bus(interface="socketcan", channel="vcan1", fd=True, ignore_config=True)
    cli_s, heartbeat_s = [], []
    try:
        for k in range(repeats):
            started = time.monotonic()
            subprocess.run([sys.executable, "-m", "bench.cli", "node", "--help"], capture_output=True, check=True,
                           timeout=HEARTBEAT_WAIT_S)
            cli_s.append(time.monotonic() - started)
            while bus.recv(timeout=0.0) is not None:    # nothing left over from the last start
                pass
            run_dir = work / f"run{k}"
            run_dir.mkdir(exist_ok=True)
            started = time.monotonic()
            proc = start_node("mtq", f"startup-{k}", scenario, hub, run_dir, run_dir / "mtq.log")
            try:
                while True:
                    msg = bus.recv(timeout=0.5)
                    if msg is not None and msg.arbitration_id == heartbeat_id:
                        heartbeat_s.append(time.monotonic() - started)
                        break
                    if proc.poll() is not None or time.monotonic() - started > HEARTBEAT_WAIT_S:
                        raise RuntimeError(f"mtq: no heartbeat (exit {proc.poll()}): "
                                           f"{(run_dir / 'mtq.log').read_text()[-1500:]}")
            finally:
                proc.terminate()
                try:
                    proc.wait(20)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
    finally:
        bus.shutdown()
        session.close()
    return {"tree": str(tree), "cli_help_s": [round(x, 2) for x in cli_s],
            "mtq_first_heartbeat_s": [round(x, 2) for x in heartbeat_s]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tree", type=Path, default=REPO, help="checkout whose bench to start")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--busy", type=int, default=0, help="host processes spinning meanwhile")
    parser.add_argument("--mem", default="384M", help="the guest's memory (tests/uml.py DEFAULT_MEM is the tests')")
    parser.add_argument("--job", type=Path, default=Path("/tmp/can-uml-startup"))
    parser.add_argument("--guest", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    tree = args.tree.resolve()
    if args.guest:
        print("RESULT " + json.dumps(guest(tree, args.repeats)), flush=True)
        return 0
    sys.path.insert(0, str(REPO / "tests"))
    import uml
    uml.ensure_uml()
    load_before = os.getloadavg()[0]
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.busy)]
    try:
        command = ["env", f"PYTHONPATH={tree}", sys.executable, str(Path(__file__).resolve()), "--guest",
                   "--tree", str(tree), "--repeats", str(args.repeats)]
        result = uml.run(command, args.job, timeout_s=120 + args.repeats * 2 * HEARTBEAT_WAIT_S, mem=args.mem)
    finally:
        for proc in busy:
            proc.kill()
            proc.wait()
    line = next((x for x in result.output.splitlines() if x.startswith("RESULT ")), None)
    if line is None:
        print(result.output[-3000:])
        return 1
    figures = json.loads(line[len("RESULT "):])
    print(f"tree {tree} (guest memory {args.mem}, busy host processes: {args.busy}, "
          f"host load average before: {load_before:.1f})")
    for name in ("cli_help_s", "mtq_first_heartbeat_s"):
        values = figures[name]
        print(f"  {name}: median {statistics.median(values):.1f} s, max {max(values):.1f} s, all {values}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
