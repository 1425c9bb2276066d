"""The control plane: which processes are on a run's bus, which are ready, and what their clocks say,
answered only under the run's key.

A Zenoh liveliness token proves nothing: its key expression is all there is, any process that
reaches the bus can declare `alive/<name>` for a node that is stopped or not yet started, and a
token cannot carry a MAC. So every process of a run answers queries on its own key instead:

    query    bench/<run_id>/presence/*          payload: a nonce, 32 hex digits, fresh per query
    reply    bench/<run_id>/presence/<process>  payload: JSON {"process", "host", "ready",
                                                 "monotonic_ns", "nonce"}
                                                 attachment: the data-topic tag (data_auth.tag)
                                                 with sender = <process>

A reply counts only when its tag is valid under the run's data key, its sender, its `process` and
the last segment of its key expression are one name, and it carries this query's nonce. Without
the key nothing can answer for a node (declare it alive or ready, or hide that it stopped: a
stopped process answers nothing), and a recorded answer is worthless for the next query. The same
reply is the clock ping of clock_sync.py, so a clock offset is signed too.

Queries ask every matching queryable (`QueryTarget.ALL`) and keep every reply
(`ConsolidationMode.NONE`): with Zenoh's default consolidation a forged reply on a node's key could
take the place of the genuine one.

A process without the run's key (started by hand, in-process tests) answers unsigned and accepts
unsigned answers, as data_auth does for data.
"""
from __future__ import annotations

import json
import logging
import secrets
import socket
import threading
import time
from collections import Counter
from dataclasses import dataclass

import zenoh

from bench.bus import data_auth, keys

PRESENCE = "presence"       # bench/<run_id>/presence/<process>
NONCE_HEX = 32
QUERY_DONE_GRACE_S = 30.0

log = logging.getLogger("bench.presence")


@dataclass(frozen=True)
class PresenceReply:
    """One authenticated answer: who, where, whether ready, and its clock between t0 and t1."""

    process: str
    host: str
    ready: bool
    monotonic_ns: int       # the responder's CLOCK_MONOTONIC when it answered
    sent_ns: int            # the asker's CLOCK_MONOTONIC when it asked (t0)
    received_ns: int        # ... and when this reply came back (t1)


class PresenceResponder:
    """A process's answer to presence queries; `ready` turns true once its subscribers match."""

    def __init__(self, session: zenoh.Session, run_id: str, process: str, key: bytes | None,
                 host: str | None = None):
        self.process, self.host = process, host or socket.gethostname()
        self.ready = False
        self._key_expr = keys.key(run_id, f"{PRESENCE}/{process}")
        self._signer = data_auth.Signer(key, process) if key is not None else None
        self._queryable = session.declare_queryable(self._key_expr, self._on_query)

    def _on_query(self, query: zenoh.Query) -> None:
        try:
            nonce = query.payload.to_bytes().decode("ascii") if query.payload is not None else ""
        except UnicodeDecodeError:
            return
        if len(nonce) != NONCE_HEX:
            return      # not a presence query: nothing to say
        payload = json.dumps({"process": self.process, "host": self.host, "ready": self.ready,
                              "monotonic_ns": time.monotonic_ns(), "nonce": nonce}).encode()
        attachment = self._signer(self._key_expr, payload) if self._signer is not None else None
        try:
            query.reply(self._key_expr, payload, attachment=attachment)
        except Exception:   # noqa: BLE001 - the session is closing, or the asker left
            pass

    def undeclare(self) -> None:
        try:
            self._queryable.undeclare()
        except Exception:   # noqa: BLE001 - already closed with its session
            pass


def _open_reply(reply: zenoh.Reply, prefix: str, key: bytes | None, nonce: str, sent_ns: int,
                received_ns: int) -> PresenceReply | None:
    sample = reply.ok
    if sample is None:
        return None
    key_expr = str(sample.key_expr)
    name = key_expr[len(prefix):] if key_expr.startswith(prefix) else ""
    payload = sample.payload.to_bytes()
    if key is not None:
        opened = data_auth.open_tag(key, key_expr, payload, data_auth.attachment_bytes(sample))
        if opened is None or opened[0].decode("ascii", "replace") != name:
            return None
    try:
        data = json.loads(payload)
        answer = PresenceReply(str(data["process"]), str(data["host"]), data["ready"] is True,
                               int(data["monotonic_ns"]), sent_ns, received_ns)
        fresh = data["nonce"] == nonce
    except (ValueError, KeyError, TypeError):
        return None
    if not fresh or answer.process != name:
        return None
    return answer


