"""A simulation's recording written in bulk (``record_simulation``, ``testbed.record.simrecord``): every
message the bytes of the per-message path; at T < 10 ms the phase plane decimated, and said so."""

import json

import numpy as np
import pytest
from mcap.reader import make_reader

from testbed import scenario
from testbed.record import recording, simrecord
from testbed.record.schema import to_pb
from testbed.sim.loop import LinkEffects
from testbed.sim.trajectory import simulate_scenario

T0 = 1_700_000_000_123_456_789


def _messages(path):
    with open(path, "rb") as f:
        return [(ch.topic, m.log_time, m.publish_time, m.data) for _, ch, m in make_reader(f).iter_messages()]


def _metadata(path):
    with open(path, "rb") as f:
        return {m.name: m.metadata for m in make_reader(f).iter_metadata()}


def _sc(name, **over):
    return scenario.with_overrides(scenario.load(name), over) if over else scenario.load(name)


CASES = [("paper", {}, None), ("paper-greedy", {}, None), ("paper-escape", {"mode": "ideal"}, None),
         ("paper", {"timing": "physical"}, None), ("paper", {"method": "unquantized-hold"}, None),
         ("paper", {"method": "static"}, None),
         ("paper", {}, LinkEffects(ack_via_attacker=True, corrupt=((7, "range"), (40, "length"))))]


@pytest.mark.parametrize("name,over,net", CASES)
def test_bulk_recording_is_the_per_message_recording_byte_for_byte(tmp_path, name, over, net):
    sc = _sc(name, **over)
    res = simulate_scenario(sc, effects=net)
    a, b = tmp_path / "a.mcap", tmp_path / "b.mcap"
    ca = recording.record_simulation(a, sc, res, t0_ns=T0, bulk=False)
    cb = recording.record_simulation(b, sc, res, t0_ns=T0)
    ma, mb = _messages(a), _messages(b)
    assert len(ma) > 4 * len(res.t)
    assert ma == mb
    assert ca == cb
    assert json.loads(_metadata(b)["testbed.run"]["phase_every"]) == 1


def test_the_encoder_writes_what_protobuf_writes():
    """Edge values one at a time against ``schema.to_pb(...).SerializeToString()``."""
    rng = np.random.default_rng(0)
    vals = [0.0, -0.0, 1.0, -1.5, np.nan, np.inf, -np.inf, 1e-300, 5e-324]
    N = len(vals)
    x = np.array([[v, rng.normal()] for v in vals])
    cols = {"k": np.arange(N) * 1000, "sensor_tx_ns": (np.arange(N) - 3, np.arange(N) % 2 == 0),
            "symbol": np.array([-1, 0, 1, 2**31 - 1, -(2**31), 36, 37, 5, -7]), "saturated": np.arange(N) % 2,
            "silent": np.zeros(N), "E": np.array(vals), "xi": (x, np.array([2, 0, 1, 2, 2, 2, 2, 2, 2])),
            "q": (x[:, ::-1], np.full(N, 2)), "header": T0 + np.arange(N) * 10**9 - 123_456_789,
            "log10_E": (np.array(vals), np.arange(N) % 3 == 0)}
    got = simrecord.encode("EncoderSample", N, cols)
    for k in range(N):
        d = {"k": int(cols["k"][k]), "symbol": int(cols["symbol"][k]), "saturated": int(cols["saturated"][k]),
             "silent": 0, "E": float(vals[k]), "xi": tuple(x[k, :cols["xi"][1][k]]), "q": tuple(x[k, ::-1])}
        if cols["sensor_tx_ns"][1][k]:
            d["sensor_tx_ns"] = int(cols["sensor_tx_ns"][0][k])
        extra = {"header": int(cols["header"][k])}
        if cols["log10_E"][1][k]:
            extra["log10_E"] = float(vals[k])
        assert got[k] == to_pb(d, "EncoderSample", extra).SerializeToString(), k


