"""What a node keeps per step, per frame or per event, on disk as it comes instead of in memory
(here, in the lowest layer the nodes share, so that the bus model and the board can use it too).

A node of a real-time run lives as long as the run: a list that gains an entry per step or per
frame grows without bound (a 6-minute soak of attitude_pointing_rt showed the board at ~160 MiB/h,
the plant ~42, the bus model and the recorder ~20 each: issue 44, docs/performance.md "Long runs").
These containers keep a small block in memory and the rest in an unlinked temporary file (gone
when the process ends, however it ends), and give everything back once, at the end, when the
node writes its files:

- `SpilledRows`: rows of one shape and dtype (a trajectory column, latencies in ns); `array()`.
- `SpilledJson`: JSON records (the board's applied commands, the fault injector's log); `raw()`
  yields each record's text,
  so a JSON file listing them is written without holding them (`write_json_with_list`).
- `SpilledRecords`: opaque byte records (the MCAP writer's chunk indexes, bench/recorder.py).
- `WindowCounter`: a Counter of time windows (bus load per 100 ms) whose closed windows are spilled.

Memory stays flat while the node runs; what reads the data back at the end (the node's own
output files) takes memory for that moment only.
"""
from __future__ import annotations

import json
import os
import struct
import tempfile
from collections import Counter
from typing import IO, Iterable, Iterator

import numpy as np

BLOCK_ROWS = 1024           # rows in memory before a block goes to disk (8 kB for a float64 column)
TEXT_BUFFER_BYTES = 64 * 1024


def _temporary_file(directory: str | os.PathLike | None = None) -> IO[bytes]:
    # Unlinked at once where the OS allows it: nothing to clean up after a crash or a kill.
    return tempfile.TemporaryFile(prefix="bench-spill-", dir=directory)


class SpilledRows:
    """Rows of shape `row_shape` and dtype `dtype`, appended one at a time; `array()` gives them
    all, in order, as one array of shape (n, *row_shape)."""

    def __init__(self, row_shape: tuple[int, ...] = (), dtype=np.float64, block_rows: int = BLOCK_ROWS,
                 directory: str | os.PathLike | None = None):
        self.row_shape = tuple(row_shape)
        self.dtype = np.dtype(dtype)
        self._block = np.empty((block_rows, *self.row_shape), dtype=self.dtype)
        self._in_block = 0
        self._spilled = 0
        self._directory = directory
        self._file: IO[bytes] | None = None

    def append(self, row) -> None:
        self._block[self._in_block] = row
        self._in_block += 1
        if self._in_block == len(self._block):
            if self._file is None:
                self._file = _temporary_file(self._directory)
            self._file.write(self._block.tobytes())
            self._spilled += self._in_block
            self._in_block = 0

    def __len__(self) -> int:
        return self._spilled + self._in_block

    def __bool__(self) -> bool:
        return len(self) > 0

    def array(self) -> np.ndarray:
        """Every row so far (a new array; appending goes on afterwards)."""
        out = np.empty((len(self), *self.row_shape), dtype=self.dtype)
        if self._spilled:
            self._file.seek(0)
            flat = out[:self._spilled].reshape(-1).view(np.uint8)
            view = memoryview(flat)
            read = 0
            while read < len(view):
                got = self._file.readinto(view[read:])
                if not got:
                    raise OSError("spill file shorter than what was written to it")
                read += got
            self._file.seek(0, os.SEEK_END)
        out[self._spilled:] = self._block[:self._in_block]
        return out

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        array = self.array()
        return array if dtype is None else array.astype(dtype)

    def __iter__(self) -> Iterator:
        """The rows as Python values (ints or floats for scalar rows), oldest first."""
        return iter(self.array().tolist())

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


class SpilledJson:
    """JSON records appended one at a time (json.dumps as it comes, one per line on disk).
    encode(record) -> a JSON-able value and decode(value) -> record, for records that are not
    plain JSON values (a dataclass); iterating gives records back, `raw()` their JSON text."""

    def __init__(self, directory: str | os.PathLike | None = None, encode=None, decode=None):
        self._directory = directory
        self._encode, self._decode = encode, decode
        self._file: IO[bytes] | None = None     # opened with the first record
        self._count = 0

    def append(self, record) -> None:
        if self._file is None:
            self._file = _temporary_file(self._directory)
        value = record if self._encode is None else self._encode(record)
        self._file.write(json.dumps(value).encode() + b"\n")
        self._count += 1

    def __len__(self) -> int:
        return self._count

    def raw(self) -> Iterator[str]:
        """Each record's JSON text (as json.dumps wrote it), oldest first."""
        if self._file is None:
            return
        self._file.flush()
        self._file.seek(0)
        try:
            for _ in range(self._count):
                yield self._file.readline().rstrip(b"\n").decode()
        finally:
            self._file.seek(0, os.SEEK_END)

    def __iter__(self) -> Iterator:
        decode = self._decode or (lambda value: value)
        return (decode(json.loads(text)) for text in self.raw())

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


def write_json_with_list(path: str | os.PathLike, head: dict, key: str, items: Iterable) -> None:
    """Write `head` with `key` added last, holding the list `items`, exactly as
    `json.dumps({**head, key: list(items)})` would, without building the list: `items` may be a
    SpilledJson (its records' text is copied) or any iterable of JSON-able values."""
    if key in head:
        raise ValueError(f"{key!r} is already in the head")
    opening = json.dumps({**head, key: []})
    assert opening.endswith("[]}")
    texts = items.raw() if isinstance(items, SpilledJson) else (json.dumps(item) for item in items)
    with open(path, "w", buffering=TEXT_BUFFER_BYTES) as f:
        f.write(opening[:-2])
        for i, text in enumerate(texts):
            if i:
                f.write(", ")
            f.write(text)
        f.write("]}")


