"""The launcher's end of run read back from its spill file a chunk at a time: the same summary, bit for bit,
as the whole-file read it replaced, and memory bounded by the columns, not by one object a record."""

from __future__ import annotations

import hashlib
import io
import json
import random
import time
from pathlib import Path

import numpy as np
import pytest
from helpers.sims import sim_recording

from testbed.live.collect import Collector, Spill
from testbed.loop.quantizer import Codebook
from testbed.record import columns, reader
from testbed.record.summary import LIVE_FIELDS, build_summary, to_lists, write_json
from testbed.record.timingstats import StoredArray
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


@pytest.mark.slow  # half a second or more on a warm cache
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
        # as the launcher reads it: rows a chunk at a time, the lag measured as the records came (the encoder's
        # batches shuffled), per-sample values in files
        assert col.lag > 7 and col.role_lag > 0
        from testbed.live.collect import SpillRows  # the file's own order, read back: the collector's figures
        assert SpillRows(sc, col._spill.path, sc.n_steps, None, LIVE_FIELDS).measure_lag() == (col.lag, col.role_lag)
        for chunk in (7, None):
            s = build_summary(sc, col.rows(sc, LIVE_FIELDS, chunk=chunk), run_id="r", ack_via_attacker=False,
                              nodes={}, faults=[], codebook=Codebook(2, 6, True), arrays=True, store=tmp_path)
            f = io.StringIO()
            write_json(s, f)
            assert json.loads(f.getvalue()) == want
        # the nodes' own accounts (records in the order of k, the plant's final last) check out
        summaries = {r: {"telemetry_records": len(tele[r]) + (r == "plant"),
                         "telemetry_sha256": _digest([tele[r][k] for k in sorted(tele[r])]
                                                     + ([final] if r == "plant" else []))}
                     for r in transport.ROLES}
        col.summaries.update(summaries)
        assert col.telemetry_check() == [] and col.telemetry_behind() == []  # the launcher need not wait
        col.MAX_HELD = 3  # the encoder's records strayed further: digested from their k order, a window at a time
        assert col.lag_of["encoder"] > col.MAX_HELD and col.telemetry_check() == []
        del col.MAX_HELD
        col.summaries["encoder"] = dict(summaries["encoder"], telemetry_sha256="0" * 64)
        col.summaries["attacker"] = dict(summaries["attacker"], telemetry_records=31)
        bad = {f.role: f.detail for f in col.telemetry_check()}  # a Fault each
        assert col.telemetry_behind() == ["attacker"]  # one record more published than arrived: the launcher waits
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


@pytest.mark.slow  # half a second or more on a warm cache
def test_the_timing_section_in_windows_equals_the_whole_arrays(tmp_path, monkeypatch):
    """The end of run's timing percentiles, computed a window of samples at a time into ``stats.Spool`` files
    (windows, bins and the sorted set made small: several passes), equal numpy's on the whole columns,
    as the summary computed them before: a synthetic 1 kHz spill written with the collector's writer."""
    import sys
    from pathlib import Path

    from testbed import scenario
    from testbed.live.collect import spill_columns
    from testbed.record import summary as summary_mod
    from testbed.record.timingstats import Spool, percentiles

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


def _text(sc, src, store=None):
    s = build_summary(sc, src, run_id="r", ack_via_attacker=False, nodes={}, faults=[],
                      codebook=Codebook(2, 6, True), arrays=True, store=store)
    f = io.StringIO()
    write_json(s, f)
    return f.getvalue(), s


def _provoked(cols, N):
    """Causes the simulation itself does not make, written into the columns: withheld samples, an invalid payload,
    a controller record missing, a deadline miss and a break of lockstep (the decoder's E altered)."""
    from testbed.record.columns import normalize

    cols.get("encoder", "silent")[[5, 6, N - 3]] = 1
    cols.get("controller", "theta")[[5, 6, N - 3]] = 1
    normalize(cols)
    cols.get("controller", "reason")[9] = msg.ControllerTelemetry.INVALID
    cols.get("controller", "theta")[9] = 1
    cols.present[12, transport.ROLES.index("controller")] = 0
    cols.get("plant", "flags")[[3, 4]] |= msg.PlantTelemetry.FLAG_MISS
    cols.get("controller", "E")[20:23] *= 1.5
    return cols


