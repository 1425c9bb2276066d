"""Deployment files: which node runs on which host, where each host listens, router or not.

TOML, validated on load like scenarios (`DeploymentError` names the field and the problem, on one
line): at most 64 kB, no type coercion, bounded lengths and counts, nesting limited by the parser
and a depth check of its result, ports 0-65535 in ASCII digits.

```toml
name = "lab"                 # names the certificate authority
certs = "certs/lab"          # certificate directory, relative to this file (`bench certs lab.toml`)
launcher = "sim"             # the host where `bench run` runs (default: the plant's host)
# secure = true              # mutual TLS + access control; default: true when there are 2+ hosts
# router = "sim"             # a host where `bench router` runs; every session connects to it

[hosts.sim]
endpoints = ["tls/10.0.0.1:7447"]
nodes = ["plant", "recorder"]

[hosts.flight]
endpoints = ["tls/10.0.0.2:0"]
nodes = ["controller", "estimator"]
```

How sessions find each other: the rendezvous is the router host's first endpoint when there is a
router, else the launcher host's first endpoint (the hub of `bench run`). Every other session
listens on its host's addresses with an ephemeral port and connects to the rendezvous; gossip
(session.py) then tells each peer the others' addresses, so data flows directly between hosts.
A node the file does not place runs on the launcher's host.
"""
from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Annotated

import msgspec

from bench.bus import acl, toml_input
from bench.bus.certs import CertificateError, Identity, check_identity, identity_files
from bench.bus.session import SessionOptions

LAUNCHER = "launcher"
ROUTER = "router"
# A deployment names a few hosts: these bound what a file can make the loader hold.
MAX_DEPLOYMENT_BYTES = 64 * 1024
MAX_DEPLOYMENT_NESTING = 8      # hosts.NAME.endpoints[i] is 3 levels
MAX_HOSTS = 64


class DeploymentError(ValueError):
    """A deployment that cannot be run, with the field and the problem in the message (one line)."""

    def __init__(self, message: str):
        # What a file put in a key or value (a newline, an escape sequence) shown escaped.
        text = "".join(c if c.isprintable() else repr(c)[1:-1] for c in str(message))
        super().__init__(text if len(text) <= 1000 else text[:997] + "...")


Name = Annotated[str, msgspec.Meta(min_length=1, max_length=64)]
Endpoint = Annotated[str, msgspec.Meta(max_length=256)]


class Host(msgspec.Struct, forbid_unknown_fields=True):
    endpoints: Annotated[list[Endpoint], msgspec.Meta(max_length=16)] = msgspec.field(default_factory=list)
    nodes: Annotated[list[Name], msgspec.Meta(max_length=16)] = msgspec.field(default_factory=list)


