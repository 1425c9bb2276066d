"""What mutual TLS and a hop between hosts cost: one-hop latency and lock-step loop rate.

    .venv/bin/python benchmarks/bench_deployment.py                  # needs root (network namespaces)
    .venv/bin/python benchmarks/bench_deployment.py --pings 1000 --rounds 1

In one invocation, so every configuration sees the same machine load:

- one-hop latency: a pinger session publishes a stamp, an echo session (another process) puts it
  straight back; one hop = round trip / 2, on the pinger's clock only (no offset to remove).
  Configurations: loopback TCP, loopback TLS (mutual, with the access-control table), and across
  two network namespaces joined by veth pairs and a bridge, TCP and TLS.
- lock-step loop rate: the default rendezvous (288 steps) through `bench run`: on loopback plain
  and `--secure`, and deployed over three namespaces (plant+recorder, controller, estimator)
  plain and secure. Rate = steps per second between the plant's first and last sensing stamps
  (process start-up excluded).

Rounds alternate the configurations (ABCD ABCD ...). Printed: median, p90, p99 per configuration
and the ratios to loopback TCP measured in the same run.
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from bench.bus import acl
from bench.bus.certs import identity_files, write_deployment_certs
from bench.bus.session import SessionOptions, free_loopback_port, open_session
from bench.runtime.netns import NetnsLab, deployment_toml, netns_available, run_deployment

PING_KEY = "bench/bench-deployment/ping"
PONG_KEY = "bench/bench-deployment/pong"


# --- the two ends of the ping-pong (run as `bench_deployment.py pinger|echo ...`) ----------------
def _options(listen: str | None, connect: str | None, cert_dir: str | None, name: str) -> SessionOptions:
    return SessionOptions(listen=(listen,) if listen else (), connect=(connect,) if connect else (),
                          identity=identity_files(Path(cert_dir), name) if cert_dir else None)


def echo_main(args) -> int:
    # The echo is the controller's identity, the pinger the plant's; the ping-pong keys are granted
    # to those roles for this benchmark only (_bench_roles), so TLS runs with the full ACL.
    session = open_session(_options(None, args.connect, args.cert_dir, "controller"))
    publisher = session.declare_publisher(PONG_KEY)
    session.declare_subscriber(PING_KEY, lambda s: publisher.put(s.payload.to_bytes()))
    sys.stdin.read()   # until the pinger's parent closes our stdin
    session.close()
    return 0


def pinger_main(args) -> int:
    import threading

    session = open_session(_options(args.listen, None, args.cert_dir, "plant"))
    publisher = session.declare_publisher(PING_KEY)
    got = threading.Event()
    arrived = {}

    def on_pong(sample) -> None:
        arrived["t1"] = time.monotonic_ns()
        got.set()

    session.declare_subscriber(PONG_KEY, on_pong)
    deadline = time.monotonic() + 60
    while not publisher.matching_status.matching:   # the echo is up
        if time.monotonic() > deadline:
            print(json.dumps({"error": "no echo"}))
            return 1
        time.sleep(0.01)
    time.sleep(0.5)
    one_hop_us = []
    for i in range(args.pings + 20):
        got.clear()
        t0 = time.monotonic_ns()
        publisher.put(str(t0).encode())
        if not got.wait(2.0):
            continue
        if i >= 20:   # warm-up
            one_hop_us.append((arrived["t1"] - t0) / 2e3)
        time.sleep(0.002)
    print(json.dumps({"one_hop_us": one_hop_us}))
    session.close()
    return 0


# --- orchestration ------------------------------------------------------------------------------
def _bench_roles() -> None:
    """Grant the ping-pong keys to the two identities the benchmark uses (each process of the
    ping-pong calls this before it opens its session)."""

    acl.ROLES["plant"] = acl.Role(publishes=acl.ROLES["plant"].publishes + ("ping",),
                                  subscribes=acl.ROLES["plant"].subscribes + ("pong",))
    acl.ROLES["controller"] = acl.Role(publishes=acl.ROLES["controller"].publishes + ("pong",),
                                       subscribes=acl.ROLES["controller"].subscribes + ("ping",),
                                       can_channels=acl.ROLES["controller"].can_channels)


def ping_pong(lab: NetnsLab | None, secure: bool, cert_dir: Path, pings: int) -> np.ndarray:
    me = [sys.executable, str(Path(__file__).resolve())]
    protocol = "tls" if secure else "tcp"
    certs = ["--cert-dir", str(cert_dir)] if secure else []
    if lab is None:
        address, wrap_a, wrap_b = "127.0.0.1", (lambda c: c), (lambda c: c)
    else:
        address = lab.address["sim"]
        wrap_a, wrap_b = (lambda c: lab.command("sim", c)), (lambda c: lab.command("flight", c))
    port = free_loopback_port() if lab is None else 7448
    endpoint = f"{protocol}/{address}:{port}"
    pinger = subprocess.Popen(wrap_a([*me, "pinger", "--listen", endpoint, "--pings", str(pings), *certs]),
                              stdout=subprocess.PIPE, text=True)
    echo = subprocess.Popen(wrap_b([*me, "echo", "--connect", endpoint, *certs]), stdin=subprocess.PIPE)
    try:
        out, _ = pinger.communicate(timeout=600)
    finally:
        echo.stdin.close()
        echo.wait(timeout=30)
    result = json.loads(out.strip().splitlines()[-1])
    if "error" in result:
        raise RuntimeError(result["error"])
    return np.array(result["one_hop_us"])


def loop_rate(trajectory_path: Path) -> float:
    with np.load(trajectory_path) as data:
        sensed = data["stamp_sensed_ns"]
    sensed = sensed[sensed >= 0]
    return (len(sensed) - 1) / ((sensed[-1] - sensed[0]) / 1e9)


def lockstep_local(runs_dir: Path, run_id: str, secure: bool) -> float:
    cmd = [sys.executable, "-m", "bench.cli", "run", "--run-id", run_id, "--runs-dir", str(runs_dir), "--no-progress",
           "--no-report", *(["--secure"] if secure else [])]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    if result.returncode != 0:
        raise RuntimeError(result.stderr)
    return loop_rate(runs_dir / run_id / "trajectory.npz")


PLACEMENT = {"sim": ["plant", "recorder"], "flight": ["controller"], "est": ["estimator"]}


def lockstep_netns(lab: NetnsLab, work: Path, runs_dir: Path, run_id: str, secure: bool) -> float:
    deployment = work / f"deploy-{'tls' if secure else 'tcp'}.toml"
    deployment.write_text(deployment_toml(lab, PLACEMENT, "sim", secure, certs=str(work / "certs")))
    result, codes = run_deployment(lab, deployment, PLACEMENT, "sim", run_id, runs_dir, ["--no-report"])
    if result.returncode != 0 or any(c != 0 for c in codes.values()):
        raise RuntimeError(f"{result.stderr} {codes}")
    return loop_rate(runs_dir / run_id / "trajectory.npz")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="role")
    p = sub.add_parser("pinger")
    p.add_argument("--listen", required=True)
    p.add_argument("--pings", type=int, default=2000)
    p.add_argument("--cert-dir")
    e = sub.add_parser("echo")
    e.add_argument("--connect", required=True)
    e.add_argument("--cert-dir")
    parser.add_argument("--pings", type=int, default=2000, help="pings per configuration and round")
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args()
    _bench_roles()
    if args.role == "pinger":
        return pinger_main(args)
    if args.role == "echo":
        return echo_main(args)

    reason = netns_available()
    if reason:
        print(f"bench_deployment: {reason}", file=sys.stderr)
        return 2
    work = Path(tempfile.mkdtemp(prefix="bench-deployment-"))
    runs_dir = work / "runs"
    console = Console(width=130)
    hops: dict[str, list] = {}
    rates: dict[str, list] = {}
    try:
        with NetnsLab(list(PLACEMENT)) as lab:
            write_deployment_certs(work / "certs", "bench", {n: ("127.0.0.1", *lab.address.values())
                                                             for n in acl.identities()})
            for r in range(args.rounds):
                for name, (where, secure) in {"loopback TCP": (None, False), "loopback TLS+ACL": (None, True),
                                              "2 namespaces TCP": (lab, False), "2 namespaces TLS+ACL": (lab, True)}.items():
                    hops.setdefault(name, []).append(ping_pong(where, secure, work / "certs", args.pings))
                    console.print(f"round {r}: {name}: median one hop {np.median(hops[name][-1]):.0f} us")
                for name, run in {"loopback": lambda i: lockstep_local(runs_dir, f"lo-tcp-{i}", False),
                                  "loopback --secure": lambda i: lockstep_local(runs_dir, f"lo-tls-{i}", True),
                                  "3 namespaces TCP": lambda i: lockstep_netns(lab, work, runs_dir, f"ns-tcp-{i}", False),
                                  "3 namespaces TLS+ACL": lambda i: lockstep_netns(lab, work, runs_dir, f"ns-tls-{i}", True),
                                  }.items():
                    try:
                        rate = run(r)
                    except RuntimeError as exc:
                        # On a loaded machine the launcher's hang check can misfire at the very end
                        # (the plant's token gone, its interpreter still exiting): note it, run again.
                        console.print(f"round {r}: {name}: failed ({str(exc).strip()}); once more")
                        rate = run(f"{r}b")
                    rates.setdefault(name, []).append(rate)
                    console.print(f"round {r}: {name}: {rates[name][-1]:.1f} steps/s")
    finally:
        shutil.rmtree(work, ignore_errors=True)

    base = np.concatenate(hops["loopback TCP"])
    table = Table(title=f"one hop (round trip / 2), {args.rounds} x {args.pings} pings")
    for column in ("configuration", "n", "median us", "p90 us", "p99 us", "median ratio", "p99 ratio"):
        table.add_column(column, justify="right")
    for name, runs in hops.items():
        x = np.concatenate(runs)
        table.add_row(name, str(len(x)), f"{np.median(x):.0f}", f"{np.percentile(x, 90):.0f}", f"{np.percentile(x, 99):.0f}",
                      f"{np.median(x) / np.median(base):.2f}", f"{np.percentile(x, 99) / np.percentile(base, 99):.2f}")
    console.print(table)
    base_rate = np.median(rates["loopback"])
    table = Table(title="lock-step loop rate, default rendezvous (288 steps), plant's sensing stamps")
    for column in ("configuration", "runs (steps/s)", "median steps/s", "ratio to loopback"):
        table.add_column(column, justify="right")
    for name, values in rates.items():
        table.add_row(name, ", ".join(f"{v:.1f}" for v in values), f"{np.median(values):.1f}",
                      f"{np.median(values) / base_rate:.2f}")
    console.print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