@pytest.mark.parametrize("name,over,provoke,fault", [
    ("paper", {"duration": 6.0}, False, None),                              # attacker drops
    ("paper", {"duration": 6.0}, True, None),                               # + withheld, invalid, missing, misses
    ("paper", {"method": "zoom", "duration": 5.0}, True, None),             # a method's ends replayed: lockstep
    ("paper-greedy", {"duration": 8.0}, False, 41),                         # a method fault at sample 41
])
def test_the_summary_is_the_same_however_the_rows_are_cut(tmp_path, name, over, provoke, fault):
    """``build_summary`` chunk by chunk (1 row, 7 rows, the whole run; per-sample values in memory or in files,
    ``stats.Stack``) writes the same JSON, byte for byte, on recordings with losses of several causes, a break of
    lockstep and a method fault."""
    from testbed.record.summary import ColumnChunks, load

    _sc, _res, path = sim_recording(tmp_path, name, **over)
    cols, sc = load(path, note=False)
    N = sc.n_steps
    if provoke:
        cols = _provoked(cols, N)
    if fault is not None:
        cols.events.append(msg.Event(node="controller", kind="method_fault", k=fault, detail="raised"))
    want, s = _text(sc, cols)
    assert json.loads(want)["samples"] == (N if fault is None else fault)
    if provoke:
        assert s["losses"]["withheld"] == 3 and s["losses"]["attacker"] >= 1 and s["deadline_missed_at"].tolist() == [3, 4]
        if over.get("method") == "zoom":
            assert s["lockstep_breaks"][:3] == [20, 21, 22]
    if fault is not None:
        assert s["method_fault_at"] == fault and s["escaped"] is True
    for size in (1, 7, None):
        for store in (None, tmp_path):
            got, s = _text(sc, ColumnChunks(cols, size), store)
            assert got == want, (size, store)
    assert to_lists(s) == json.loads(want)  # the values kept in files (stats.StoredArray) as lists
    assert isinstance(s["x"], StoredArray) and s["x"][3].tolist() == json.loads(want)["x"][3]


def _spill_of(path, sc, rec, order):
    """A spill file of a recording's telemetry, written in ``order`` (a list of (role index, k))."""
    sp = Spill(path)
    for ri, k in order:
        sp.write(ri, rec.telemetry[transport.ROLES[ri]][k].encode())
    sp.close()


NOISY = str(Path(__file__).resolve().parents[2] / "docs" / "examples" / "paper-noisy.toml")


@pytest.mark.parametrize("chunk,name,over", [(1, "paper", {}), (7, "paper", {}), (64, "paper", {}), (None, "paper", {}),
                                             (7, NOISY, {"method": "zoom"})])  # x_meas; a method's ends replayed
def test_the_spill_read_as_rows_gives_the_whole_columns_summary(tmp_path, chunk, name, over):
    """``collect.SpillRows`` (the launcher's end of run): records in the order they arrive (the nodes a few
    samples apart, a batch late), read as chunks of rows, give the summary of the whole columns byte for byte;
    the lag it measures is how far the order strays."""
    from testbed.live.collect import SpillRows

    if name == NOISY:  # a copy: the recording goes next to the scenario (sim_recording: NAME.mcap)
        (tmp_path / "noisy.toml").write_text(Path(NOISY).read_text())
    sc, res, path = sim_recording(tmp_path, str(tmp_path / "noisy.toml") if name == NOISY else name, duration=5.0,
                                  **over)
    rec = reader.read(path)
    tele = rec.telemetry
    order = []
    for k in range(sc.n_steps + 9):
        for ri, role in enumerate(transport.ROLES):
            kk = k - 3 * ri  # the later nodes behind the plant
            if 0 <= kk < sc.n_steps and kk in tele[role] and not (role == "attacker" and 20 <= kk < 25):
                order.append((ri, kk))
    late = [(transport.ROLES.index("attacker"), k) for k in range(20, 25) if k in tele["attacker"]]
    order[300:300] = late  # a batch that came long after
    _spill_of(tmp_path / "telemetry.bin", sc, rec, order)
    whole = columns.from_records(sc, {r: {k: tele[r][k] for r2, k in [(transport.ROLES[i], k) for i, k in order]
                                          if r2 == r} for r in transport.ROLES}, plant_final=rec.plant_final,
                                 fields=LIVE_FIELDS)
    want, s = _text(sc, whole)
    assert ("x_meas" in s) == (name == NOISY)
    rows = SpillRows(sc, tmp_path / "telemetry.bin", whole.rows, None, LIVE_FIELDS, chunk=chunk,
                     plant_final=rec.plant_final)
    assert rows.lag >= 20 and rows.last_k("plant") == whole.last_k("plant")
    got, _ = _text(sc, rows, tmp_path)
    assert got == want