class Deployment(msgspec.Struct, forbid_unknown_fields=True):
    name: Name
    hosts: Annotated[dict[Name, Host], msgspec.Meta(max_length=MAX_HOSTS)]
    certs: Annotated[str, msgspec.Meta(max_length=4096)] = "certs"
    launcher: Name | None = None
    router: Name | None = None
    secure: bool | None = None
    # Filled in by load_deployment (not in the file): the directory the file is in.
    base_dir: str = "."

    # --- what the file says, resolved ---------------------------------------------------------
    @property
    def is_secure(self) -> bool:
        return self.secure if self.secure is not None else len(self.hosts) > 1

    @property
    def cert_dir(self) -> Path:
        return (Path(self.base_dir) / self.certs).resolve()

    @property
    def launcher_host(self) -> str:
        if self.launcher is not None:
            return self.launcher
        return self.host_of("plant")

    def host_of(self, node: str) -> str:
        for name, host in self.hosts.items():
            if node in host.nodes:
                return name
        return self.launcher if self.launcher is not None else next(iter(self.hosts))

    def nodes_on(self, host: str, needed: list[str]) -> list[str]:
        return [n for n in needed if self.host_of(n) == host]

    @property
    def rendezvous(self) -> str:
        return self.hosts[self.router or self.launcher_host].endpoints[0]

    def identity(self, name: str) -> Identity | None:
        return identity_files(self.cert_dir, name) if self.is_secure else None

    # --- sessions -----------------------------------------------------------------------------
    def _ephemeral(self, host: str) -> tuple[str, ...]:
        """The host's endpoints with port 0: one more session on the same addresses."""
        return tuple(e.rpartition(":")[0] + ":0" for e in self.hosts[host].endpoints)

    def hub_options(self) -> SessionOptions:
        """The session of `bench run` on the launcher host."""
        host = self.launcher_host
        if self.router:
            return SessionOptions(listen=self._ephemeral(host), connect=(self.rendezvous,), identity=self.identity(LAUNCHER))
        return SessionOptions(listen=tuple(self.hosts[host].endpoints), identity=self.identity(LAUNCHER))

    def node_options(self, node: str, host: str) -> SessionOptions:
        if node not in self.hosts[host].nodes and self.host_of(node) != host:
            raise DeploymentError(f"node {node!r} is not placed on host {host!r} (it runs on {self.host_of(node)!r})")
        return SessionOptions(listen=self._ephemeral(host), connect=(self.rendezvous,), identity=self.identity(node))

    def router_options(self) -> SessionOptions:
        if not self.router:
            raise DeploymentError("deployment has no router (set router = HOST)")
        return SessionOptions(listen=tuple(self.hosts[self.router].endpoints), mode="router",
                              identity=self.identity(ROUTER))

    def identities_on(self, host: str, needed: list[str]) -> list[str]:
        names = list(self.nodes_on(host, needed))
        if host == self.launcher_host:
            names.append(LAUNCHER)
        if host == self.router:
            names.append(ROUTER)
        return names

    def check_certificates(self, host: str, needed: list[str]) -> None:
        """Every certificate the host's sessions present exists, is current and its key private."""
        if not self.is_secure:
            return
        for name in self.identities_on(host, needed):
            try:
                check_identity(self.identity(name))
            except CertificateError as exc:
                raise DeploymentError(f"host {host!r}: {exc}") from exc

    def certificate_addresses(self) -> dict[str, tuple[str, ...]]:
        """Identity -> the addresses it listens on (subject alternative names of its certificate)."""
        addresses = {}
        for name in acl.identities():
            if name == LAUNCHER:
                host = self.launcher_host
            elif name == ROUTER:
                host = self.router or self.launcher_host
            else:
                host = self.host_of(name)
            addresses[name] = tuple(_address(e) for e in self.hosts[host].endpoints)
        return addresses


def _address(endpoint: str) -> str:
    return endpoint.partition("/")[2].rpartition(":")[0].strip("[]")


def _check(d: Deployment) -> None:
    if not d.hosts:
        raise DeploymentError("hosts: at least one host is needed")
    protocol = "tls" if d.is_secure else "tcp"
    placed: dict[str, str] = {}
    for name, host in d.hosts.items():
        if not host.endpoints:
            raise DeploymentError(f"hosts.{name}.endpoints: host {name!r} has no endpoints")
        for endpoint in host.endpoints:
            proto, sep, address = endpoint.partition("/")
            host_part, colon, port = address.rpartition(":")
            valid_port = port.isascii() and port.isdigit() and len(port) <= 5 and int(port) < 65536
            if not sep or not colon or not host_part or not valid_port:
                raise DeploymentError(f"hosts.{name}.endpoints: {endpoint!r} is not of the form {protocol}/ADDRESS:PORT")
            if proto != protocol:
                raise DeploymentError(f"hosts.{name}.endpoints: {endpoint!r} must use {protocol}/ "
                                      f"({'secure' if d.is_secure else 'plain'} deployment)")
        for node in host.nodes:
            if node not in acl.ROLES or node in (LAUNCHER, ROUTER):
                known = ", ".join(n for n in acl.ROLES if n not in (LAUNCHER, ROUTER))
                raise DeploymentError(f"hosts.{name}.nodes: unknown node {node!r} (known: {known})")
            if node in placed:
                raise DeploymentError(f"hosts.{name}.nodes: node {node!r} is on two hosts ({placed[node]!r} and {name!r})")
            placed[node] = name
    for field_name in ("launcher", "router"):
        value = getattr(d, field_name)
        if value is not None and value not in d.hosts:
            raise DeploymentError(f"{field_name}: {value!r} is not one of the hosts ({', '.join(d.hosts)})")
    if d.launcher is None and "plant" not in placed and len(d.hosts) > 1:
        raise DeploymentError("launcher: name the host where `bench run` runs (or place the plant)")
    rendezvous_port = d.rendezvous.rpartition(":")[2]
    if rendezvous_port == "0":
        raise DeploymentError(f"hosts.{d.router or d.launcher_host}.endpoints: the rendezvous endpoint "
                              f"{d.rendezvous!r} needs a fixed port (the other hosts connect to it)")


