"""A campaign's results file (bench/studies/campaign.py): rows appended to `<out>.parts/` as small
Parquet files while it runs (written to a temporary name, then renamed), read back so that a
re-run skips the cases done, and merged into `<out>` in case order at the end; seed 001's columns.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from bench.studies.campaign_engines import CELL_COLUMNS


def seed001_schema():
    import pyarrow as pa

    from bench.gnc.cwh import RendezvousParams
    from bench.studies.campaign_metrics import run_metrics

    sample = run_metrics(np.zeros((2, 6)), np.zeros((1, 3)), RendezvousParams.from_reference(), [0.0], [0], [True])
    types = {bool: pa.bool_(), int: pa.int64(), float: pa.float64()}
    fields = [("case_id", pa.string()), ("case_index", pa.int64())] + [(c, pa.string()) for c in CELL_COLUMNS]
    fields += [("seed", pa.int64()), ("status", pa.string()), ("error", pa.string())]
    fields += [(k, types[type(v)]) for k, v in sample.items()]
    fields += [("wall_time_s", pa.float64()), ("scenario_json", pa.string())]
    return pa.schema(fields)


def parts_dir(out: Path) -> Path:
    return out.with_name(out.name + ".parts")


class ResultsWriter:
    """Appends rows as numbered part files (written to a temporary name, then renamed)."""

    def __init__(self, out: Path, flush_every: int, flush_interval_s: float = 5.0, schema=None):
        self.out, self.dir = out, parts_dir(out)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.flush_every, self.flush_interval_s = max(1, flush_every), flush_interval_s
        self.pending: list[dict] = []
        self.last_flush = time.monotonic()
        self.schema = schema if schema is not None else seed001_schema()
        self.next_part = 1 + max((int(p.stem.split("-")[1]) for p in self.dir.glob("part-*.parquet")), default=0)

    def add(self, row: dict) -> None:
        self.pending.append(row)
        if len(self.pending) >= self.flush_every or time.monotonic() - self.last_flush > self.flush_interval_s:
            self.flush()

    def flush(self) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        if not self.pending:
            return
        table = pa.Table.from_pylist(self.pending, schema=self.schema)
        final = self.dir / f"part-{self.next_part:06d}.parquet"
        tmp = final.with_suffix(".tmp")
        pq.write_table(table, tmp)
        os.replace(tmp, final)
        self.next_part += 1
        self.pending = []
        self.last_flush = time.monotonic()


def read_rows(out: Path) -> list[dict]:
    """Rows already in the results file and its parts (a later row of a case replaces an earlier)."""
    import pyarrow.parquet as pq

    rows: dict[str, dict] = {}
    sources = ([out] if out.is_file() else []) + sorted(parts_dir(out).glob("part-*.parquet"))
    for path in sources:
        for row in pq.read_table(path).to_pylist():
            rows[row["case_id"]] = row
    return list(rows.values())


def finalise(out: Path, case_order: dict[str, int] | None = None, schema=None) -> int:
    """Merge the parts into `out`, sorted by case order; remove the parts. Returns the row count."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    import shutil

    rows = read_rows(out)
    key = (lambda r: case_order.get(r["case_id"], len(case_order))) if case_order else (lambda r: r["case_index"])
    rows.sort(key=lambda r: (key(r), r["case_id"]))
    tmp = out.with_name(out.name + ".tmp")
    pq.write_table(pa.Table.from_pylist(rows, schema=schema if schema is not None else seed001_schema()), tmp)
    os.replace(tmp, out)
    shutil.rmtree(parts_dir(out), ignore_errors=True)
    return len(rows)
