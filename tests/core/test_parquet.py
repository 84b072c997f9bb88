"""``testbed.common.parquet``, the writer of ``testbed export``'s Parquet files, against two readers that share
no code with it: pyarrow's (C++) and polars' (Rust)."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from testbed.common.parquet import ParquetWriter

DTYPES = ["bool", "int8", "int16", "int32", "int64", "uint8", "uint16", "uint32", "uint64", "float32", "float64"]


def _column(rng: np.random.Generator, dt: str, n: int) -> np.ndarray:
    d = np.dtype(dt)
    if d == np.bool_:
        return rng.random(n) < 0.3
    if d.kind in "iu":
        info = np.iinfo(d)
        a = rng.integers(info.min, info.max, size=n, dtype=d, endpoint=True)
        a[: min(n, 2)] = [info.min, info.max][: min(n, 2)]
        return a
    return (rng.standard_normal(n) * 10.0 ** rng.integers(-300 if d.itemsize == 8 else -30, 30, size=n)).astype(d)


def _groups(rng: np.random.Generator, sizes: list[int], special: bool) -> list[dict[str, np.ndarray]]:
    out = []
    for g, n in enumerate(sizes):
        cols = {dt: _column(rng, dt, n) for dt in DTYPES}
        if special and g == 1 and n >= 5:  # NaN, infinities and zeros of both signs in one group only
            for dt in ("float32", "float64"):
                cols[dt][:5] = [np.nan, np.inf, -np.inf, -0.0, 0.0]
        if g == 2 and n >= 3:               # a group whose floats' extremes are zeros of the other sign
            for dt in ("float32", "float64"):
                cols[dt][:] = np.where(np.arange(n) % 2 == 0, 0.0, -0.0)
                cols[dt][0] = 1.0
        out.append(cols)
    return out


@pytest.mark.parametrize("seed", range(6))
def test_pyarrow_and_polars_read_back_the_arrays_the_metadata_and_exact_statistics(tmp_path, seed):
    rng = np.random.default_rng(seed)
    sizes = [int(rng.integers(1, 3000)) for _ in range(4)] + [0, int(rng.integers(1, 40))]
    groups = _groups(rng, sizes, special=True)
    meta = {"testbed.run": '{"source": "live", "run_id": "r\\u00e9"}', "plain": "x" * int(rng.integers(0, 300))}
    path = tmp_path / "t.parquet"
    with ParquetWriter(path, DTYPES, [np.dtype(d) for d in DTYPES], meta, level=int(rng.integers(1, 5))) as w:
        for cols in groups:
            w.write(cols)
    whole = {dt: np.concatenate([g[dt] for g in groups]) for dt in DTYPES}
    want = pa.Table.from_arrays([pa.array(whole[dt]) for dt in DTYPES], names=DTYPES,
                                metadata={k.encode(): v.encode() for k, v in meta.items()})

    f = pq.ParquetFile(path, page_checksum_verification=True)
    back = f.read()
    assert back.schema.equals(want.schema, check_metadata=True), (back.schema, want.schema)
    for dt in DTYPES:  # the values: NaN where NaN was (Table.equals takes NaN as unequal to itself)
        got = back.column(dt).to_numpy()
        assert got.dtype == np.dtype(dt) and np.array_equal(got, whole[dt], equal_nan=dt.startswith("float")), dt
        assert np.array_equal(np.signbit(got), np.signbit(whole[dt])) if dt.startswith("float") else True
    # one row group a write (an empty write adds none), each with exact statistics
    md = f.metadata
    assert [md.row_group(i).num_rows for i in range(md.num_row_groups)] == [n for n in sizes if n]
    for i, cols in enumerate(g for g, n in zip(groups, sizes, strict=True) if n):
        for j, dt in enumerate(DTYPES):
            st = md.row_group(i).column(j).statistics
            a = cols[dt]
            assert st.null_count == 0
            if a.dtype.kind == "f" and np.isnan(a).any():
                assert not st.has_min_max
                continue
            assert st.has_min_max
            lo, hi = st.min, st.max
            assert lo == a.min() and hi == a.max(), (dt, lo, hi, a.min(), a.max())
            if a.dtype.kind == "f" and a.min() == 0:
                assert np.signbit(lo)          # the format's rule: a zero minimum is -0.0 ...
            if a.dtype.kind == "f" and a.max() == 0:
                assert not np.signbit(hi)      # ... and a zero maximum +0.0
    import polars as pl
    df = pl.read_parquet(path)
    assert df.columns == DTYPES and df.height == sum(sizes)
    for dt in DTYPES:
        got = df[dt].to_numpy()
        assert got.dtype == np.dtype(dt) and np.array_equal(got, whole[dt], equal_nan=dt.startswith("float")), dt


def test_a_flipped_bit_in_a_page_fails_its_checksum(tmp_path):
    path = tmp_path / "t.parquet"
    x = np.arange(5000, dtype=np.float64) / 7
    with ParquetWriter(path, ["x"], [x.dtype], {}) as w:
        w.write({"x": x})
    data = bytearray(path.read_bytes())
    data[len(data) // 4] ^= 0x10                   # inside the one page's compressed values
    path.write_bytes(bytes(data))
    with pytest.raises(OSError, match="CRC|checksum"):
        pq.ParquetFile(path, page_checksum_verification=True).read()


def test_columns_of_unequal_length_or_repeated_names_are_refused(tmp_path):
    with pytest.raises(ValueError, match="differ"):
        ParquetWriter(tmp_path / "a.parquet", ["x", "x"], [np.dtype("f8")] * 2, {})
    with ParquetWriter(tmp_path / "b.parquet", ["x", "y"], [np.dtype("f8")] * 2, {}) as w, \
            pytest.raises(ValueError, match="one length"):
        w.write({"x": np.zeros(3), "y": np.zeros(4)})
    with ParquetWriter(tmp_path / "c.parquet", ["x"], [np.dtype("f8")], {}) as w, \
            pytest.raises(ValueError, match="1-D"):
        w.write({"x": np.zeros((3, 2))})
    assert pq.read_table(tmp_path / "b.parquet").num_rows == 0   # closed with its footer all the same


def test_a_write_that_fails_leaves_no_file_without_its_footer(tmp_path):
    path = tmp_path / "t.parquet"
    with pytest.raises(RuntimeError), ParquetWriter(path, ["x"], [np.dtype("f8")], {}) as w:
        w.write({"x": np.zeros(10)})
        raise RuntimeError("the disk filled up")
    assert not path.exists()


def test_a_footer_that_cannot_be_written_leaves_no_file(tmp_path):
    """The disk fills up as the footer is written (``close``, when the ``with`` block ends well)."""
    path = tmp_path / "t.parquet"

    class Full:
        def __init__(self, f):
            self.f, self.closed = f, False

        def write(self, b):
            raise OSError(28, "No space left on device")

        def close(self):
            self.f.close()
            self.closed = True

    with pytest.raises(OSError, match="No space"), ParquetWriter(path, ["x"], [np.dtype("f8")], {}) as w:
        w.write({"x": np.zeros(10)})
        w._f = Full(w._f)
    assert not path.exists()