def _deeper_than(value, limit: int) -> str | None:
    """Path of the first value nested deeper than `limit` tables and arrays, else None."""
    stack = [("", value, 0)]
    while stack:
        where, item, depth = stack.pop()
        if isinstance(item, (dict, list)):
            if depth >= limit:
                return where.lstrip(".") or "<root>"
            items = item.items() if isinstance(item, dict) else enumerate(item)
            stack.extend((f"{where}.{k}" if isinstance(item, dict) else f"{where}[{k}]", v, depth + 1) for k, v in items)
    return None


def _read(path: Path) -> dict:
    """The file parsed by tomllib, whose limits (a syntax error, a key given twice, an integer too
    long to convert, a nesting that exhausts its recursion) and ours (size, depth) become one-line
    DeploymentErrors, naming the key where tomllib's frames tell it (bench/bus/toml_input.py)."""
    where = f"deployment file {str(path)!r}"
    try:
        if not path.is_file():
            raise DeploymentError(f"{where} does not exist")
        size = path.stat().st_size
        if size > MAX_DEPLOYMENT_BYTES:
            raise DeploymentError(f"{where}: {size} bytes; a deployment file may hold at most {MAX_DEPLOYMENT_BYTES}")
        text = path.read_text(errors="replace")
    except (OSError, ValueError) as exc:   # unreadable, a NUL in the name
        if isinstance(exc, DeploymentError):
            raise
        raise DeploymentError(f"{where}: {exc}") from None
    try:
        raw = tomllib.loads(text)
    except ValueError as exc:     # TOMLDecodeError, or an integer too long to convert
        raise DeploymentError(f"{where}: {toml_input.field(exc, text)}: {toml_input.problem(exc)}") from None
    except RecursionError:
        raise DeploymentError(f"{where}: nested deeper than {MAX_DEPLOYMENT_NESTING} levels (too deep for the "
                              "TOML parser)") from None
    deep = _deeper_than(raw, MAX_DEPLOYMENT_NESTING)
    if deep is not None:
        raise DeploymentError(f"{where}: {deep}: nested deeper than {MAX_DEPLOYMENT_NESTING} levels")
    return raw


def load_deployment(path: str | Path) -> Deployment:
    """Read and validate a deployment file; DeploymentError names the field."""
    path = Path(path)
    raw = _read(path)
    raw["base_dir"] = str(path.resolve().parent)

    def convert(value, kind, prefix: str):
        try:
            return msgspec.convert(value, kind, strict=True)
        except msgspec.ValidationError as exc:
            # msgspec says "Expected `str` - at `$.nodes[0]`"; lead with the field.
            problem, at, where = str(exc).rpartition(" - at `$")
            field = prefix + where.rstrip("`") if at else prefix.rstrip(".")
            raise DeploymentError(f"deployment file {str(path)!r}: {field or '<root>'}: {problem if at else exc}") from None

    hosts = raw.get("hosts")
    if isinstance(hosts, dict) and len(hosts) <= MAX_HOSTS:
        # One host at a time, so that a message names the host (msgspec says hosts[...]).
        for name, host in hosts.items():
            convert(host, Host, f"hosts.{name}")
    deployment = convert(raw, Deployment, "")
    _check(deployment)
    return deployment


def local_deployment(cert_dir: Path, port: int, secure: bool) -> Deployment:
    """`bench run` on one host: the hub on loopback `port`, every node on loopback."""
    protocol = "tls" if secure else "tcp"
    return Deployment(name="local", hosts={"local": Host(endpoints=[f"{protocol}/127.0.0.1:{port}"])},
                      certs=str(cert_dir), launcher="local", secure=secure, base_dir="/")
