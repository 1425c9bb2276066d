"""Hosts on one machine, for tests and benchmarks: Linux network namespaces joined by veth pairs.

Each host is a namespace with one interface `eth0` (10.<a>.<b>.<i>/24) whose veth peer sits on a
bridge in a namespace of its own (the "switch"), so every host reaches every other and nothing
else: the addresses exist only inside these namespaces. `with NetnsLab(["sim", "flight"]) as lab`
creates them and deletes every namespace on exit, also when the body raises; `lab.run(host, cmd)`
/ `lab.popen(host, cmd)` run a command inside a host. Needs root and iproute2.
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import threading
import sys
import time
from pathlib import Path


def netns_available() -> str | None:
    """None if namespaces can be made here, else the reason."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("ip") is None:
        return "iproute2 (`ip`) is not installed"
    probe = f"bprobe{os.getpid()}"
    made = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if made.returncode != 0:
        return f"ip netns add failed: {made.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


def _exit_on_sigterm(signum, _frame):
    raise SystemExit(128 + signum)


def _ip(*args: str) -> None:
    result = subprocess.run(["ip", *args], capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {result.stderr.strip()}")


class NetnsLab:
    def __init__(self, hosts: list[str], subnet: str | None = None):
        tag = f"{os.getpid() % 100000}"
        self.hosts = list(hosts)
        self.netns = {h: f"b{tag}{h[:6]}" for h in self.hosts}
        self.switch = f"b{tag}sw"
        self.subnet = subnet or f"10.{200 + os.getpid() % 50}.{os.getpid() % 250}"
        self.address = {h: f"{self.subnet}.{i + 1}" for i, h in enumerate(self.hosts)}
        self._made: list[str] = []
        self._previous_sigterm = None

    def __enter__(self) -> "NetnsLab":
        # SIGTERM (a `timeout`, a CI cancel) would end Python without running __exit__ and leave
        # the namespaces behind: turn it into SystemExit while the lab exists.
        self._previous_sigterm = None
        if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:
            self._previous_sigterm = signal.signal(signal.SIGTERM, _exit_on_sigterm)
        try:
            self._create()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _create(self) -> None:
        _ip("netns", "add", self.switch)
        self._made.append(self.switch)
        _ip("-n", self.switch, "link", "add", "br0", "type", "bridge")
        _ip("-n", self.switch, "link", "set", "br0", "up")
        for i, host in enumerate(self.hosts):
            ns = self.netns[host]
            _ip("netns", "add", ns)
            self._made.append(ns)
            _ip("-n", ns, "link", "set", "lo", "up")
            # Created inside the host namespace, its peer moved straight to the switch.
            _ip("-n", ns, "link", "add", "eth0", "type", "veth", "peer", "name", f"p{i}", "netns", self.switch)
            _ip("-n", ns, "addr", "add", f"{self.address[host]}/24", "dev", "eth0")
            _ip("-n", ns, "link", "set", "eth0", "up")
            _ip("-n", self.switch, "link", "set", f"p{i}", "master", "br0")
            _ip("-n", self.switch, "link", "set", f"p{i}", "up")

    def close(self) -> None:
        for ns in reversed(self._made):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        self._made.clear()
        if self._previous_sigterm is not None:
            signal.signal(signal.SIGTERM, self._previous_sigterm)
            self._previous_sigterm = None

    def command(self, host: str, cmd: list[str]) -> list[str]:
        return ["ip", "netns", "exec", self.netns[host], *cmd]

    def popen(self, host: str, cmd: list[str], **kwargs) -> subprocess.Popen:
        return subprocess.Popen(self.command(host, cmd), **kwargs)

    def run(self, host: str, cmd: list[str], **kwargs) -> subprocess.CompletedProcess:
        return subprocess.run(self.command(host, cmd), capture_output=True, text=True, **kwargs)

    def wait_listening(self, host: str, port: int, timeout_s: float = 60.0, proc: subprocess.Popen | None = None) -> None:
        """Until something listens on TCP `port` inside `host` (or `proc` exits)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if proc is not None and proc.poll() is not None:
                raise RuntimeError(f"process exited with {proc.returncode} before listening on {port}")
            out = self.run(host, ["ss", "-Hltn", f"sport = :{port}"]).stdout
            if out.strip():
                return
            time.sleep(0.1)
        raise TimeoutError(f"nothing listens on {host}:{port} after {timeout_s} s")


# ------------------------------------------------------------------------------------------------
# A deployment across the lab's hosts
# ------------------------------------------------------------------------------------------------
def deployment_toml(lab: NetnsLab, placement: dict[str, list[str]], launcher: str, secure: bool,
                    hub_port: int = 7447, certs: str = "certs", router: str | None = None) -> str:
    """A deployment file for `placement` (host -> nodes) on the lab's addresses."""
    protocol = "tls" if secure else "tcp"
    lines = ['name = "netns"', f'certs = "{certs}"', f'launcher = "{launcher}"', f"secure = {str(secure).lower()}"]
    if router:
        lines.append(f'router = "{router}"')
    for host in lab.hosts:
        port = hub_port if host in (launcher, router) else 0
        nodes = ", ".join(f'"{n}"' for n in placement.get(host, []))
        lines += [f"[hosts.{host}]", f'endpoints = ["{protocol}/{lab.address[host]}:{port}"]', f"nodes = [{nodes}]"]
    return "\n".join(lines) + "\n"


def run_deployment(lab: NetnsLab, deployment_file: Path, placement: dict[str, list[str]], launcher: str,
                   run_id: str, runs_dir: Path, run_args: list[str] = (), hub_port: int = 7447,
                   timeout_s: float = 600.0, router: str | None = None) -> tuple[subprocess.CompletedProcess, dict[str, int]]:
    """`bench run --deployment` in the launcher's namespace, `bench node` for every node placed on
    another host in its namespace (and `bench router` first on the router's host, if there is one).
    Returns the launcher's result and each remote node's exit code. Every process is killed on the
    way out if it is still running."""
    bench = [sys.executable, "-m", "bench.cli"]
    run_dir = Path(runs_dir) / run_id
    router_proc = None
    if router:
        router_log = Path(runs_dir) / f"{run_id}-router.log"
        router_log.parent.mkdir(parents=True, exist_ok=True)
        with open(router_log, "w") as log:
            router_proc = lab.popen(router, [*bench, "router", "--deployment", str(deployment_file)],
                                    stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        lab.wait_listening(router, hub_port, proc=router_proc)
    launcher_proc = lab.popen(launcher, [*bench, "run", "--deployment", str(deployment_file), "--run-id", run_id,
                                         "--runs-dir", str(runs_dir), "--no-progress", *run_args],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    remote: dict[str, subprocess.Popen] = {}
    try:
        if not router:
            lab.wait_listening(launcher, hub_port, proc=launcher_proc)
        scenario = run_dir / "scenario.json"
        deadline = time.monotonic() + 60
        while not scenario.exists():
            if launcher_proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"launcher wrote no {scenario}: {launcher_proc.communicate()}")
            time.sleep(0.05)
        (run_dir / "logs").mkdir(parents=True, exist_ok=True)
        for host, nodes in placement.items():
            if host == launcher:
                continue
            for node in nodes:
                log = open(run_dir / "logs" / f"{node}.log", "w")
                remote[node] = lab.popen(host, [*bench, "node", node, "--run-id", run_id, "--scenario", str(scenario),
                                                "--deployment", str(deployment_file), "--host", host,
                                                "--run-dir", str(run_dir)],
                                         stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
                log.close()
        out, err = launcher_proc.communicate(timeout=timeout_s)
        codes = {}
        for node, proc in remote.items():
            try:
                codes[node] = proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                codes[node] = None
        return subprocess.CompletedProcess(launcher_proc.args, launcher_proc.returncode, out, err), codes
    finally:
        for proc in [launcher_proc, *remote.values()]:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        if router_proc is not None:
            router_proc.terminate()   # `bench router` stops cleanly on SIGTERM
            try:
                router_proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                router_proc.kill()
                router_proc.wait()