def test_records_added_at_once_equal_records_added_one_by_one(tmp_path, paper):
    """``SpillRows`` decodes the records of one role and layout as one array (``columns.add_records``); a spill
    with every odd case (a vector of the wrong width, an optional vector on some records only, an empty one,
    a k past the rows, records far out of order) reads to the same columns as decoding them one at a time."""
    from testbed.live.collect import SpillRows

    rng = np.random.default_rng(5)
    path = tmp_path / "odd.bin"
    sp = Spill(path)
    recs = []
    for k in range(300):
        x = tuple(rng.normal(size=2))
        recs.append((0, msg.PlantTelemetry(k=k, t_ns=k * 10**8, sensor_tx_ns=k, u_rx_ns=msg.NO_TIME if k % 9 == 0 else k,
                                           delay_ns=0, theta=k % 2, flags=k % 4, flow_status=-1 if k % 50 == 0 else 0,
                                           x=x if k % 37 else x + (1.0,), u=(0.5,) if k % 41 else (),
                                           x_meas=x if k % 3 == 0 else ())))
        recs.append((1, msg.EncoderTelemetry(k=k, sensor_tx_ns=k, rx_ns=k, tx_ns=k, symbol=k % 37, saturated=k % 5 == 0,
                                             silent=int(k % 11 == 0), E=float(k), xi=x, q=x)))
        recs.append((2, msg.AttackerTelemetry(k=k, rx_ns=k, tx_ns=k, dropped=k % 3 == 0, corrupted=0, attack_on=1,
                                              dropped_total=k, forwarded_total=k)))
        recs.append((3, msg.ControllerTelemetry(k=299 - k, sym_stamp_ns=k, rx_ns=k, tx_ns=k, symbol=k % 37, theta=k % 2,
                                                reason=0, E=1.0, xi=x, q=x, u=(1.0,))))
    for ri, t in recs:
        sp.write(ri, t.encode())
    sp.close()
    sc = paper
    whole = columns.ColumnBuilder(sc, 250)
    for ri, t in recs:
        whole.add(ri, t)
    want = whole.finish()
    rows = SpillRows(sc, path, 250, chunk=64)
    assert rows.lag == 299
    got = [c for _, c in rows.chunks(250)]
    for t in want.tables:
        assert np.array_equal(np.concatenate([c.tables[t] for c in got])[:250], want.tables[t], equal_nan=True), t
    assert np.array_equal(np.concatenate([c.present for c in got])[:250], want.present)
    assert sum(c.malformed for c in got) == want.malformed > 0


@pytest.mark.parametrize("behind", [50, 150])
def test_a_node_far_behind_the_others_is_read_split_by_node_in_a_window_of_two_chunks(tmp_path, behind):
    """The controller's records arrive ``behind`` samples after the others' (a stalled node): the lag is that
    large, each node's own order is kept, so ``SpillRows`` splits the file by node and reads the parts side
    by side: the builder's window stays two chunks (not the lag), and the summary and the columns are those of
    the whole columns, byte for byte."""
    from testbed.live.collect import SpillRows

    sc, res, path = sim_recording(tmp_path, "paper", duration=20.0)
    rec = reader.read(path)
    tele = rec.telemetry
    ctl = transport.ROLES.index("controller")
    order = []
    for k in range(sc.n_steps + behind):
        for ri, role in enumerate(transport.ROLES):
            kk = k - behind if ri == ctl else k
            if 0 <= kk < sc.n_steps and kk in tele[role]:
                order.append((ri, kk))
    _spill_of(tmp_path / "telemetry.bin", sc, rec, order)
    whole = columns.from_records(sc, tele, plant_final=rec.plant_final, fields=LIVE_FIELDS)
    want, _ = _text(sc, whole)
    spans = []

    class Watched(SpillRows):
        def _builder(self, span, ColumnBuilder, k0=0):
            spans.append(span)
            return super()._builder(span, ColumnBuilder, k0)

    chunk = 16
    rows = Watched(sc, tmp_path / "telemetry.bin", whole.rows, None, LIVE_FIELDS, chunk=chunk,
                   plant_final=rec.plant_final)
    assert rows.lag >= behind - 1 and rows.role_lag == 0 and rows.split
    got = list(rows.chunks(whole.rows))
    assert max(spans) == 2 * chunk + 1  # two chunks, whatever the lag
    for t in whole.tables:
        assert np.array_equal(np.concatenate([c.tables[t] for _, c in got])[:whole.rows], whole.tables[t],
                              equal_nan=True), t
    assert np.array_equal(np.concatenate([c.present for _, c in got])[:whole.rows], whole.present)
    # the collector's own lag figures give the same reading
    same = SpillRows(sc, tmp_path / "telemetry.bin", whole.rows, rows.lag, LIVE_FIELDS, chunk=chunk,
                     plant_final=rec.plant_final, role_lag=0)
    assert same.split
    assert _text(sc, same, tmp_path)[0] == want
    # and without the split (no role_lag given) the window is the lag: the same summary
    wide = SpillRows(sc, tmp_path / "telemetry.bin", whole.rows, rows.lag, LIVE_FIELDS, chunk=chunk,
                     plant_final=rec.plant_final)
    assert not wide.split and _text(sc, wide, tmp_path)[0] == want
