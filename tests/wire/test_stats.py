"""testbed.record.timingstats: percentiles of a spooled series (bounded memory) are numpy's, bit for bit."""

import numpy as np
import pytest

from testbed.record.timingstats import Spool, percentiles
from testbed.wire.messages import NO_TIME


def spooled(a, block=777):
    s = Spool()
    for i in range(0, len(a), block):
        s.extend(a[i:i + block])
    return s


@pytest.fixture
def small_passes(monkeypatch):
    """Windows, bins and the gathered set small, so that the selection takes several passes."""
    monkeypatch.setattr(Spool, "WINDOW", 1000)
    monkeypatch.setattr(Spool, "GATHER", 300)
    monkeypatch.setattr(Spool, "BINS", 16)


@pytest.mark.parametrize("seed", range(8))
def test_spool_percentiles_equal_numpy(small_passes, seed):
    rng = np.random.default_rng(seed)
    for n in (1, 2, 3, 101, int(rng.integers(1000, 6000))):
        for a in (rng.integers(-10**6, 10**6, n), rng.integers(0, 4, n), rng.integers(-2**62, 2**62, n),
                  rng.lognormal(10, 2, n).astype(np.int64)):
            got = percentiles(spooled(a))
            assert got == percentiles(a)
            assert got["p50"] == float(np.percentile(a.astype(float), 50) / 1e3)


def test_spool_extremes_and_no_time(small_passes):
    a = np.array([np.iinfo(np.int64).max, np.iinfo(np.int64).min + 1, 0, NO_TIME, 5] * 400, dtype=np.int64)
    s = spooled(a)
    assert s.n == 1600 and percentiles(s) == percentiles(a)
    assert [s.order_stat(r) for r in (0, 399, 400, 800, 1599)] == sorted(a[a != NO_TIME].tolist())[0:1] + \
        [np.iinfo(np.int64).min + 1, 0, 5, np.iinfo(np.int64).max]


def test_spool_empty_and_memory():
    s = Spool()
    s.extend(np.array([NO_TIME], dtype=np.int64))
    assert percentiles(s) == {"p50": None, "p99": None, "max": None, "n": 0}
    import tracemalloc

    big = np.random.default_rng(0).integers(0, 10**9, 1_000_000)
    s = spooled(big, block=1 << 16)
    del big
    tracemalloc.start()
    p = percentiles(s)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert p["n"] == 1_000_000 and peak < 3 * (8 * Spool.WINDOW + 8 * Spool.GATHER + 8 * Spool.BINS) + (1 << 20)
