"""A small Parquet writer: flat columns of numbers, one row group per ``write``, for ``testbed export``.

It writes the subset of the format every Parquet reader reads (format 2, ``parquet.thrift`` of
apache/parquet-format): one optional column per array, version 1 data pages in PLAIN encoding,
one page per column chunk, compressed with zstd (``zstandard``, which mcap already needs; a row
group's pages by two threads, since zstd releases the GIL), each page's CRC-32, and min / max
statistics where they are exact (integers, booleans, and floats without NaN). Definition levels
are all 1 (no nulls); a NaN is a value, as in the arrays. The file's key-value metadata holds
what the caller gives.

Why not pyarrow's writer: it costs ``testbed export`` about 30 MB of imports and 10 to 25 MB of
write buffers on top of the run's columns, and its default dictionary encoding makes a run's
float columns larger and slower (measured on a 10-minute 1 kHz recording; docs/benchmarks.md,
"Post-mortems against the disk"). pyarrow and polars read these files back as the table pyarrow
would have written (``tests/core/test_parquet.py``, ``tests/runs/test_postmortem.py``).

Types: float64 and float32 as DOUBLE and FLOAT; int64 and uint64 as INT64; the narrower integers
as INT32 with their logical type (``INT(8, false)`` for uint8, ...), so that readers give back
the dtype; booleans as BOOLEAN (bit-packed). Any other dtype is cast to float64.
"""

from __future__ import annotations

import struct
import threading
import zlib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import IO, Any

import numpy as np

from .protobuf import varint as _varint

# ---- the Thrift compact protocol (the subset parquet.thrift needs)
_T_TRUE, _T_FALSE, _T_BYTE, _T_I16, _T_I32, _T_I64, _T_DOUBLE, _T_BINARY, _T_LIST, _T_SET, _T_MAP, _T_STRUCT = (
    range(1, 13))


def _zigzag(n: int) -> int:
    return (n << 1) ^ (n >> 63)


def _value(t: int, v: Any) -> bytes:
    if t in (_T_I16, _T_I32, _T_I64):
        return _varint(_zigzag(int(v)))
    if t == _T_BYTE:
        return struct.pack("<b", v)
    if t == _T_BINARY:
        b = v.encode() if isinstance(v, str) else bytes(v)
        return _varint(len(b)) + b
    if t == _T_STRUCT:
        return v                         # already encoded by ``_struct``
    if t == _T_LIST:
        et, items = v
        head = bytes([len(items) << 4 | et]) if len(items) < 15 else bytes([0xF0 | et]) + _varint(len(items))
        return head + b"".join(_value(et, e) for e in items)
    raise ValueError(f"thrift type {t}")


def _struct(*fields: tuple[int, int, Any]) -> bytes:
    """A struct of ``(field id, type, value)`` in increasing id order; a None value is left out."""
    out, last = bytearray(), 0
    for fid, t, v in fields:
        if v is None:
            continue
        tn = (_T_TRUE if v else _T_FALSE) if t == _T_TRUE else t
        out += bytes([(fid - last) << 4 | tn]) if 0 < fid - last <= 15 else bytes([tn]) + _varint(_zigzag(fid))
        if t != _T_TRUE:
            out += _value(t, v)
        last = fid
    out.append(0)
    return bytes(out)


# ---- parquet.thrift's enums
BOOLEAN, INT32, INT64, FLOAT, DOUBLE = 0, 1, 2, 4, 5
_OPTIONAL = 1
_PLAIN, _RLE = 0, 3
_ZSTD = 6
_DATA_PAGE = 0
#: converted types of the integer annotations (``ConvertedType``)
_CONVERTED = {(8, False): 11, (16, False): 12, (32, False): 13, (64, False): 14,
              (8, True): 15, (16, True): 16, (32, True): 17, (64, True): 18}


