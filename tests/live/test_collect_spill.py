"""The launcher's end of run read back from its spill file a chunk at a time: the same summary, bit for bit,
as the whole-file read it replaced, and memory bounded by the columns, not by one object a record."""

from __future__ import annotations

import hashlib
import io
import json
import random
import time

import numpy as np
import pytest
from helpers.sims import sim_recording

from testbed.live.collect import Collector, Spill
from testbed.quantizer import Codebook
from testbed.record import columns, reader
from testbed.record.summary import LIVE_FIELDS, build_summary, write_json
from testbed.wire import messages as msg
from testbed.wire import transport


def _summary(sc, cols, arrays):
    s = build_summary(sc, cols, run_id="r", ack_via_attacker=False, nodes={}, faults=[],
                      codebook=Codebook(2, 6, True), arrays=arrays)
    f = io.StringIO()
    write_json(s, f)
    return json.loads(f.getvalue())


def _digest(recs) -> str:
    h = hashlib.sha256()
    for r in recs:
        h.update(r.encode())
    return h.hexdigest()


def _collect(session, keys, sc, tele, final, spill, *, shuffle_role="encoder", batch=7):
    """A collector fed ``tele`` over a real Zenoh session, in batches; ``shuffle_role``'s batches out of order."""
    col = Collector(session, keys, sc.n_steps, spill=spill)
    pubs = {r: session.declare_publisher(keys.telemetry(r)) for r in transport.ROLES}
    rng = random.Random(3)
    total = 0
    for role in transport.ROLES:
        recs = [tele[role][k] for k in sorted(tele[role])]
        if role == "plant":
            recs.append(final)
        batches = [recs[i:i + batch] for i in range(0, len(recs), batch)]
        if role == shuffle_role:
            rng.shuffle(batches)
        for b in batches:
            pubs[role].put(msg.pack_batch([t.encode() for t in b]))
        total += len(recs)
    end = time.monotonic() + 30
    while time.monotonic() < end:
        with col.lock:
            got = sum(len(d) for d in col.tele.values()) if spill is None else None
            spilled = None if spill is None else col._spill.f.tell()
        if spill is None and got + 1 >= total:
            break
        if spill is not None and spilled >= sum(5 + len(t.encode()) for r in transport.ROLES
                                                for t in tele[r].values()):
            break
        time.sleep(0.05)
    time.sleep(0.2)
    return col


def test_the_streamed_end_of_run_equals_the_whole_file_read(tmp_path, monkeypatch):
    """A run's telemetry through the collector (records spilled, read back 97 bytes at a time so that
    records straddle the reads, the encoder's arriving out of order): the launcher's summary equals,
    bit for bit, the one built from every record in memory (the old whole-file read), and the
    nodes' digests check out from the stream."""
    import zenoh

    sc, res, path = sim_recording(tmp_path, "paper", duration=5.0)
    rec = reader.read(path)
    tele = {r: dict(d) for r, d in rec.telemetry.items()}
    tele["attacker"] = {k: t for k, t in tele["attacker"].items() if k < 30}  # a node that died early
    final = rec.plant_final
    old = columns.from_records(sc, tele, plant_final=final)  # what the launcher built before
    want = _summary(sc, old, arrays=False)
    assert len(want["x"]) == sc.n_steps and want["symbols"] == res.symbols.tolist()

    monkeypatch.setattr(Spill, "CHUNK", 97)
    monkeypatch.setattr(Collector, "RECENT", 8)  # the memory keeps 8..16 records a node
    keys = transport.Keys.for_run(f"spill{id(tmp_path) & 0xffff}")
    with zenoh.open(transport.make_config()) as session:
        col = _collect(session, keys, sc, tele, final, tmp_path / "telemetry.bin")
        assert all(len(d) <= 2 * Collector.RECENT for d in col.tele.values())
        assert col.plant_final == final and col.rejected == 0
        got = _summary(sc, col.snapshot(sc, fields=LIVE_FIELDS), arrays=True)
        assert got == want  # every key, every sample, every float
        # the nodes' own accounts (records in the order of k, the plant's final last) check out
        summaries = {r: {"telemetry_records": len(tele[r]) + (r == "plant"),
                         "telemetry_sha256": _digest([tele[r][k] for k in sorted(tele[r])]
                                                     + ([final] if r == "plant" else []))}
                     for r in transport.ROLES}
        col.summaries.update(summaries)
        assert col.telemetry_check() == []
        col.summaries["encoder"] = dict(summaries["encoder"], telemetry_sha256="0" * 64)
        col.summaries["attacker"] = dict(summaries["attacker"], telemetry_records=31)
        bad = {f.role: f.detail for f in col.telemetry_check()}  # a Fault each
        assert bad == {"encoder": f"{len(tele['encoder'])} records collected, the node published "
                                  f"{len(tele['encoder'])}; digests differ",
                       "attacker": "30 records collected, the node published 31"}
        # without a spill file (everything in memory) the same
        col2 = _collect(session, transport.Keys.for_run(keys.run_id + "m"), sc, tele, final, None)
        assert _summary(sc, col2.snapshot(sc, fields=LIVE_FIELDS), arrays=True) == want
        col2.summaries.update(summaries)
        assert col2.telemetry_check() == []