@pytest.mark.slow  # half a second or more on a warm cache
def test_fast_runs_decimate_the_phase_plane_and_keep_every_sample(tmp_path):
    sc = _sc("paper", T=0.002, duration=4.0)
    res = simulate_scenario(sc)
    N = len(res.t)
    every = recording.phase_every(sc.T)
    assert every == 5
    a, b = tmp_path / "a.mcap", tmp_path / "b.mcap"
    recording.record_simulation(a, sc, res, t0_ns=T0, bulk=False)
    counts = recording.record_simulation(b, sc, res, t0_ns=T0)
    ma = [m for m in _messages(a) if m[0] != "/phase"]
    mb = [m for m in _messages(b) if m[0] != "/phase"]
    assert ma == mb
    for t in ("/telemetry/plant", "/telemetry/encoder", "/telemetry/attacker", "/telemetry/controller"):
        assert counts[t] == N + (t == "/telemetry/plant")
    phase = [m for m in _messages(b) if m[0] == "/phase"]
    assert counts["/phase"] == len(phase) == -(-N // every)
    assert [m[1] for m in phase] == [T0 + k * int(round(sc.T * 1e9)) for k in range(0, N, every)]
    run = _metadata(b)["testbed.run"]
    assert json.loads(run["phase_every"]) == every and run["writer"] == "bulk" and run["simulator"] == "batch"


@pytest.mark.slow  # half a second or more on a warm cache
def test_every_reader_reads_a_decimated_recording(tmp_path):
    from helpers.recordings import assert_columns_equal_reference

    import testbed
    from testbed.record import columns, reader
    from testbed.runs import report

    sc = _sc("paper", T=0.002, duration=4.0)
    res = simulate_scenario(sc)
    path = tmp_path / "r.mcap"
    recording.record_simulation(path, sc, res)
    rec = reader.read(path)
    assert len(rec.telemetry["plant"]) == len(res.t)
    assert_columns_equal_reference(columns.read_columns(path), rec)
    run = testbed.open(path)
    assert np.array_equal(run.arrays["x"], res.x) and np.array_equal(run.arrays["E_dec"], res.E_dec)
    rep = report.report(path, resimulate=None)
    assert rep["samples"] == len(res.t)
    assert rep["resimulation"]["reproduced"] is True and rep["resimulation"]["checked"] == len(res.t)


@pytest.mark.parametrize("chunk_size", [1 << 20, 700])
def test_the_fast_adder_writes_the_file_mcaps_add_message_writes(chunk_size):
    """The same messages through mcap's ``add_message`` and through ``fast_adder`` (mixed with ``add_message``,
    chunks closed on the way): the two files are the same bytes."""
    # fast_adder writes into mcap's private Writer state (``_Writer__chunk_builder``, its
    # ``record_writer._buffer``, ``_Writer__statistics``, ...): mcap 1.6 has no public way to append an
    # encoded message more cheaply than ``add_message``.  Why it pays: 200,000 messages of 60 bytes on 3
    # channels into ZSTD chunks of 1 MiB took 8.7-9.3 us each through add_message and 3.5-4.0 us each
    # through fast_adder (2.2-2.7 times less; mcap 1.6.0, Python 3.11, this project's shared 2-core
    # machine, two runs of each, timed with time.perf_counter around the loop of adds).  This test is what
    # fails when mcap's internals change: the fast path must be taken (not the fallback) and write the
    # same bytes.
    import io

    from mcap.writer import CompressionType, Writer

    rng = np.random.default_rng(3)
    msgs = [(int(rng.integers(0, 3)), T0 + 1000 * (k // 3), rng.bytes(int(rng.integers(0, 120)))) for k in range(3000)]

    def write(fast: bool) -> bytes:
        f = io.BytesIO()
        w = Writer(f, chunk_size=chunk_size, compression=CompressionType.ZSTD, enable_data_crcs=True)
        w.start(profile="testbed", library="test")
        sid = w.register_schema(name="s", encoding="protobuf", data=b"x")
        chans = [w.register_channel(topic=f"/t{i}", message_encoding="protobuf", schema_id=sid) for i in range(3)]
        add = simrecord.fast_adder(w) if fast else w.add_message
        assert (getattr(add, "__self__", None) is w) != fast  # the fast path, not a fallback
        for i, (c, lt, data) in enumerate(msgs):
            (w.add_message if i % 97 == 0 else add)(chans[c], lt, data, lt + 5)
            if i == 1500:
                w.flush()
        w.finish()
        return f.getvalue()

    a, b = write(False), write(True)
    assert len(a) > 100_000 or chunk_size > 1000
    assert a == b
