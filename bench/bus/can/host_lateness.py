"""When the host, not the bus, held a CAN node up: the lateness each node measured of itself.

On a loaded machine the driver, the board and the bus model are processes the OS may not run in
time. Each measures its own lateness (the driver: `host_overrun` events, a command period or poll
that began late; the board: periodic frames more than half a period late; the bus model's bridge:
deliveries or wake-ups more than 5 ms late) and writes it to its report. A fault check reads them
here to tell a starved host from the fault it is testing: the same test then fails on a real bus
fault and passes on a busy machine.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path


class HostLateLog:
    """A node's record of its own lateness: how often it ran late (`host_overruns`) and, for the
    first RECORD_LIMIT times, when it noticed (ns on its clock) and by how much (s). The flight
    side's checks excuse a detection no more than these records say."""
    RECORD_LIMIT = 1000

    def __init__(self):
        self.host_overruns = 0
        self.host_late_ns_s: list[tuple[int, float]] = []

    def note(self, t_ns: int, late_s: float) -> None:
        self.host_overruns += 1
        if len(self.host_late_ns_s) < self.RECORD_LIMIT:
            self.host_late_ns_s.append((int(t_ns), float(late_s)))

    def report(self) -> dict:
        """The fields a node's report carries (read back by `host_late_records`)."""
        return {"host_overruns": self.host_overruns, "host_late_ns_s": [list(x) for x in self.host_late_ns_s]}


@dataclass(frozen=True)
class HostLate:
    node: str           # "driver", "board" or "bus_model"
    t_ns: int           # monotonic ns the node noticed it was late
    late_s: float       # how late it ran


def host_late_records(driver_events, board_report: dict, bus_model_report: dict) -> list[HostLate]:
    """Every lateness the three nodes recorded. driver_events: the driver's events, as objects
    (FaultEvent) or as the dicts of can/driver.json."""
    records = []
    for e in driver_events:
        e = e if isinstance(e, dict) else e.__dict__
        if e["kind"] == "host_overrun":
            records.append(HostLate("driver", int(e["detected_ns"]), float(e["latency_s"])))
    for node, report in (("board", board_report), ("bus_model", bus_model_report)):
        records += [HostLate(node, int(t_ns), float(late_s)) for t_ns, late_s in report.get("host_late_ns_s", [])]
    return records


def load_host_late_records(can_dir: str | Path) -> list[HostLate]:
    """The records of a run's can/ folder (driver.json, board.json, busmodel.json); a missing
    report contributes nothing."""
    can_dir = Path(can_dir)

    def read(name: str) -> dict:
        path = can_dir / name
        return json.loads(path.read_text()) if path.is_file() else {}

    return host_late_records(read("driver.json").get("events", []), read("board.json"), read("busmodel.json"))


def host_late_s(records: list[HostLate], from_ns: int, to_ns: int) -> float:
    """How long the host held the nodes up between from_ns and to_ns: each node's lateness summed,
    the most of the three taken (they share the starved CPUs, so their delays overlap, not add)."""
    per_node: dict[str, float] = {}
    for r in records:
        if from_ns <= r.t_ns <= to_ns:
            per_node[r.node] = per_node.get(r.node, 0.0) + r.late_s
    return max(per_node.values(), default=0.0)


def longest_host_late_s(records: list[HostLate], from_ns: int, to_ns: int) -> float:
    """The longest single hold-up of any node between from_ns and to_ns (a stall, where
    host_late_s also adds up many short delays)."""
    return max((r.late_s for r in records if from_ns <= r.t_ns <= to_ns), default=0.0)


def held_s(records: list[HostLate], from_ns: int, to_ns: int) -> float:
    """How long, between from_ns and to_ns, at least one of the records' nodes was held up: the
    union of the intervals [t - late, t] the records say their node was held, so that one hold
    that several records (or nodes) noticed counts once, and a hold that began before from_ns
    counts from from_ns."""
    intervals = sorted((max(r.t_ns - r.late_s * 1e9, from_ns), min(r.t_ns, to_ns)) for r in records)
    total_ns, reach_ns = 0.0, float(from_ns)
    for start_ns, end_ns in intervals:
        if end_ns > max(start_ns, reach_ns):
            total_ns += end_ns - max(start_ns, reach_ns)
            reach_ns = end_ns
    return total_ns / 1e9
