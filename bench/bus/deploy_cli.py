"""`bench certs` and `bench router`: what a multi-host deployment needs besides its nodes."""
from __future__ import annotations

import logging
import signal
import sys
import threading
from pathlib import Path

from bench.bus import acl
from bench.bus.certs import CertificateError, write_deployment_certs
from bench.bus.deployment import ROUTER, DeploymentError, load_deployment
from bench.bus.session import SessionConfigError, open_session

EXIT_BAD_INPUT = 2


def cmd_certs(args) -> int:
    """A new CA and one certificate per identity, into the deployment's certificate directory."""
    try:
        deployment = load_deployment(args.deployment)
        cert_dir = Path(args.out) if args.out else deployment.cert_dir
        if (cert_dir / "ca.pem").exists() and not args.force:
            raise DeploymentError(f"{cert_dir}/ca.pem exists: a new CA would lock out every host that has the "
                                  f"old one; pass --force to replace it")
        write_deployment_certs(cert_dir, deployment.name, deployment.certificate_addresses(), days=args.days)
    except (DeploymentError, CertificateError, OSError) as exc:
        print(f"bench certs: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f"{cert_dir}: ca.pem, ca.key (keep it off the bench hosts) and "
          f"{', '.join(acl.identities())} (.pem, .key mode 0600), secoc.key (the CAN bus key, mode 0600, for the launcher's host); "
          f"copy ca.pem and each host's own pairs to it")
    return 0


def cmd_router(args) -> int:
    """A Zenoh router on the deployment's router host, until Ctrl-C or SIGTERM."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s", stream=sys.stdout)
    try:
        deployment = load_deployment(args.deployment)
        if deployment.router is None:
            raise DeploymentError("router: the deployment names no router host")
        deployment.check_certificates(deployment.router, [])
        session = open_session(deployment.router_options())
    except (DeploymentError, SessionConfigError) as exc:
        print(f"bench router: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    logging.getLogger("bench.router").info("router %s listening on %s", ROUTER,
                                           ", ".join(deployment.hosts[deployment.router].endpoints))
    try:
        stop.wait()
    finally:
        session.close()
    return 0


def add_commands(subparsers) -> None:
    certs = subparsers.add_parser("certs", help="a certificate authority and one certificate per node for a deployment")
    certs.add_argument("deployment", help="deployment TOML (its `certs` directory receives the files)")
    certs.add_argument("--out", help="certificate directory (default: the deployment's `certs`)")
    certs.add_argument("--days", type=int, default=365, help="validity of every certificate (default 365)")
    certs.add_argument("--force", action="store_true", help="replace an existing CA")
    certs.set_defaults(func=cmd_certs)

    router = subparsers.add_parser("router", help="a Zenoh router for a deployment that names one")
    router.add_argument("--deployment", required=True, help="deployment TOML")
    router.set_defaults(func=cmd_router)