def column_type(dtype: np.dtype) -> tuple[int, np.dtype, tuple[int, bool] | None]:
    """Physical type, the dtype its values are written in, and the integer annotation (bits, signed) of a column
    of ``dtype`` (the module docstring's table)."""
    dtype = np.dtype(dtype)
    if dtype == np.bool_:
        return BOOLEAN, dtype, None
    if dtype.kind == "f" and dtype.itemsize in (4, 8):
        return (FLOAT if dtype.itemsize == 4 else DOUBLE), dtype.newbyteorder("<"), None
    if dtype.kind in "iu" and dtype.itemsize in (1, 2, 4, 8):
        signed = dtype.kind == "i"
        bits = 8 * dtype.itemsize
        phys = INT64 if bits == 64 else INT32
        return phys, np.dtype(f"<{'i' if signed else 'u'}{max(4, dtype.itemsize)}"), (bits, signed)
    return DOUBLE, np.dtype("<f8"), None


def _plain(values: np.ndarray, phys: int, wdt: np.dtype) -> np.ndarray:
    """The values' PLAIN encoding, as an array whose bytes are it (no copy when they already are)."""
    if phys == BOOLEAN:
        return np.packbits(values, bitorder="little")
    return np.ascontiguousarray(values, dtype=wdt)


def _stat_bytes(v: Any, phys: int, wdt: np.dtype) -> bytes:
    if phys == BOOLEAN:
        return bytes([int(bool(v))])
    return np.array([v], dtype=wdt).tobytes()


def _statistics(values: np.ndarray, phys: int, wdt: np.dtype) -> bytes:
    """Statistics (null count 0; min and max where exact: not for floats with NaN, whose order is undefined)."""
    lo = hi = None
    if len(values):
        lo, hi = values.min(), values.max()   # NaN when the values hold one (numpy's min and max propagate it)
        if values.dtype.kind == "f" and (np.isnan(lo) or np.isnan(hi)):
            lo = hi = None
        elif values.dtype.kind == "f":     # the format's rule for zeros: min -0.0, max +0.0
            lo = -0.0 if lo == 0 else lo
            hi = 0.0 if hi == 0 else hi
        if lo is not None:
            lo, hi = _stat_bytes(lo, phys, wdt), _stat_bytes(hi, phys, wdt)
    return _struct((3, _T_I64, 0), (5, _T_BINARY, hi), (6, _T_BINARY, lo))


