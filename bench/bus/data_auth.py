"""Authenticated data topics: every message a bench node publishes carries a MAC under the run's key.

Anyone who reaches a plain run's bus (any local process: it listens on loopback without TLS) can
publish on `bench/<run_id>/...`. So each sample carries, in its Zenoh attachment (the JSON payload
is unchanged, so the message schemas are too), a tag a receiver checks before the message reaches
node logic:

    attachment = version (1 byte, 1) | len(sender) (1 byte) | sender (ASCII) | counter (8 bytes, big endian)
                 | HMAC-SHA256(key, key_expr | 0x00 | version | len(sender) | sender | counter | payload)

- The key expression is under the MAC: a genuine message cannot be moved to another topic or run.
- `sender` (the publishing node's name) and `counter` make a replay detectable: a publisher's
  counter starts at its wall-clock time in ns and goes up by one per message (so a restarted
  publisher still goes on upwards), and a subscription takes from one sender on one key only a
  counter above the last it took (`ReplayGuard`). Zenoh delivers one publisher's reliable samples
  in order, so a genuine message is never below its predecessor.
- The key is the run's: 32 random bytes drawn by the launcher per run and written to the run
  directory's `bus.key` (hex, mode 0600), which every node of the run reads (`node_key`); in a
  deployment (certificates) it is derived from the deployment's secoc.key, so nodes on other
  hosts hold it without a copy (`deployment_key`). Nodes without a key (started by hand without
  the run's directory, in-process tests) sign nothing and check nothing.

Only stdlib hmac: an outside node signs in a few lines (docs/contract.md,
examples/outside_lqr_controller.py).
"""
from __future__ import annotations

import functools
import hashlib
import hmac
import itertools
import threading
import time
from pathlib import Path

from bench.bus.private_files import PrivateKeyError, read_private_key

KEY_FILE = "bus.key"
KEY_BYTES = 32
MAC_BYTES = 32
VERSION = 1
COUNTER_BYTES = 8
MAX_SENDER_BYTES = 64
# Domain separation from the SecOC key it is derived from in a deployment.
DEPLOYMENT_LABEL = b"orbit-hil-bench data topics v1"

FORGED = "forged"       # no, a short, a malformed or a wrong tag
REPLAYED = "replayed"   # a genuine tag whose counter this subscription has already passed


class KeyFileError(ValueError):
    """The run's key file is unreadable, readable by others, or not 64 hex digits."""


def new_key() -> bytes:
    import secrets
    return secrets.token_bytes(KEY_BYTES)


def deployment_key(secoc_key_hex: str) -> bytes:
    """The data-topic key of a deployment, from its SecOC key (the same 0600 file beside the certificates)."""
    return hmac.new(bytes.fromhex(secoc_key_hex), DEPLOYMENT_LABEL, hashlib.sha256).digest()


def read_key_file(path: Path) -> bytes:
    try:
        return read_private_key(Path(path), KEY_BYTES, f"bus key {str(path)!r}")
    except PrivateKeyError as exc:
        raise KeyFileError(str(exc)) from None


def node_key(run_dir: Path, cert_dir: Path | None = None) -> bytes | None:
    """The key a node signs and checks with: the deployment's (a secure node whose certificate
    directory has a secoc.key), else the run directory's bus.key, else None (refused for a
    secure node: it has certificates, so it is meant to be part of a run)."""
    if cert_dir is not None:
        from bench.bus.certs import read_secoc_key
        secoc_hex = read_secoc_key(Path(cert_dir))
        if secoc_hex:
            return deployment_key(secoc_hex)
    path = Path(run_dir) / KEY_FILE
    if path.is_file():
        return read_key_file(path)
    if cert_dir is not None:
        # A secure node without a key would publish into the void (every other node drops it).
        raise KeyFileError(f"no data key: neither {str(Path(cert_dir) / 'secoc.key')!r} nor {str(path)!r} exists; "
                           f"copy the deployment's secoc.key (mode 0600) beside this host's certificates")
    return None


@functools.lru_cache(maxsize=16)
def _keyed(key: bytes) -> "hmac.HMAC":
    return hmac.new(key, digestmod=hashlib.sha256)


def _mac(key: bytes, data: bytes) -> bytes:
    # A copy of the keyed HMAC object: 4 us for a 400-byte message against 40 us for hmac.digest,
    # which sets OpenSSL 3's HMAC up anew on every call (benchmarks/bench_data_auth.py).
    h = _keyed(key).copy()
    h.update(data)
    return h.digest()


def tag(key: bytes, key_expr: str, payload: bytes, sender: bytes, counter: int) -> bytes:
    """The attachment of one sample."""
    head = bytes((VERSION, len(sender))) + sender + counter.to_bytes(COUNTER_BYTES, "big")
    return head + _mac(key, key_expr.encode() + b"\x00" + head + payload)


def open_tag(key: bytes, key_expr: str, payload: bytes, attachment: bytes | None) -> tuple[bytes, int] | None:
    """(sender, counter) of a sample whose attachment is a valid tag for this key, key expression
    and payload; None for anything else (no attachment, another version, truncated, wrong MAC)."""
    if not attachment or len(attachment) < 2 or attachment[0] != VERSION:
        return None
    n = attachment[1]
    head_len = 2 + n + COUNTER_BYTES
    if len(attachment) != head_len + MAC_BYTES:
        return None
    head = attachment[:head_len]
    expected = _mac(key, key_expr.encode() + b"\x00" + head + payload)
    if not hmac.compare_digest(expected, attachment[head_len:]):
        return None
    return head[2:2 + n], int.from_bytes(head[2 + n:], "big")


class Signer:
    """One process's signing: its name and its counter (thread-safe: itertools.count is atomic)."""

    def __init__(self, key: bytes, sender: str):
        encoded = sender.encode()
        if not 0 < len(encoded) <= MAX_SENDER_BYTES:
            raise ValueError(f"sender name {sender!r} must be 1-{MAX_SENDER_BYTES} bytes")
        self.key, self.sender = key, encoded
        self._counter = itertools.count(time.time_ns())

    def __call__(self, key_expr: str, payload: bytes) -> bytes:
        return tag(self.key, key_expr, payload, self.sender, next(self._counter))


class Verifier:
    """One subscription's check: the tag, then the counter per (key expression, sender).
    `check` returns None for a message to take, else FORGED or REPLAYED."""

    def __init__(self, key: bytes):
        self.key = key
        self._last: dict[tuple[str, bytes], int] = {}
        self._lock = threading.Lock()      # Zenoh may deliver on several threads

    def check(self, key_expr: str, payload: bytes, attachment: bytes | None) -> str | None:
        opened = open_tag(self.key, key_expr, payload, attachment)
        if opened is None:
            return FORGED
        sender, counter = opened
        with self._lock:
            last = self._last.get((key_expr, sender))
            if last is not None and counter <= last:
                return REPLAYED
            self._last[(key_expr, sender)] = counter
        return None


def sender_of(attachment: bytes | None) -> str | None:
    """The sender named in a tag (not checked: call it on a sample whose tag was verified)."""
    if not attachment or len(attachment) < 2:
        return None
    return attachment[2:2 + attachment[1]].decode("ascii", "replace")


def attachment_bytes(sample) -> bytes | None:
    """A Zenoh sample's attachment as bytes (None when it has none)."""
    attachment = sample.attachment
    return None if attachment is None else attachment.to_bytes()
