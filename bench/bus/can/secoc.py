"""Authenticated commands in the manner of AUTOSAR SecOC: freshness value and truncated CMAC.

E2E (protocol.py) finds corruption; it cannot find forgery, because the data ids are no secret
from anyone who has the DBC. SecOC adds, behind the authentic PDU (MTQ_CMD_AUTH bytes 0..7):
- a freshness value: the sender's time in 10 us ticks, 64 bits in full, of which the low 32 travel
  (bytes 8..11); the receiver rebuilds the full value from its own clock, as SecOC's freshness
  manager does with a truncated freshness value. Sender and receiver share the time base (here the
  host's CLOCK_MONOTONIC, one clock for every process of a bench; a multi-host bench would need a
  synchronised time base, as AUTOSAR's StbM/CanTSyn provide);
- a MAC: AES-128-CMAC (RFC 4493, NIST SP 800-38B) over SecOC data id (2 bytes, big-endian),
  authentic PDU and full freshness value (8 bytes, big-endian), truncated to its first 64 bits
  (bytes 12..19).

The receiver verifies the MAC first (a forgery must not move any E2E state), then the freshness:
the command's age on the receiver's clock must lie in [-max_future_s, max_age_s], and its
freshness value must be newer than that of the last command it accepted. max_age_s is the command
period plus a stated margin, so a replayed, delayed or queued-too-long command is never applied,
whatever its alive counter says.
"""
from __future__ import annotations

import enum
import hmac

from cryptography.hazmat.primitives import cmac
from cryptography.hazmat.primitives.ciphers import algorithms

FRESHNESS_TICK_S = 1e-5          # 10 us
FRESHNESS_WIRE_BITS = 32         # low bits of the freshness value that travel (wraps after 11.9 h)
FRESHNESS_OFFSET = 8             # byte offsets in MTQ_CMD_AUTH
MAC_OFFSET = 12
MAC_BYTES = 8
AUTHENTIC_PDU_BYTES = 8
KEY_BYTES = 16                   # AES-128


def aes_cmac(key: bytes, message: bytes) -> bytes:
    """The full 16-byte AES-CMAC (the `cryptography` package's implementation)."""
    c = cmac.CMAC(algorithms.AES(key))
    c.update(message)
    return c.finalize()


def freshness_ticks(t_s: float) -> int:
    return round(t_s / FRESHNESS_TICK_S)


def mac(key: bytes, data_id: int, authentic_pdu: bytes, freshness: int) -> bytes:
    """The truncated MAC of one secured PDU."""
    message = data_id.to_bytes(2, "big") + bytes(authentic_pdu) + (freshness % 2**64).to_bytes(8, "big")
    return aes_cmac(key, message)[:MAC_BYTES]


def secure(key: bytes, data_id: int, payload: bytes, freshness: int) -> bytes:
    """Write the wire freshness value and the MAC into a secured PDU (E2E must already be applied)."""
    data = bytearray(payload)
    data[FRESHNESS_OFFSET:FRESHNESS_OFFSET + 4] = (freshness % 2**FRESHNESS_WIRE_BITS).to_bytes(4, "little")
    data[MAC_OFFSET:MAC_OFFSET + MAC_BYTES] = mac(key, data_id, data[:AUTHENTIC_PDU_BYTES], freshness)
    return bytes(data)


def rebuild_freshness(wire: int, now_ticks: int) -> int:
    """The full freshness value nearest the receiver's time whose low bits are `wire`."""
    modulo = 2**FRESHNESS_WIRE_BITS
    behind = (now_ticks - wire) % modulo
    if behind >= modulo // 2:
        behind -= modulo          # from the future (clock skew)
    return now_ticks - behind


class Verdict(enum.Enum):
    OK = "ok"
    WRONG_MAC = "WRONG_MAC"
    STALE = "STALE"


class FreshnessVerifier:
    """Receive side of one secured PDU: MAC, age and newer-than-last."""

    def __init__(self, key: bytes, data_id: int, max_age_s: float, max_future_s: float):
        if len(key) != KEY_BYTES:
            raise ValueError(f"SecOC key must be {KEY_BYTES} bytes (AES-128), not {len(key)}")
        self.key = key
        self.data_id = data_id
        self.max_age_ticks = freshness_ticks(max_age_s)
        self.max_future_ticks = freshness_ticks(max_future_s)
        self.last_accepted: int | None = None

    def verify(self, data: bytes, now_s: float) -> tuple[Verdict, int, float]:
        """(verdict, full freshness value, age in s) of a received secured PDU; changes nothing."""
        now_ticks = freshness_ticks(now_s)
        wire = int.from_bytes(data[FRESHNESS_OFFSET:FRESHNESS_OFFSET + 4], "little")
        freshness = rebuild_freshness(wire, now_ticks)
        age_s = (now_ticks - freshness) * FRESHNESS_TICK_S
        expected = mac(self.key, self.data_id, data[:AUTHENTIC_PDU_BYTES], freshness)
        if not hmac.compare_digest(expected, bytes(data[MAC_OFFSET:MAC_OFFSET + MAC_BYTES])):
            return Verdict.WRONG_MAC, freshness, age_s
        too_old = now_ticks - freshness > self.max_age_ticks
        too_new = freshness - now_ticks > self.max_future_ticks
        not_newer = self.last_accepted is not None and freshness <= self.last_accepted
        if too_old or too_new or not_newer:
            return Verdict.STALE, freshness, age_s
        return Verdict.OK, freshness, age_s

    def accept(self, freshness: int) -> None:
        """The command was applied: nothing at or before its freshness value ever will be."""
        self.last_accepted = freshness
