"""Key files only their owner may read: the data topics' key, a SecOC key, the board check's --key-file."""
from __future__ import annotations

import stat
from pathlib import Path


class PrivateKeyError(ValueError):
    """A key file that cannot be read, that others can read, or that does not hold the key."""


def read_private_key(path: Path, n_bytes: int, what: str, kind: str = "") -> bytes:
    """A key of n_bytes, as hexadecimal digits, from a file only its owner can read;
    PrivateKeyError naming `what` (and the key's `kind`) otherwise."""
    try:
        mode = stat.S_IMODE(path.stat().st_mode)
        text = path.read_text().strip()
    except OSError as exc:
        raise PrivateKeyError(f"{what}: {exc.strerror}") from None
    if mode & 0o077:
        raise PrivateKeyError(f"{what} is readable by others (mode {mode:04o}); chmod 600 it")
    try:
        key = bytes.fromhex(text)
    except ValueError:
        key = b""
    if len(key) != n_bytes:
        raise PrivateKeyError(f"{what} must hold {2 * n_bytes} hexadecimal digits" + (f" ({kind})" if kind else ""))
    return key
