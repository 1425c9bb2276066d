"""The reports the launcher takes from its processes (their ProcessStats, the plant's StepDone),
taken only when genuine, and what the processes dropped as unauthentic, named by publisher."""
from __future__ import annotations

import threading
import time
from pathlib import Path

from bench.bus import data_auth, keys
from bench.bus.schemas import MalformedMessage, ProcessStats, StepDone, decode
from bench.runtime.reports import is_signed_by


class StatsCollector:
    """The reports the launcher takes from its processes: each one's ProcessStats (a node publishes
    them once, as it stops) and the plant's StepDone (`genuine_step`).

    Anyone on the bus of a plain run can publish either, under any name. A process this launcher
    started signs its reports with the secret handed to it at start (`trust`; bench/runtime/reports.py),
    so a report naming it is taken only with a valid signature under that secret, its stats only
    once (a replay of them is counted as `replayed`, not taken); any other report naming it is
    dropped and counted under its `forged`. Reports naming no process of the run are ignored.

    A process on another host (`remote`, a deployment) was not started here and has no secret: in
    a secure run, access control lets only its certificate publish its stats. They are taken only
    once the plant has reported its last step or the launcher is stopping the nodes (earlier ones
    are kept aside as premature), the first per process (later ones counted as conflicting)."""

    def __init__(self, session, run_id: str, names: set[str], remote: set[str] | frozenset = frozenset()):
        self.run_id = run_id
        self.names = names
        self.remote = set(remote)
        self.report_keys: dict[str, bytes] = {}
        self.stats: dict = {}
        self.forged: dict[str, int] = {}      # process -> reports naming it that it did not sign
        self.accepting = False
        self.premature = 0
        self._premature: dict = {}
        self._lock = threading.Lock()        # Zenoh delivers on several threads
        self._subscriber = session.declare_subscriber(keys.key(run_id, f"{keys.STATUS_STATS}/*"), self._on_stats)

    def trust(self, name: str, key: bytes) -> None:
        """`name` is a process this launcher started with `key`."""
        self.report_keys[name] = key

    def _genuine(self, name: str, message) -> bool:
        """A report naming `name`: signed with its key, or from a remote process (access control's)."""
        if name in self.remote:
            return True
        key = self.report_keys.get(name)
        if key is not None and is_signed_by(message, key):
            return True
        with self._lock:
            self.forged[name] = self.forged.get(name, 0) + 1
        return False

    def genuine_step(self, message: StepDone) -> bool:
        return self._genuine("plant", message)

    def _on_stats(self, sample) -> None:
        try:
            message = decode(sample.payload.to_bytes(), ProcessStats)
        except MalformedMessage:
            return
        if message.header.run_id != self.run_id or message.process not in self.names:
            return
        if not self._genuine(message.process, message):
            return
        entry = {"published": message.published, "malformed": message.malformed}
        if message.unauthentic:
            entry["unauthentic"] = message.unauthentic
        if message.realtime_priority:
            entry["realtime_priority"] = message.realtime_priority
        with self._lock:
            if message.process not in self.remote:
                # Signed by the process itself, which sends its stats once: a second is a replay.
                taken = self.stats.setdefault(message.process, entry)
                if taken is not entry:
                    taken["replayed"] = taken.get("replayed", 0) + 1
                return
            if not self.accepting:
                # Kept aside, the latest per process: a node's own stats are the last it sends, and
                # on a busy host they can overtake the plant's last-step message that opens the window.
                self.premature += 1
                self._premature[message.process] = entry
                return
            if message.process in self.stats:
                taken = self.stats[message.process]
                taken["conflicting"] = taken.get("conflicting", 0) + 1
                return
            self.stats[message.process] = entry

    def accept(self) -> None:
        self.accepting = True

    def wait_for_stats(self, names: set[str], timeout_s: float) -> None:
        """Until every process in `names` has reported its stats (each sends them as it stops), at
        most timeout_s: a node killed before it could send them never will."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                if names <= set(self.stats):
                    return
            time.sleep(0.005)

    def finish(self) -> None:
        """At the end of the run: a remote process whose stats came only before the window takes its
        latest early one, marked as such; the forged reports are counted under each process."""
        with self._lock:
            for process, entry in self._premature.items():
                self.stats.setdefault(process, {**entry, "premature": True})
            for process, count in self.forged.items():
                self.stats.setdefault(process, {})["forged"] = count

    def undeclare(self) -> None:
        self._subscriber.undeclare()


def unauthentic_drops(stats: dict, run_dir: Path) -> list[str]:
    """What each process dropped for its tag, named by the topic's publishers: "estimate/translation
    from 'estimator' dropped as forged by 'controller': 40 ..." (a node from outside that does not
    sign, or signs with another key, leaves a loop waiting for messages it did send)."""
    from bench.contract.table import topic_of

    lines = []
    for process, entry in sorted(stats.items()):
        for reason, by_topic in sorted((entry.get("unauthentic") or {}).items()):
            for topic, n in sorted(by_topic.items()):
                table = topic_of(topic)
                source = f" from {', '.join(repr(p) for p in table.publishers)}" if table is not None else ""
                lines.append(f"{topic}{source} dropped as {reason} by '{process}': {n} (no valid tag under the run's key, "
                             f"{run_dir / data_auth.KEY_FILE}, or a counter already seen)")
    return lines