@pytest.mark.slow  # seconds: a long run's spill read back in chunks (39 s on a busy 2-core machine)
def test_the_spill_is_read_in_bounded_chunks(tmp_path):
    """500,000 records read back through ``Spill.records``: every one, in order, and the reader's memory
    (tracemalloc's peak) a few chunks, not the file (about 30 MB)."""
    import tracemalloc

    sp = Spill(tmp_path / "telemetry.bin")
    t = msg.EncoderTelemetry(k=0, sensor_tx_ns=1, rx_ns=2, tx_ns=3, symbol=5, saturated=0, silent=0, E=0.5,
                             xi=(0.1, 0.2), q=(0.3, 0.4))
    tmpl = bytearray(t.encode())
    n = 500_000
    for k in range(n):
        tmpl[0:4] = k.to_bytes(4, "little")
        sp.write(1, bytes(tmpl))
    size = sp.f.tell()
    assert size > 25e6
    tracemalloc.start()
    seen, ok = 0, True
    for ri, b in sp.records():
        ok &= ri == 1 and int.from_bytes(b[0:4], "little") == seen
        seen += 1
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert seen == n and ok
    assert peak < 8 * Spill.CHUNK, peak  # the file is 30 MB: read whole it would be that much at least
    assert msg.EncoderTelemetry.decode(b).k == n - 1


@pytest.mark.parametrize("cut", [1, 3, 40])
def test_a_spill_cut_mid_record_reads_up_to_its_last_whole_record(tmp_path, cut):
    sp = Spill(tmp_path / "t.bin")
    for k in range(10):
        sp.write(2, bytes([k]) * 30)
    sp.f.flush()
    data = (tmp_path / "t.bin").read_bytes()
    (tmp_path / "t.bin").write_bytes(data[:len(data) - cut])
    sp.f.seek(0, 2)
    got = [b for _, b in Spill.records(sp, chunk=16)]
    assert len(got) == (9 if cut <= 35 else 8) and all(b == bytes([i]) * 30 for i, b in enumerate(got))
    assert np.all([len(b) == 30 for b in got])


def test_the_timing_section_in_windows_equals_the_whole_arrays(tmp_path, monkeypatch):
    """The end of run's timing percentiles, computed a window of samples at a time into ``stats.Spool`` files
    (windows, bins and the sorted set made small: several passes), equal numpy's on the whole columns,
    as the summary computed them before: a synthetic 1 kHz spill written with the collector's writer."""
    import sys
    from pathlib import Path

    from testbed import scenario
    from testbed.live.collect import spill_columns
    from testbed.record import summary as summary_mod
    from testbed.stats import Spool, percentiles

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    import bench_soak

    n = 5000
    sc = scenario.with_overrides(scenario.load("paper"), {"T": 0.001, "duration": n * 0.001})
    final = bench_soak.synthetic_spill(tmp_path / "telemetry.bin", sc, n)
    sp = Spill.__new__(Spill)
    sp.path, sp.f = tmp_path / "telemetry.bin", open(tmp_path / "telemetry.bin", "ab")
    cols = spill_columns(sc, sp.decoded(), n, LIVE_FIELDS, plant_final=final)
    sp.close()
    monkeypatch.setattr(summary_mod, "TIMING_WINDOW", 777)
    monkeypatch.setattr(Spool, "WINDOW", 500)
    monkeypatch.setattr(Spool, "GATHER", 200)
    monkeypatch.setattr(Spool, "BINS", 8)
    tm = _summary(sc, cols, arrays=True)["timing"]
    g, NT = cols.get, msg.NO_TIME
    t, urx, etx, ctx, atx = (g(r, f)[:n] for r, f in (("plant", "t_ns"), ("plant", "u_rx_ns"), ("encoder", "tx_ns"),
                                                      ("controller", "tx_ns"), ("attacker", "tx_ns")))

    def d(a, b):
        ok = (a != NT) & (b != NT)
        return a[ok] - b[ok]

    assert tm["sampling_jitter_us"] == percentiles(t - np.arange(n) * 1_000_000)
    assert tm["sensor_to_actuator_us"] == percentiles(d(urx, t))
    assert tm["stages_us"] == {"encoder": percentiles(d(etx, t)), "proxy": percentiles(d(atx, etx)),
                               "controller": percentiles(d(ctx, atx)), "plant": percentiles(d(urx, ctx))}
    assert tm["sampling_jitter_us"]["n"] == n and tm["sampling_jitter_us"]["p50"] > 0
