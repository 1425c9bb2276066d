"""Scenario section [estimator]."""
from __future__ import annotations

from typing import Literal

import msgspec


class EstimatorConfig(msgspec.Struct, forbid_unknown_fields=True):
    # "truth": full state knowledge, seed 001's first case (ground truth passed through).
    mode: Literal["truth"] = "truth"
