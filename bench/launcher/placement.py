"""Where a run's sessions are: the hub on this host's loopback (plain, or mutual TLS with
certificates made for the run), or a deployment file's hosts, with the nodes on other hosts."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from bench.bus import acl
from bench.bus.certs import identity_files, write_deployment_certs
from bench.bus.deployment import LAUNCHER, Deployment, DeploymentError
from bench.bus.session import SessionOptions, free_loopback_port, loopback_endpoint


@dataclass
class Placement:
    """Where this run's sessions are: the hub's session options, what each local node is told,
    and which nodes run on other hosts (node -> host). Local and plain unless asked otherwise."""

    hub: SessionOptions
    hub_endpoint: str
    node_args: list[str]
    remote: dict[str, str]


def local_placement(port: int | None, zenoh_config: str | None, cert_dir: Path | None = None) -> Placement:
    """`bench run` on this host: the hub on loopback; with cert_dir, mutual TLS and access control."""
    protocol = "tls" if cert_dir else "tcp"
    hub = loopback_endpoint(port or free_loopback_port(), protocol)
    identity = identity_files(cert_dir, LAUNCHER) if cert_dir else None
    options = SessionOptions(listen=(hub,), config_file=Path(zenoh_config) if zenoh_config else None, identity=identity)
    return Placement(options, hub, ["--cert-dir", str(cert_dir)] if cert_dir else [], {})


def deployment_placement(deployment: Deployment, deployment_file: Path, names: list[str],
                         zenoh_config: str | None) -> Placement:
    host = deployment.launcher_host
    if deployment.host_of("plant") != host:
        raise DeploymentError(f"the plant runs on {deployment.host_of('plant')!r}: it must be on the launcher's "
                              f"host {host!r} (the launcher follows the plant's progress)")
    deployment.check_certificates(host, names)
    options = dataclasses.replace(deployment.hub_options(), config_file=Path(zenoh_config) if zenoh_config else None)
    remote = {n: deployment.host_of(n) for n in names if deployment.host_of(n) != host}
    return Placement(options, deployment.rendezvous, ["--deployment", str(Path(deployment_file).resolve()), "--host", host],
                     remote)


def make_local_certs(cert_dir: Path) -> Path:
    """A throw-away CA and certificates for one secure local run (`bench run --secure`)."""
    write_deployment_certs(cert_dir, "local", {name: ("127.0.0.1",) for name in acl.identities()})
    return cert_dir
