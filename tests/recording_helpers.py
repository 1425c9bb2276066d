"""Shared by the recorder and report tests: a loopback pair of sessions and node contexts."""
from __future__ import annotations

import logging
from contextlib import contextmanager
from pathlib import Path

from bench.bus.session import SessionOptions, free_loopback_port, loopback_endpoint, open_session
from bench.runtime.node import NodeContext
from bench.scenario import parse_scenario


@contextmanager
def session_pair():
    """Two Zenoh sessions on loopback, the second connected to the first."""
    endpoint = loopback_endpoint(free_loopback_port())
    first = open_session(SessionOptions(listen=(endpoint,)))
    second = open_session(SessionOptions(connect=(endpoint,)))
    try:
        yield first, second
    finally:
        second.close()
        first.close()


def node_context(name: str, run_id: str, session, run_dir: Path) -> NodeContext:
    scenario = parse_scenario({"name": "recorder-test"})
    return NodeContext(name=name, run_id=run_id, scenario=scenario, session=session, run_dir=run_dir,
                       log=logging.getLogger(f"test.{name}"))