class ParquetWriter:
    """``with ParquetWriter(path, names, dtypes, metadata) as w: w.write({name: array, ...})``, one row group a call.

    ``metadata``: the file's key-value metadata (str to str). ``level``: zstd's compression level.  When the
    ``with`` block or the footer's write raises (a full disk), the file is removed rather than left without its footer.
    """

    def __init__(self, path: str | Path, names: list[str], dtypes: list[np.dtype], metadata: dict[str, str],
                 *, level: int = 1, created_by: str = "dos-testbed (testbed export)") -> None:
        import zstandard

        if len(set(names)) != len(names):
            raise ValueError("column names must differ")
        self.names, self.types = list(names), [column_type(d) for d in dtypes]
        self.metadata, self.created_by = dict(metadata), created_by
        self._compressor = lambda: zstandard.ZstdCompressor(level=level)
        self._local = threading.local()     # a compressor a thread (one is not safe to share between threads)
        # zstd releases the GIL: a row group's pages are compressed by two threads (``write``, ``_page``)
        self._pool = ThreadPoolExecutor(2, thread_name_prefix="parquet-zstd")
        self._groups: list[bytes] = []
        self._rows = 0
        self.path = Path(path)
        self._f: IO[bytes] = open(self.path, "wb")
        self._f.write(b"PAR1")
        self._pos = 4

    def __enter__(self) -> ParquetWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, *exc: object) -> None:
        if exc_type is not None:
            self._discard()
            return
        try:
            self.close()
        except BaseException:
            self._discard()
            raise

    def _page(self, levels: bytes, plain: np.ndarray, values: np.ndarray, phys: int,
              wdt: np.dtype) -> tuple[bytes, bytes]:
        """One page's body (its definition levels and its values compressed as one frame, never concatenated)
        and its statistics: the work of a row group's pages, shared by the pool's threads (zstd and numpy's
        reductions release the GIL)."""
        z = getattr(self._local, "z", None)
        if z is None:
            z = self._local.z = self._compressor()
        c = z.compressobj(size=len(levels) + plain.nbytes)
        return c.compress(levels) + c.compress(plain.data.cast("B")) + c.flush(), _statistics(values, phys, wdt)

    def _discard(self) -> None:
        """A write that failed (a full disk, in a row group or the footer): no file without its footer is left."""
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._f.close()
        if self.path.is_file():          # not a device such as /dev/full
            self.path.unlink()

    def write(self, columns: dict[str, np.ndarray]) -> None:
        """One row group: every column, all of one length."""
        n = {len(columns[name]) for name in self.names}
        if len(n) != 1 or any(np.ndim(columns[name]) != 1 for name in self.names):
            raise ValueError("the columns of a row group must be 1-D, of one length")
        rows = n.pop()
        if rows == 0:
            return
        # definition levels, all 1: a 4-byte length, then one RLE run of ``rows`` ones (bit width 1)
        run = _varint(rows << 1) + b"\x01"
        levels = struct.pack("<I", len(run)) + run
        pages = []
        for name, (phys, wdt, ann) in zip(self.names, self.types, strict=True):
            values = np.asarray(columns[name])
            if phys == BOOLEAN:
                values = values.astype(bool, copy=False)
            elif values.dtype != wdt and ann is None:
                values = values.astype(wdt)
            plain = _plain(values, phys, wdt)
            pages.append((name, self._pool.submit(self._page, levels, plain, values, phys, wdt), phys,
                          len(levels) + plain.nbytes))
        chunks, total = [], 0
        for name, future, phys, raw_len in pages:
            body, stats = future.result()
            head = _struct((1, _T_I32, _DATA_PAGE), (2, _T_I32, raw_len), (3, _T_I32, len(body)),
                           (4, _T_I32, _signed32(zlib.crc32(body))),
                           (5, _T_STRUCT, _struct((1, _T_I32, rows), (2, _T_I32, _PLAIN), (3, _T_I32, _RLE),
                                                  (4, _T_I32, _RLE), (5, _T_STRUCT, stats))))
            offset = self._pos
            self._f.write(head)
            self._f.write(body)
            self._pos += len(head) + len(body)
            meta = _struct((1, _T_I32, phys), (2, _T_LIST, (_T_I32, [_PLAIN, _RLE])),
                           (3, _T_LIST, (_T_BINARY, [name])), (4, _T_I32, _ZSTD), (5, _T_I64, rows),
                           (6, _T_I64, len(head) + raw_len), (7, _T_I64, len(head) + len(body)),
                           (9, _T_I64, offset), (12, _T_STRUCT, stats))
            chunks.append(_struct((2, _T_I64, offset), (3, _T_STRUCT, meta)))
            total += len(head) + raw_len
        self._groups.append(_struct((1, _T_LIST, (_T_STRUCT, chunks)), (2, _T_I64, total), (3, _T_I64, rows)))
        self._rows += rows

    def close(self) -> None:
        """The footer: the file's metadata, its length and the magic."""
        if self._f.closed:
            return
        try:
            self._pool.shutdown(wait=True)
            schema = [_struct((4, _T_BINARY, "schema"), (5, _T_I32, len(self.names)))]
            for name, (phys, _wdt, ann) in zip(self.names, self.types, strict=True):
                logical = None if ann is None else _struct(
                    (10, _T_STRUCT, _struct((1, _T_BYTE, ann[0]), (2, _T_TRUE, ann[1]))))
                schema.append(_struct((1, _T_I32, phys), (3, _T_I32, _OPTIONAL), (4, _T_BINARY, name),
                                      (6, _T_I32, None if ann is None else _CONVERTED[ann]),
                                      (10, _T_STRUCT, logical)))
            kv = [_struct((1, _T_BINARY, k), (2, _T_BINARY, v)) for k, v in self.metadata.items()]
            orders = [_struct((1, _T_STRUCT, _struct())) for _ in self.names]   # TYPE_ORDER: the statistics' order
            footer = _struct((1, _T_I32, 2), (2, _T_LIST, (_T_STRUCT, schema)), (3, _T_I64, self._rows),
                             (4, _T_LIST, (_T_STRUCT, self._groups)), (5, _T_LIST, (_T_STRUCT, kv)),
                             (6, _T_BINARY, self.created_by), (7, _T_LIST, (_T_STRUCT, orders)))
            self._f.write(footer + struct.pack("<I", len(footer)) + b"PAR1")
        finally:
            self._f.close()


def _signed32(v: int) -> int:
    return v - (1 << 32) if v >= 1 << 31 else v


__all__ = ["ParquetWriter", "column_type"]