class SpilledRecords:
    """Opaque byte records (each an object with `write(builder)`, as mcap's records are), kept on
    disk; iterating yields objects whose `write(builder)` writes the same bytes again."""

    _LENGTH = struct.Struct("<I")

    def __init__(self, encode, directory: str | os.PathLike | None = None):
        """encode(record) -> bytes."""
        self._encode = encode
        self._file = _temporary_file(directory)
        self._count = 0

    def append(self, record) -> None:
        data = self._encode(record)
        self._file.write(self._LENGTH.pack(len(data)) + data)
        self._count += 1

    def __len__(self) -> int:
        return self._count

    def __iter__(self) -> Iterator["RawRecord"]:
        self._file.flush()
        self._file.seek(0)
        try:
            for _ in range(self._count):
                (size,) = self._LENGTH.unpack(self._file.read(self._LENGTH.size))
                yield RawRecord(self._file.read(size))
        finally:
            self._file.seek(0, os.SEEK_END)

    def clear(self) -> None:
        """Forget every record (the file is emptied)."""
        self._file.seek(0)
        self._file.truncate()
        self._count = 0

    def close(self) -> None:
        self._file.close()


class RawRecord:
    __slots__ = ("data",)

    def __init__(self, data: bytes):
        self.data = data

    def write(self, builder) -> None:
        builder.write(self.data)


class WindowCounter:
    """A Counter keyed by a time-window index, windows arriving in about increasing order: the
    windows more than `keep` behind the newest go to disk. `items()` (sorted by window) and
    `values()` give every window, a window touched again after it was spilled summed."""

    def __init__(self, keep: int = 4, directory: str | os.PathLike | None = None):
        self.keep = keep
        self._live: Counter = Counter()
        self._spilled = SpilledRows((2,), np.int64, block_rows=256, directory=directory)
        self._newest: int | None = None

    def __getitem__(self, window: int) -> int:
        return self._live[window]

    def __setitem__(self, window: int, value: int) -> None:
        self._live[window] = value
        if self._newest is None or window > self._newest:
            self._newest = window
            if len(self._live) > self.keep:
                for old in [w for w in self._live if w < window - self.keep]:
                    self._spilled.append((old, self._live.pop(old)))

    def items(self) -> list[tuple[int, int]]:
        merged: Counter = Counter()
        for window, busy in self._spilled:
            merged[window] += busy
        merged.update(self._live)
        return sorted(merged.items())

    def values(self) -> list[int]:
        return [busy for _, busy in self.items()]

    def __len__(self) -> int:
        return len(self.items())

    def __bool__(self) -> bool:
        return bool(self._live) or bool(self._spilled)


class StepColumn:
    """One value (or row) per step of a run of `n_rows` steps, unwritten rows at `fill`, written in
    about step order (a step's row is filled while the step is recent: its command, its report,
    the stamps of a chain closed a few steps later). Only the newest `window` rows are in memory;
    older ones go to disk. A write to a row already on disk (more than `window` steps late) is kept
    aside and applied when the column is read. Indexing: `column[k] = row`, `column[k]`, and
    `column[:n]` or np.asarray(column) for the whole column (read back from disk)."""

    def __init__(self, n_rows: int, row_shape: tuple[int, ...] = (), dtype=np.float64, fill=0, window: int = 1024,
                 directory: str | os.PathLike | None = None):
        self.n_rows = int(n_rows)
        self.row_shape = tuple(row_shape)
        self.dtype = np.dtype(dtype)
        self.fill = fill
        self._recent = np.full((max(1, min(window, self.n_rows)), *self.row_shape), fill, dtype=self.dtype)
        self._base = 0                      # the oldest step still in memory; steps before it are on disk
        self._spilled = SpilledRows(self.row_shape, self.dtype, directory=directory)
        self._late: dict[int, np.ndarray] = {}

    @property
    def shape(self) -> tuple[int, ...]:
        return (self.n_rows, *self.row_shape)

    def __len__(self) -> int:
        return self.n_rows

    def _step(self, k) -> int:
        k = int(k)
        if not 0 <= k < self.n_rows:
            raise IndexError(f"step {k} is outside 0..{self.n_rows - 1}")
        return k

    def __setitem__(self, k, row) -> None:
        k = self._step(k)
        if k < self._base:
            late = np.empty(self.row_shape, dtype=self.dtype)
            late[...] = row
            self._late[k] = late
            return
        window = len(self._recent)
        while k >= self._base + window:      # make room: the oldest row in memory is final
            slot = self._base % window
            self._spilled.append(self._recent[slot])
            self._recent[slot] = self.fill
            self._base += 1
        self._recent[k % len(self._recent)] = row

    def __getitem__(self, key):
        if isinstance(key, slice):
            return self.array()[key]
        k = self._step(key)
        if k >= self._base + len(self._recent):     # not written yet
            row = np.full(self.row_shape, self.fill, dtype=self.dtype)
            return row if self.row_shape else row[()]
        if k >= self._base:
            return self._recent[k % len(self._recent)].copy() if self.row_shape else self._recent[k % len(self._recent)]
        return self.array()[k]              # on disk: read back (not for a loop)

    def array(self) -> np.ndarray:
        out = np.full(self.shape, self.fill, dtype=self.dtype)
        spilled = self._spilled.array()
        out[:len(spilled)] = spilled
        for k in range(self._base, min(self._base + len(self._recent), self.n_rows)):
            out[k] = self._recent[k % len(self._recent)]
        for k, row in self._late.items():
            out[k] = row
        return out

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        array = self.array()
        return array if dtype is None else array.astype(dtype)