class PresenceQuery:
    """Ask every process of a run once; `refused` counts the answers that did not authenticate."""

    def __init__(self, session: zenoh.Session, run_id: str, key: bytes | None):
        self.session, self.run_id, self.key = session, run_id, key
        self._prefix = keys.key(run_id, f"{PRESENCE}/")
        self.refused = 0
        self.refused_by_name: Counter = Counter()   # the name in the refused answer's key

    def ask(self, names: str = "*", timeout_s: float = 0.5) -> dict[str, PresenceReply]:
        """Every authentic answer to one query on `presence/<names>`, by process. Returns when every
        queryable has answered, or after timeout_s."""
        nonce = secrets.token_hex(NONCE_HEX // 2)
        found: dict[str, PresenceReply] = {}
        done = threading.Event()
        sent_ns = time.monotonic_ns()

        def on_reply(reply: zenoh.Reply) -> None:
            received_ns = time.monotonic_ns()   # first: the clock ping's t1
            answer = _open_reply(reply, self._prefix, self.key, nonce, sent_ns, received_ns)
            if answer is None:
                if reply.ok is not None:
                    self.refused += 1
                    self.refused_by_name[str(reply.ok.key_expr)[len(self._prefix):]] += 1
                    if self.refused <= 5 or self.refused % 100 == 0:
                        log.warning("presence reply #%d on %s refused (no valid tag under the run's key, "
                                    "or not this query's)", self.refused, reply.ok.key_expr)
                return
            found.setdefault(answer.process, answer)

        self.session.get(keys.key(self.run_id, f"{PRESENCE}/{names}"), zenoh.handlers.Callback(on_reply, done.set),
                         payload=nonce.encode(), target=zenoh.QueryTarget.ALL,
                         consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s)
        # Until Zenoh says the query is over (every answer in, or its timeout): a query still in
        # flight when the session closes and the interpreter exits calls into Python from Zenoh's
        # threads, which aborts the process (seen under load 18: "FATAL: exception not rethrown").
        # The bound is only against a Zenoh that never calls back.
        done.wait(timeout_s + QUERY_DONE_GRACE_S)
        return dict(found)

    def wait_ready(self, names: list[str], timeout_s: float, stop: threading.Event | None = None,
                   who: str = "") -> None:
        """Block until every name has answered ready; TimeoutError naming the others."""
        deadline = time.monotonic() + timeout_s
        missing = set(names)
        while missing:
            missing -= {n for n, a in self.ask().items() if a.ready}
            if not missing:
                return
            if time.monotonic() > deadline or (stop is not None and stop.is_set()):
                raise TimeoutError(f"{who + ': ' if who else ''}not ready after {timeout_s:g} s: "
                                   f"{', '.join(sorted(missing))}")
            time.sleep(0.02)


class PresenceWatcher:
    """Asks a run's processes every period_s on a thread of its own and keeps when each last
    answered. A process is silent once lease_s has passed since its last authentic answer (or
    since the watch began, for one that never answered), as a liveliness token lapses after its
    lease; it is back as soon as it answers again."""

    def __init__(self, session: zenoh.Session, run_id: str, key: bytes | None, names, lease_s: float,
                 period_s: float | None = None):
        self.query = PresenceQuery(session, run_id, key)
        self.names = set(names)
        self.lease_s = lease_s
        # Four looks a lease: a process is seen silent within a quarter lease of its lease running out.
        self.period_s = period_s if period_s is not None else max(0.05, lease_s / 4)
        started = time.monotonic()
        self._last_s = {name: started for name in self.names}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="presence-watch", daemon=True)

    def start(self) -> "PresenceWatcher":
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                answers = self.query.ask(timeout_s=min(self.period_s, 0.5))
            except Exception:   # noqa: BLE001 - the session is closing
                return
            with self._lock:
                for name in self.names & set(answers):
                    self._last_s[name] = answers[name].received_ns / 1e9    # CLOCK_MONOTONIC, as time.monotonic
            self._stop.wait(self.period_s)

    def silent_since(self, name: str, now: float | None = None) -> float | None:
        """When `name`'s lease ran out (monotonic s) if it has not answered since; else None."""
        now = time.monotonic() if now is None else now
        with self._lock:
            expired = self._last_s[name] + self.lease_s
        return expired if now >= expired else None

    def stop(self) -> None:
        # Joined whatever it takes (one query at most): a query left in flight when the session
        # closes and the interpreter exits can call into Python from Zenoh's threads, which aborts.
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
