"""The one place a Zenoh session is opened in this project.

Zenoh's default configuration scouts by UDP multicast and listens on every interface. A test
bench must not announce itself on the host's network, so every session here is built from an
explicit configuration: multicast scouting off, gossip on (peers that know one endpoint find the
rest through it), loopback listen endpoints unless the user names others, and a short liveliness
lease (the run's `[run.liveliness] lease_s`) so a dead or hung peer is noticed within seconds.
"""
from __future__ import annotations

import json
import socket
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

LOOPBACK_HOST = "127.0.0.1"
# Liveliness lease: tokens of a peer that stops answering vanish after about this long. A bench
# run passes its scenario's [run.liveliness] lease_s; 2 s survives four concurrent lock-step runs
# on two busy cores (benchmarks/bench_concurrent_runs.py), where 600 ms did not (a 534 ms stall).
LEASE_MS = 2000
KEEP_ALIVE_PER_LEASE = 4


class SessionConfigError(ValueError):
    """A session option the user gave is wrong (bad endpoint, unreadable file, port in use)."""


@dataclass(frozen=True)
class SessionOptions:
    """Where a bench process listens and whom it connects to.

    listen: endpoints such as ``tcp/127.0.0.1:7447``. Empty means one ephemeral loopback port.
    connect: endpoints of a router or of peers on other hosts.
    config_file: a JSON5 Zenoh configuration for anything else; applied first, then the bench's
    safety settings (scouting, gossip, lease) and the endpoints above on top of it.
    """

    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    config_file: Path | None = None
    mode: str = "peer"
    lease_ms: int = LEASE_MS


@dataclass
class _Checked:
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)


def loopback_endpoint(port: int) -> str:
    return f"tcp/{LOOPBACK_HOST}:{port}"


def free_loopback_port() -> int:
    """A TCP port on loopback that nobody listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((LOOPBACK_HOST, 0))
        return s.getsockname()[1]


def check_port_free(endpoint: str) -> None:
    """Raise SessionConfigError naming the endpoint if its TCP port is taken.

    Zenoh reports a taken port deep inside its own error text; a user deserves one line.
    """
    proto, _, address = endpoint.partition("/")
    if proto != "tcp":
        return
    host, _, port_text = address.rpartition(":")
    host = host.strip("[]")
    try:
        port = int(port_text)
    except ValueError as exc:
        raise SessionConfigError(f"endpoint {endpoint!r}: port {port_text!r} is not a number") from exc
    if port == 0:
        return
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as exc:
            raise SessionConfigError(
                f"port {port} on {host} is already in use ({exc.strerror}); "
                f"choose another with --port or stop the process holding it"
            ) from exc


def _validate_endpoint(endpoint: str) -> str:
    proto, sep, address = endpoint.partition("/")
    if not sep or proto not in {"tcp", "udp", "tls", "quic", "unixsock-stream", "ws"} or not address:
        raise SessionConfigError(
            f"endpoint {endpoint!r} is not of the form tcp/HOST:PORT (e.g. tcp/127.0.0.1:7447)"
        )
    return endpoint


def build_config(options: SessionOptions) -> zenoh.Config:
    """Zenoh configuration for one bench process; never Zenoh's defaults."""
    if options.config_file is not None:
        path = Path(options.config_file)
        if not path.is_file():
            raise SessionConfigError(f"zenoh config file {str(path)!r} does not exist")
        try:
            config = zenoh.Config.from_file(str(path))
        except Exception as exc:  # zenoh raises its own ZError with the parser's message
            raise SessionConfigError(f"zenoh config file {str(path)!r} is invalid: {exc}") from exc
    else:
        config = zenoh.Config()
    checked = _Checked(
        listen=[_validate_endpoint(e) for e in options.listen] or [loopback_endpoint(0)],
        connect=[_validate_endpoint(e) for e in options.connect],
    )
    if not 100 <= options.lease_ms <= 60_000:
        raise SessionConfigError(f"lease of {options.lease_ms} ms is outside 100-60000 ms")
    if options.mode not in {"peer", "client"}:
        raise SessionConfigError(f"zenoh mode {options.mode!r} must be 'peer' or 'client'")
    settings = {
        "mode": json.dumps(options.mode),
        "scouting/multicast/enabled": "false",
        "scouting/gossip/enabled": "true",
        "listen/endpoints": json.dumps(checked.listen if options.mode == "peer" else []),
        "connect/endpoints": json.dumps(checked.connect),
        "transport/link/tx/lease": str(options.lease_ms),
        "transport/link/tx/keep_alive": str(KEEP_ALIVE_PER_LEASE),
        # The bench's own processes must not share memory by accident; keep transport plain.
        "transport/shared_memory/enabled": "false",
        "adminspace/enabled": "false",
    }
    for key, value in settings.items():
        config.insert_json5(key, value)
    return config


def open_session(options: SessionOptions | None = None) -> zenoh.Session:
    """Open a Zenoh session with the bench's safe configuration.

    Raises SessionConfigError with one readable line for a bad endpoint or a taken port.
    """
    options = options or SessionOptions()
    for endpoint in options.listen:
        check_port_free(_validate_endpoint(endpoint))
    config = build_config(options)
    try:
        return zenoh.open(config)
    except Exception as exc:
        raise SessionConfigError(f"could not open zenoh session ({options.listen or 'ephemeral'}): {exc}") from exc
