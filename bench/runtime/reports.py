"""Reports a node makes to the launcher that started it, signed so that nobody else can make them.

A node's ProcessStats (its counters, sent once as it stops) and the plant's StepDone (its progress,
and the end of the run) go over the bus, where any peer of a plain run can publish under any name.
The launcher therefore draws a fresh secret for each process it starts (`new_report_key`) and hands
it over in the process's environment (REPORT_KEY_ENV; readable by the same user only, never on the
command line); the node signs its reports with it (`sign`: HMAC-SHA256 over the message with an
empty `mac`), and the launcher takes a report as that process's only if `is_signed_by` its key.

The key is per run and per process: a signed report of one run is worthless in another, and one
process cannot sign for another. A node started by hand or on another host has no key and signs
nothing (there, mutual TLS and access control decide who may speak: docs/security.md).
"""
from __future__ import annotations

import hashlib
import hmac
import os
import secrets
from typing import TypeVar

import msgspec

from bench.bus.schemas import ProcessStats, StepDone, encode

REPORT_KEY_ENV = "BENCH_REPORT_KEY"
REPORT_KEY_BYTES = 32

Report = TypeVar("Report", ProcessStats, StepDone)
SIGNED_TYPES = (ProcessStats, StepDone)


def new_report_key() -> bytes:
    return secrets.token_bytes(REPORT_KEY_BYTES)


def key_from_environment() -> bytes | None:
    """This node's key, taken out of the environment (so nothing the node starts inherits it);
    None when started without one (by hand, or on another host)."""
    text = os.environ.pop(REPORT_KEY_ENV, None)
    if text is None:
        return None
    try:
        key = bytes.fromhex(text)
    except ValueError:
        key = b""
    if len(key) != REPORT_KEY_BYTES:
        raise ValueError(f"{REPORT_KEY_ENV} must be {2 * REPORT_KEY_BYTES} hex digits")
    return key


def sign(message: Report, key: bytes) -> Report:
    return msgspec.structs.replace(message, mac=_mac(message, key))


def is_signed_by(message: Report, key: bytes) -> bool:
    # The schema allows only lowercase hex in `mac`, so compare_digest gets ASCII.
    return bool(message.mac) and hmac.compare_digest(message.mac, _mac(message, key))


def _mac(message: Report, key: bytes) -> str:
    # Over the canonical encoding of the decoded message: msgspec writes the fields in declaration
    # order and floats in their shortest round-trip form, so sender and launcher encode alike.
    return hmac.new(key, encode(msgspec.structs.replace(message, mac="")), hashlib.sha256).hexdigest()
