"""Timing statistics of a run's integer-ns stamps (the nodes' summaries and the run summary share them)."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from typing import IO, TYPE_CHECKING, Any

import numpy as np

from ..wire.messages import NO_TIME

if TYPE_CHECKING:
    import numpy.typing as npt


class Timings:
    """ns values a node collects for its percentiles, in a fixed amount of memory however long the run.

    Every value is kept up to ``cap`` of them (the percentiles are then exact); beyond that a uniform
    random sample of ``cap`` values (reservoir sampling, Algorithm R, with a fixed seed) stands for
    them, while the count and the maximum stay exact.  With the default cap of 65,536 values (512 KiB)
    p50 and p99 are off by less than about 0.1 percentile points (the sample's standard error); a run
    of up to 65,536 samples (11 minutes at T = 10 ms) is exact.
    """

    CAP = 65536

    def __init__(self, cap: int = CAP, seed: int = 0) -> None:
        self._a = np.empty(int(cap), dtype=np.int64)
        self.n = 0
        self.max: int | None = None
        self._rng = np.random.default_rng(seed)

    def append(self, v: int) -> None:
        if v == NO_TIME:
            return
        cap = len(self._a)
        if self.n < cap:
            self._a[self.n] = v
        else:
            j = int(self._rng.integers(0, self.n + 1))
            if j < cap:
                self._a[j] = v
        self.n += 1
        if self.max is None or v > self.max:
            self.max = v

    def __len__(self) -> int:
        return self.n

    def values(self) -> np.ndarray:
        """The values kept (all of them, or the sample)."""
        return self._a[:min(self.n, len(self._a))]


class Spool:
    """ns values appended a block at a time and kept in an unnamed temporary file, not in memory.

    Its percentiles (``percentiles``) are exact, the same numbers ``np.percentile`` gives on all the
    values at once, found by a few passes over the file in windows of ``WINDOW`` values
    (``order_stat``): memory is bounded however many values (a run's end-of-run summary).
    ``NO_TIME`` values are left out, as ``percentiles`` leaves them out of an array.
    """

    #: values read at a time
    WINDOW = 1 << 16
    #: bins of a pass of the selection; values gathered and sorted once a bin holds at most this many
    BINS = 1 << 12
    GATHER = 1 << 16

    def __init__(self) -> None:
        self._f: IO[bytes] | None = None
        self.n = 0
        self.min: int | None = None
        self.max: int | None = None

    def extend(self, values: np.ndarray) -> None:
        a = np.ascontiguousarray(values, dtype=np.int64)
        a = a[a != NO_TIME]
        if not a.size:
            return
        if self._f is None:
            import tempfile

            self._f = tempfile.TemporaryFile()
        self._f.seek(0, 2)
        self._f.write(a.tobytes())
        lo, hi = int(a.min()), int(a.max())
        self.min = lo if self.min is None else min(self.min, lo)
        self.max = hi if self.max is None else max(self.max, hi)
        self.n += int(a.size)

    def __len__(self) -> int:
        return self.n

    def windows(self) -> Iterator[np.ndarray]:
        """The values in the order appended, ``WINDOW`` at a time."""
        if self._f is None:
            return
        self._f.seek(0)
        while True:
            b = self._f.read(8 * self.WINDOW)
            if not b:
                return
            yield np.frombuffer(b, dtype=np.int64)

    def order_stat(self, r: int) -> int:
        """The ``r``-th smallest value (0-based): a histogram of the values in [lo, hi] per pass narrows the
        range holding it until few enough are left to sort."""
        if not 0 <= r < self.n:
            raise IndexError(r)
        assert self.min is not None and self.max is not None  # set by extend once n > 0
        lo, hi, below = self.min, self.max, 0  # below: values < lo
        while True:
            if hi == lo:
                return lo
            width = (hi - lo) // self.BINS + 1  # a Python int: the range may exceed int64's
            counts = np.zeros(self.BINS, dtype=np.int64)
            inside: list[np.ndarray] = []
            kept, n_below = 0, 0
            lo64, hi64 = np.int64(lo), np.int64(hi)
            for a in self.windows():
                n_below += int(np.count_nonzero(a < lo64))
                v = a[(a >= lo64) & (a <= hi64)]
                off = (v - lo64).view(np.uint64)  # v - lo, exact as unsigned (wraps as signed)
                counts += np.bincount((off // np.uint64(width)).astype(np.intp), minlength=self.BINS)
                kept += len(v)
                if kept <= self.GATHER:  # few enough so far: gathered (used if the range holds no more)
                    inside.append(v.copy())
            below = n_below
            if kept <= self.GATHER:  # every value of [lo, hi] gathered: sort them
                v = np.sort(np.concatenate(inside)) if inside else np.empty(0, dtype=np.int64)
                return int(v[r - below])
            cum = np.cumsum(counts)
            j = int(np.searchsorted(cum, r - below, side="right"))
            lo, hi = lo + j * width, min(hi, lo + (j + 1) * width - 1)

    def close(self) -> None:
        if self._f is not None:
            self._f.close()
            self._f = None


def _percentile_of(stat: Callable[[int], int], n: int, p: float) -> float:
    """``np.percentile`` (linear) of ``n`` values from their order statistics ``stat(r)``, bit for bit:
    numpy's virtual index (n - 1) q, its neighbours and its interpolation (``_lerp``)."""
    q = float(np.true_divide(p, 100))
    virtual = (n - 1) * q
    if virtual >= n - 1:
        return float(stat(n - 1))
    prev = float(np.floor(virtual))
    a, b = float(stat(int(prev))), float(stat(int(prev) + 1))
    t = virtual - prev
    d = b - a
    return b - d * (1 - t) if t >= 0.5 else a + d * t


def percentiles(values: Spool | Timings | np.ndarray | Iterable[int | None], unit: float = 1e3) -> dict:
    """p50 / p99 / max / count of ns values, in microseconds by default (None when empty)."""
    if isinstance(values, Spool):
        if values.n == 0:
            return {"p50": None, "p99": None, "max": None, "n": 0}
        n, stat = values.n, values.order_stat
        assert values.max is not None  # n > 0
        return {"p50": _percentile_of(stat, n, 50) / unit, "p99": _percentile_of(stat, n, 99) / unit,
                "max": float(values.max) / unit, "n": int(n)}
    if isinstance(values, Timings):
        if values.n == 0:
            return {"p50": None, "p99": None, "max": None, "n": 0}
        a = values.values().astype(float)
        assert values.max is not None  # n > 0
        return {"p50": float(np.percentile(a, 50) / unit), "p99": float(np.percentile(a, 99) / unit),
                "max": float(values.max / unit), "n": int(values.n)}
    if isinstance(values, np.ndarray) and values.dtype.kind in "iu":
        a = values[values != NO_TIME].astype(float)
    else:
        a = np.asarray([v for v in values if v is not None and v != NO_TIME], dtype=float)
    if a.size == 0:
        return {"p50": None, "p99": None, "max": None, "n": 0}
    return {"p50": float(np.percentile(a, 50) / unit), "p99": float(np.percentile(a, 99) / unit),
            "max": float(a.max() / unit), "n": int(a.size)}


def fmt_percentiles(p: dict | None) -> str:
    """Percentiles in microseconds as one line of text (``testbed run``, ``testbed report``)."""
    if not p or p.get("p50") is None:
        return "n/a"
    return f"p50 {p['p50']:.0f} us, p99 {p['p99']:.0f} us, max {p['max']:.0f} us"


class StoredArray:
    """A per-sample array kept in an unnamed temporary file, read back a block of rows at a time: what a
    run's summary holds for its per-sample values when they are made a chunk at a time (``Stack``), so that
    its memory stays bounded however long the run.  ``len``, a slice of rows (a numpy array, read from the
    file), a single row or value, ``tolist`` (every row: only for a caller that wants the lists) and
    truth (not empty) behave as the numpy array's; ``record.summary.write_json`` streams it out."""

    def __init__(self, f: IO[bytes], dtype: np.dtype, shape: tuple, n: int) -> None:
        self._f, self.dtype, self._row, self._n = f, np.dtype(dtype), tuple(shape), int(n)
        self._size = self.dtype.itemsize * int(np.prod(self._row, dtype=np.int64))

    @property
    def shape(self) -> tuple:
        return (self._n,) + self._row

    @property
    def ndim(self) -> int:
        return 1 + len(self._row)

    def __len__(self) -> int:
        return self._n

    def __bool__(self) -> bool:
        return self._n > 0

    def _read(self, lo: int, hi: int) -> np.ndarray:
        hi = max(lo, hi)
        b = os.pread(self._f.fileno(), (hi - lo) * self._size, lo * self._size) if hi > lo else b""
        return np.frombuffer(b, dtype=self.dtype).reshape((hi - lo,) + self._row).copy()

    def __getitem__(self, i: slice | int) -> Any:
        if isinstance(i, slice):
            lo, hi, step = i.indices(self._n)
            if step != 1:
                raise IndexError("a StoredArray reads contiguous rows only")
            return self._read(lo, hi)
        i = int(i)
        if i < 0:
            i += self._n
        if not 0 <= i < self._n:
            raise IndexError(i)
        v = self._read(i, i + 1)[0]
        return v.item() if v.ndim == 0 else v

    def __iter__(self) -> Iterator[np.ndarray]:
        for lo in range(0, self._n, Stack.BLOCK):
            yield from self._read(lo, min(self._n, lo + Stack.BLOCK))

    def tolist(self) -> list:
        return self[:].tolist()

    def close(self) -> None:
        self._f.close()


class Stack:
    """Chunks of a per-sample array appended in the order of their samples, kept in an unnamed temporary file
    (in ``dir``: a run's folder) rather than in memory; ``result()`` is the whole as a ``StoredArray``.  The
    ``stack`` of ``testbed.sim.batch.RunTally`` for a run's summary made a chunk at a time."""

    #: rows read at a time when iterated
    BLOCK = 1 << 14

    def __init__(self, dir: str | os.PathLike[str] | None = None) -> None:
        self._dir = dir
        self._f: IO[bytes] | None = None
        self.dtype: np.dtype | None = None
        self.row: tuple = ()
        self.n = 0

    def append(self, a: npt.ArrayLike) -> None:
        a = np.asarray(a)
        if self._f is None:
            import tempfile

            self._f = tempfile.TemporaryFile(dir=self._dir)
            self.dtype, self.row = a.dtype, a.shape[1:]
        elif a.dtype != self.dtype or a.shape[1:] != self.row:
            a = a.astype(self.dtype).reshape((len(a),) + self.row)
        self._f.write(np.ascontiguousarray(a).tobytes())
        self.n += len(a)

    def result(self, dtype: npt.DTypeLike | None = None, row: tuple = ()) -> StoredArray:
        """The appended rows (``dtype`` and ``row``: the shape of an empty one's rows)."""
        if self._f is None:
            import tempfile

            self._f = tempfile.TemporaryFile(dir=self._dir)
            self.dtype, self.row = np.dtype(dtype or np.float64), tuple(row)
        assert self.dtype is not None  # set with the file
        self._f.flush()
        return StoredArray(self._f, self.dtype, self.row, self.n)
