"""The one place a Zenoh session is opened in this project.

Zenoh's default configuration scouts by UDP multicast and listens on every interface. A test
bench must not announce itself on the host's network, so every session here is built from an
explicit configuration: multicast scouting off, gossip on (peers that know one endpoint find the
rest through it), loopback listen endpoints unless the user names others, and a short liveliness
lease (the run's `[run.liveliness] lease_s`) so a dead or hung peer is noticed within seconds.
Secure sessions (an `identity`: the node's certificate, key and the deployment's CA, see
certs.py) speak TLS only, with mutual authentication, and carry the bench's access-control table
(acl.py), so every process enforces on each of its links who may say and hear what.
"""
from __future__ import annotations

import json
import socket
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from bench.bus import acl
from bench.bus.certs import CertificateError, Identity, check_identity

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
    # Mutual TLS with this identity's certificate (CN = the node name) and the deployment's CA.
    identity: Identity | None = None
    # With an identity: enforce the bench's access-control table (acl.ROLES) on every link. Only
    # tests that play a rogue process turn it off.
    access_control: bool = True

    @property
    def secure(self) -> bool:
        return self.identity is not None

    @property
    def link_protocol(self) -> str:
        return "tls" if self.secure else "tcp"


@dataclass
class _Checked:
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)


def loopback_endpoint(port: int, protocol: str = "tcp") -> str:
    return f"{protocol}/{LOOPBACK_HOST}:{port}"


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
    if proto not in ("tcp", "tls"):
        return
    host, _, port_text = address.partition("#")[0].rpartition(":")
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


def plain_settings(mode: str, listen: list[str], connect: list[str], lease_ms: int) -> dict[str, str]:
    """The settings every bench session gets (JSON5 text by Zenoh config key), TLS aside; also what
    the published contract tells an outside node to use (bench.contract.document)."""
    return {
        "mode": json.dumps(mode),
        "scouting/multicast/enabled": "false",
        "scouting/gossip/enabled": "true",
        "listen/endpoints": json.dumps(listen if mode != "client" else []),
        "connect/endpoints": json.dumps(connect),
        "transport/link/tx/lease": str(lease_ms),
        "transport/link/tx/keep_alive": str(KEEP_ALIVE_PER_LEASE),
        # The bench's own processes must not share memory by accident; keep transport plain.
        "transport/shared_memory/enabled": "false",
        "adminspace/enabled": "false",
    }


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
        listen=[_validate_endpoint(e) for e in options.listen] or [loopback_endpoint(0, options.link_protocol)],
        connect=[_validate_endpoint(e) for e in options.connect],
    )
    if not 100 <= options.lease_ms <= 60_000:
        raise SessionConfigError(f"lease of {options.lease_ms} ms is outside 100-60000 ms")
    if options.mode not in {"peer", "client", "router"}:
        raise SessionConfigError(f"zenoh mode {options.mode!r} must be 'peer', 'client' or 'router'")
    settings = plain_settings(options.mode, checked.listen, checked.connect, options.lease_ms)
    if options.secure:
        settings.update(_tls_settings(options, checked))
    for key, value in settings.items():
        config.insert_json5(key, value)
    return config


def _tls_settings(options: SessionOptions, checked: _Checked) -> dict[str, str]:
    """Mutual TLS on every link, nothing else, and the access-control table.

    verify_name_on_connect is off: a bench host is named by its address in the deployment file,
    not by DNS, and what a peer may do is decided by the CN of the certificate it proved it holds
    (enable_mtls), which the access-control table keys on. close_link_on_expiration drops a link
    whose peer's certificate expires during a run.
    """
    plain = [e for e in checked.listen + checked.connect if not e.startswith("tls/")]
    if plain:
        raise SessionConfigError(f"endpoint {plain[0]!r}: a secure session uses tls/ endpoints only")
    identity = options.identity
    try:
        check_identity(identity)
    except CertificateError as exc:
        raise SessionConfigError(str(exc)) from exc
    tls = {
        "root_ca_certificate": str(identity.ca_path),
        "listen_certificate": str(identity.cert_path),
        "listen_private_key": str(identity.key_path),
        "connect_certificate": str(identity.cert_path),
        "connect_private_key": str(identity.key_path),
        "enable_mtls": True,
        "verify_name_on_connect": False,
        "close_link_on_expiration": True,
    }
    settings = {"transport/link/protocols": json.dumps(["tls"]), "transport/link/tls": json.dumps(tls)}
    if options.access_control:
        settings["access_control"] = json.dumps(acl.access_control_config())
    return settings


# Zenoh's own log (it writes to stdout), for secure sessions: the TLS listener's line naming why it refused a
# peer ("invalid peer certificate: certificate expired ...", "... UnknownIssuer") is the one a
# user needs; everything else stays at error. RUST_LOG overrides it.
TLS_LOG_FILTER = "error,zenoh_link_tls::unicast=warn"
_log_initialised = False


def _init_tls_log() -> None:
    global _log_initialised
    if not _log_initialised:
        zenoh.init_log_from_env_or(TLS_LOG_FILTER)
        _log_initialised = True


def open_session(options: SessionOptions | None = None) -> zenoh.Session:
    """Open a Zenoh session with the bench's safe configuration.

    Raises SessionConfigError with one readable line for a bad endpoint or a taken port.
    """
    options = options or SessionOptions()
    for endpoint in options.listen:
        check_port_free(_validate_endpoint(endpoint))
    config = build_config(options)
    if options.secure:
        _init_tls_log()
    try:
        return zenoh.open(config)
    except Exception as exc:
        raise SessionConfigError(f"could not open zenoh session ({options.listen or 'ephemeral'}): {exc}") from exc
