"""The SecOC key a run's CAN nodes share: the scenario's, the deployment's, or a fresh one per run.

There is no built-in key. A scenario that leaves can.security.key_hex empty (every built-in one)
gets, before its nodes start, the deployment's key (secoc.key beside the certificates, mode 0600,
written by `bench certs`) when the run has a certificate directory, else 16 random bytes from the
operating system's generator. The launcher writes the scenario with the key into the run's
scenario.json with mode 0600, the file every node reads; the recorder leaves the key out of the
MCAP metadata, and neither the report nor the summary prints the scenario.
"""
from __future__ import annotations

import os
import secrets
from pathlib import Path

import msgspec

KEY_BYTES = 16
SCENARIO_FILE_MODE = 0o600


def can_needs_key(can) -> bool:
    """A [can] section on an authenticated profile without its key."""
    return can is not None and can.security.authenticated and not can.security.key_hex


def can_with_key(can, key_hex: str):
    """The [can] section with this SecOC key."""
    return msgspec.structs.replace(can, security=msgspec.structs.replace(can.security, key_hex=key_hex))


def needs_key(scenario) -> bool:
    return can_needs_key(getattr(scenario, "can", None))


def with_run_key(scenario, cert_dir: Path | None = None):
    """The scenario with its SecOC key filled in when it needs one (unchanged otherwise)."""
    if not needs_key(scenario):
        return scenario
    key_hex = None
    if cert_dir is not None:
        from bench.bus.certs import read_secoc_key
        key_hex = read_secoc_key(cert_dir)
    key_hex = key_hex or secrets.token_hex(KEY_BYTES)
    return msgspec.structs.replace(scenario, can=can_with_key(scenario.can, key_hex))


def write_private(path: Path, data: bytes) -> None:
    """Write a file only its owner can read, with mode 0600 from its creation."""
    path = Path(path)
    if path.exists():
        path.unlink()
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, SCENARIO_FILE_MODE)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
