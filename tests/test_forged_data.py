"""A rogue peer on a plain run's bus, without the run's key, forges the loop's data messages
(commands, estimates, sensor samples, truth: well-formed, this run's id, the step being flown) and
replays every genuine message it captures, at once and again steps later. The run's metrics.json
and trajectory are those of the same run without the rogue; the nodes count what they dropped,
and the recorder neither takes forged stats nor records a forged message as the run's. Loopback only.

On the main branch before data topics were signed this fails: the plant flew the rogue's commands
(the trajectory differs) and no process counted anything."""
from __future__ import annotations

import json
import threading

import numpy as np
import zenoh

from bench.bus import keys
from bench.bus.schemas import (ProcessStats, RangeBearing, RelativePosition, ThrustCommand, TranslationEstimate,
                               TruthState, decode, encode, header)
from test_forged_reports import attacked_beside_clean, comparable

REPLAY_LAG_STEPS = 2
# Long enough for the rogue to be on the bus while the loop runs: it joins through the launcher's
# endpoint after the run has started (here its first sample comes 0.3 s after it subscribed), and
# a 60-step lock-step loop (about 40 ms since the hot path got shorter) was once over before its
# subscription saw a truth sample (stop 51's CI18: it saw one sample in all); 2000 steps are about
# 1.3 s. It attacks only the first ATTACK_STEPS steps it sees, so that its own load (a Python
# callback answering every sample) is the same however long the run.
STEPS = 2000
ATTACK_STEPS = 30


class RogueData:
    """On each genuine truth sample of step k (the first message of a step, so its command can win
    the race against the controller's): forged messages for step k on every loop topic, half
    without an attachment and half with a made-up MAC (the layout of a genuine one, the sender
    'controller'); forged stats claiming the controller published one command. Every genuine
    sample it sees is sent again at once, and those of REPLAY_LAG_STEPS steps ago once more. After
    ATTACK_STEPS truth samples it only listens."""

    def __init__(self, session, run_id: str):
        self.session, self.run_id = session, run_id
        self.sent = {"forged": 0, "replayed": 0}
        self._captured: list[list[tuple[str, bytes, bytes]]] = [[]]
        self._lock = threading.Lock()
        self.subscriber = session.declare_subscriber(keys.all_topics(run_id), self._on_sample)

    def _put(self, key_expr: str, payload: bytes, attachment: bytes | None, kind: str) -> None:
        # Not to its own subscriber: it sees only what others publish.
        self.session.put(key_expr, payload, attachment=attachment, allowed_destination=zenoh.Locality.REMOTE)
        self.sent[kind] += 1

    def _forge(self, topic: str, message, i: int) -> None:
        payload = encode(message)
        made_up = None if i % 2 == 0 else b"\x01\x0acontroller" + (1 << 62).to_bytes(8, "big") + bytes(range(32))
        self._put(keys.key(self.run_id, topic), payload, made_up, "forged")

    def _on_sample(self, sample) -> None:
        if len(self._captured) > ATTACK_STEPS:
            return
        attachment = None if sample.attachment is None else sample.attachment.to_bytes()
        key_expr, payload = str(sample.key_expr), sample.payload.to_bytes()
        with self._lock:
            self._captured[-1].append((key_expr, payload, attachment))
            old = self._captured[-1 - REPLAY_LAG_STEPS] if len(self._captured) > REPLAY_LAG_STEPS else []
            if key_expr.endswith("/" + keys.TRUTH):
                self._captured.append([])
            else:
                old = []
        if key_expr.endswith("/" + keys.TRUTH):
            k = decode(payload, TruthState).header.seq
            self._forge_step(k)
        self._put(key_expr, payload, attachment, "replayed")             # at once
        for captured in old:                                              # a few steps late: old seq
            self._put(*captured, "replayed")

    def _forge_step(self, k: int) -> None:
        hdr = header(self.run_id, k, 600.0 * k)
        for i in range(2):
            self._forge(keys.COMMAND_THRUST, ThrustCommand(hdr, [0.9, -0.9, 0.9], True, "rogue", 0.0), i)
            self._forge(keys.SENSE_RELPOS, RelativePosition(hdr, [1e4, 1e4, 1e4], 1.0), i)
            self._forge(keys.SENSE_RANGE_BEARING, RangeBearing(hdr, 1e4, 0.1, 0.1), i)
            self._forge(keys.TRUTH, TruthState(hdr, [1e4, 1e4, 1e4, 1.0, 1.0, 1.0], [0.0, 0.0, 0.0]), i)
            self._forge(keys.ESTIMATE_TRANSLATION, TranslationEstimate(
                hdr, [1e4, 1e4, 1e4, 1.0, 1.0, 1.0], None, 0.001, None, 0, False), i)
            self._forge(f"{keys.STATUS_STATS}/controller", ProcessStats(
                header(self.run_id, 0, 0.0), "controller", {keys.COMMAND_THRUST: 1}, {}), i)

    def close(self) -> None:
        self.subscriber.undeclare()


def test_forged_and_replayed_data_change_nothing_in_a_plain_run(runs_dir):
    rogue, (attacked, attacked_trajectory), (clean, clean_trajectory) = attacked_beside_clean(
        runs_dir, "data", STEPS, RogueData)
    assert rogue.sent["forged"] > 0 and rogue.sent["replayed"] > 0, rogue.sent
    assert comparable(attacked) == comparable(clean)
    for key, values in clean_trajectory.items():
        np.testing.assert_array_equal(attacked_trajectory[key], values)
    assert attacked["process_stats"]["controller"]["published"][keys.COMMAND_THRUST] == STEPS
    # The rogue reached the nodes, which dropped and counted its forgeries and replays.
    dropped = {name: entry.get("unauthentic", {}) for name, entry in attacked["process_stats"].items()}
    assert dropped["plant"].get("forged", {}).get(keys.COMMAND_THRUST, 0) > 0, dropped
    assert dropped["plant"].get("replayed", {}).get(keys.COMMAND_THRUST, 0) > 0, dropped
    assert dropped["controller"].get("forged", {}).get(keys.ESTIMATE_TRANSLATION, 0) > 0, dropped
    assert dropped["controller"].get("replayed", {}).get(keys.ESTIMATE_TRANSLATION, 0) > 0, dropped
    assert sum(dropped["estimator"].get("forged", {}).values()) > 0, dropped
    assert sum(dropped["estimator"].get("replayed", {}).values()) > 0, dropped
    assert all("unauthentic" not in entry for entry in clean["process_stats"].values())
    # The recorder: the forged stats are not what the controller published, and the forged and
    # replayed samples are counted apart, not recorded as the run's.
    counts = json.loads((runs_dir / "data-rogue" / "recorder_counts.json").read_text())
    assert counts["publishers"]["controller"][keys.COMMAND_THRUST] == STEPS
    command_counts = counts["topics"][keys.COMMAND_THRUST]
    assert command_counts["recorded"] == STEPS and command_counts["missing"] == 0, command_counts
    assert command_counts["unauthentic"]["forged"] > 0 and command_counts["unauthentic"]["replayed"] > 0
