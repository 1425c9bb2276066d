"""What the recorder takes in during a run: the budget that admits a sample (anyone on the bus
can publish under the run's keys, bench/recorder.py) and the spool that keeps the admitted ones,
as they arrived, until the recorder writes them into the recording (bench/recorder.py: in bursts and
at the stop)."""
from __future__ import annotations

import struct
import threading
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

from bench.bus.spill import SpilledRecords

# Budgets (bench/recorder.py's docstring). The default loop publishes ~2 000 samples/s per topic of
# ~0.5 kB in lock-step (README, loop rate); a saturated 1 Mbit/s CAN bus is ~7 900 frames/s.
MAX_MESSAGE_BYTES = 256 * 1024
MAX_TOPICS = 512
TOPIC_MESSAGES_PER_S, TOPIC_MESSAGE_BURST = 20_000.0, 40_000.0
TOPIC_BYTES_PER_S, TOPIC_BYTE_BURST = 2e6, 8e6
TOTAL_BYTES_PER_S, TOTAL_BYTE_BURST = 8e6, 32e6


@dataclass
class TokenBucket:
    """Admits `amount` if the bucket holds it; refills at rate_per_s up to burst."""

    rate_per_s: float
    burst: float
    tokens: float = -1.0
    last_s: float | None = None

    def take(self, amount: float, now_s: float) -> bool:
        if self.last_s is None:
            self.tokens, self.last_s = self.burst, now_s
        self.tokens = min(self.burst, self.tokens + (now_s - self.last_s) * self.rate_per_s)
        self.last_s = now_s
        if amount > self.tokens:
            return False
        self.tokens -= amount
        return True


@dataclass
class RecordingBudget:
    """What the recorder may keep; `admit` returns None or the reason a sample is dropped."""

    max_message_bytes: int = MAX_MESSAGE_BYTES
    max_topics: int = MAX_TOPICS
    total: TokenBucket = field(default_factory=lambda: TokenBucket(TOTAL_BYTES_PER_S, TOTAL_BYTE_BURST))
    messages: dict = field(default_factory=dict)
    bytes: dict = field(default_factory=dict)
    dropped: dict = field(default_factory=dict)      # topic -> Counter(reason)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def admit(self, topic: str, size: int, now_s: float) -> str | None:
        with self._lock:     # Zenoh calls back on several threads
            reason = self._reason(topic, size, now_s)
            if reason is not None:
                key = topic if (topic in self.messages or len(self.dropped) < self.max_topics) else "<other topics>"
                self.dropped.setdefault(key, Counter())[reason] += 1
            return reason

    def _reason(self, topic: str, size: int, now_s: float) -> str | None:
        if size > self.max_message_bytes:
            return "message_too_large"
        if topic not in self.messages:
            if len(self.messages) >= self.max_topics:
                return "too_many_topics"
            self.messages[topic] = TokenBucket(TOPIC_MESSAGES_PER_S, TOPIC_MESSAGE_BURST)
            self.bytes[topic] = TokenBucket(TOPIC_BYTES_PER_S, TOPIC_BYTE_BURST)
        if not self.messages[topic].take(1.0, now_s):
            return "message_rate"
        if not self.bytes[topic].take(size, now_s):
            return "byte_rate"
        if not self.total.take(size, now_s):
            return "total_byte_rate"
        return None

    def dropped_counts(self) -> dict[str, dict[str, int]]:
        with self._lock:
            return {topic: dict(reasons) for topic, reasons in sorted(self.dropped.items())}


class SampleSpool:
    """The samples of a run as they arrived (key expression, payload, MAC attachment, arrival wall
    time), on disk (bench/bus/spill.py) until the recording takes them."""

    _HEAD = struct.Struct("<IIiq")     # key length, payload length, attachment length (-1: none), arrival ns

    def __init__(self, directory: Path):
        self._records = SpilledRecords(self._encode, directory)

    @classmethod
    def _encode(cls, sample: tuple[str, bytes, bytes | None, int]) -> bytes:
        key_expr, payload, attachment, received_ns = sample
        key = key_expr.encode()
        head = cls._HEAD.pack(len(key), len(payload), -1 if attachment is None else len(attachment), received_ns)
        return b"".join((head, key, payload, attachment or b""))

    def append(self, sample: tuple[str, bytes, bytes | None, int]) -> None:
        self._records.append(sample)

    def __len__(self) -> int:
        """Samples waiting to be taken."""
        return len(self._records)

    def take(self) -> Iterator[tuple[str, bytes, bytes | None, int]]:
        """Every waiting sample, in arrival order, as (key expression, payload, attachment, arrival
        ns); the spool is empty afterwards (read it to its end)."""
        for record in self._records:
            data = record.data
            key_len, payload_len, attachment_len, received_ns = self._HEAD.unpack_from(data)
            at = self._HEAD.size + key_len
            attachment = None if attachment_len < 0 else data[at + payload_len:at + payload_len + attachment_len]
            yield data[self._HEAD.size:at].decode(), data[at:at + payload_len], attachment, received_ns
        self._records.clear()

    def close(self) -> None:
        self._records.close()
