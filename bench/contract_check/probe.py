"""What `bench contract check` puts on the bus itself: inputs an outside node must refuse.

A node that never checks the tag on what it receives passes every check of what it publishes,
and would follow anyone on the bus. So while the run goes on, the probe takes the first genuine
sample it sees on the checked node's input (the controller's estimates, the estimator's sensor
samples) and sends on that key:
- forged copies: the same message with `seq` set far past the run (FORGED_SEQ_BASE + i) and a tag
  under a key that is not the run's (the genuine sender's name), so any output carrying such a seq
  answered a forged input;
- replays: the genuine sample itself, payload and tag unchanged (its counter already passed), so a
  second output for that seq answered a replay.
The bench's own nodes and the recorder drop them too (counted as forged and replayed); the check
discounts what it sent itself.
"""
from __future__ import annotations

import json
import secrets
import threading

import zenoh

from bench.bus import data_auth, keys
from bench.bus.session import SessionOptions, open_session

FORGED_SEQ_BASE = 1_000_000
N_FORGED = 3
N_REPLAYED = 2


class InputProbe:
    """Connects to the run's hub, captures the first sample on `topic`, and sends the forged and
    replayed ones."""

    def __init__(self, hub: str, run_id: str, topic: str):
        self.run_id, self.topic = run_id, topic
        self.key_expr = keys.key(run_id, topic)
        self.sent_forged = 0
        self.sent_replayed = 0
        self.replayed_seq: int | None = None
        self._captured = threading.Event()
        self._sample: tuple[bytes, bytes | None] | None = None
        self._session = open_session(SessionOptions(connect=(hub,)))
        self._publisher = self._session.declare_publisher(self.key_expr, congestion_control=zenoh.CongestionControl.BLOCK,
                                                          reliability=zenoh.Reliability.RELIABLE)
        self._subscriber = self._session.declare_subscriber(self.key_expr, self._on_estimate)
        self._thread = threading.Thread(target=self._send, name="contract-probe", daemon=True)
        self._stop = threading.Event()
        self._thread.start()

    def _on_estimate(self, sample: zenoh.Sample) -> None:
        if self._sample is None:
            attachment = data_auth.attachment_bytes(sample)
            self._sender = (data_auth.sender_of(attachment) or "bench").encode()
            self._sample = (sample.payload.to_bytes(), attachment)
            self._captured.set()

    def _send(self) -> None:
        while not self._captured.wait(0.02):
            if self._stop.is_set():
                return
        payload, attachment = self._sample
        try:
            estimate = json.loads(payload)
            self.replayed_seq = int(estimate["header"]["seq"])
        except (ValueError, KeyError, TypeError):
            return
        wrong_key = secrets.token_bytes(data_auth.KEY_BYTES)
        for i in range(N_FORGED):
            estimate["header"]["seq"] = FORGED_SEQ_BASE + i
            forged = json.dumps(estimate).encode()
            self._publisher.put(forged, attachment=data_auth.tag(wrong_key, self.key_expr, forged, self._sender, i + 1))
            self.sent_forged += 1
        for _ in range(N_REPLAYED):
            self._publisher.put(payload, attachment=attachment)
            self.sent_replayed += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._session.close()
