"""What a scenario is judged on, and the verdict of a run against it.

A scenario lists its pass criteria (`[[criteria]]`), each a bound on one figure of the run's
metrics.json, with the reason it is the bound:

    [[criteria]]
    metric = "final_position_error_m"
    max = 100.0
    why = "seed 003: the chaser ends within 100 m of the target"

`metric` is a dotted path into metrics.json ("can_bus.driver.board_ok_at_end"); `max`, `min` or
`equals` bound it. A run passes when every criterion holds; a figure the run did not produce (a
partial run, a section left out) fails its criterion as "not measured", never passes it.
"""
from __future__ import annotations

import math
from typing import Annotated

import msgspec

MAX_CRITERIA = 32
METRIC_PATH = r"^[A-Za-z0-9_]+(\.[A-Za-z0-9_]+){0,5}$"
Bound = Annotated[float, msgspec.Meta(ge=-1e12, le=1e12)]


class Criterion(msgspec.Struct, forbid_unknown_fields=True):
    metric: Annotated[str, msgspec.Meta(pattern=METRIC_PATH, max_length=200)]
    why: Annotated[str, msgspec.Meta(min_length=1, max_length=400)]
    max: Bound | None = None
    min: Bound | None = None
    equals: bool | None = None

    def __post_init__(self):
        if self.max is None and self.min is None and self.equals is None:
            raise ValueError(f"criterion {self.metric!r}: give max, min or equals")
        if self.max is not None and self.min is not None and self.min > self.max:
            raise ValueError(f"criterion {self.metric!r}: min {self.min} is above max {self.max}")

    @property
    def bound_text(self) -> str:
        if self.equals is not None:
            return f"= {str(self.equals).lower()}"
        parts = ([f">= {self.min:g}"] if self.min is not None else []) + ([f"<= {self.max:g}"] if self.max is not None else [])
        return " and ".join(parts)


Criteria = Annotated[list[Criterion], msgspec.Meta(max_length=MAX_CRITERIA)]


def metric_value(metrics: dict, path: str):
    """The figure at a dotted path of metrics.json; None where the run did not produce it."""
    value = metrics
    for part in path.split("."):
        if not isinstance(value, dict) or part not in value:
            return None
        value = value[part]
    return value


def judge(criterion: Criterion, metrics: dict) -> dict:
    """One criterion against a run's metrics: its value, bound, and whether it holds."""
    value = metric_value(metrics, criterion.metric)
    result = {"metric": criterion.metric, "bound": criterion.bound_text, "why": criterion.why, "value": value}
    if criterion.equals is not None:
        result["passed"] = isinstance(value, bool) and value == criterion.equals
    elif isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        result["passed"] = False
    else:
        result["passed"] = ((criterion.max is None or value <= criterion.max)
                            and (criterion.min is None or value >= criterion.min))
    if value is None:
        result["value"] = "not measured"
    return result


def verdict(criteria: list[Criterion], metrics: dict, partial: bool = False) -> dict:
    """{"passed": bool | None, "criteria": [...]}: None when the scenario declares no criterion.
    A partial run fails whatever its figures say: it did not fly the scenario."""
    judged = [judge(c, metrics) for c in criteria]
    if not judged:
        return {"passed": None, "criteria": []}
    passed = all(j["passed"] for j in judged) and not partial
    return {"passed": passed, "criteria": judged, **({"partial_run": True} if partial else {})}
