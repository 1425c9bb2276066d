"""metrics.json is valid JSON whatever the run did: no NaN or Infinity literals.

Python's json writes NaN and Infinity, which no strict JSON reader (jq, JavaScript, msgspec)
accepts. A non-finite number means "no meaningful value" (a diverged run, a percentile of
nothing): it is written as null, and the writer refuses anything it would otherwise let through.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np


def finite(value):
    """A copy of plain data (dicts, lists, numpy scalars and arrays) with non-finite floats as None."""
    if isinstance(value, dict):
        return {str(k): finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite(v) for v in value]
    if isinstance(value, np.ndarray):
        return finite(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


def dumps_finite(data) -> str:
    return json.dumps(finite(data), indent=2, allow_nan=False)


def write_json(path: Path, data) -> None:
    """Write atomically (a reader never sees half a file, a crash never leaves one)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(dumps_finite(data))
    os.replace(tmp, path)
