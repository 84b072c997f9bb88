"""Recordings as data (fast tier): the columnar reader, testbed.open / simulate, export, compare, bad input.

The columnar reader (``testbed.record.columns``) is checked against the reference
reader (``testbed.record.reader.read``, protobuf classes and dataclasses) on
complete and cut files; the streamed ``report --json`` against the in-memory
report; export round-trips through pyarrow; compare on identical and different
runs; and every command that reads a recording turns cut, bit-flipped, foreign
and crafted files into one line and exit 2 (or a report marked TRUNCATED).
"""

from __future__ import annotations

import dataclasses
import io
import json
import random
import re
import resource
import subprocess
from pathlib import Path

import numpy as np
import pytest
from helpers.cli import PY, tb_run_here
from helpers.recordings import assert_columns_equal_reference
from helpers.sims import sim_recording

import testbed
from testbed import scenario
from testbed.common.errors import BadInput
from testbed.record import columns, reader, recording, schema, topics
from testbed.record.summary import write_json
from testbed.runs.report import report
from testbed.sim.batch import simulate_scenario
from testbed.wire import messages as msg

ROOT = Path(__file__).resolve().parents[2]





# ---------------------------------------------------------------------------- the reader
@pytest.mark.parametrize("name", ["paper", "cartpole"])
def test_columns_equal_the_reference_reader(tmp_path, name):
    sc, res, path = sim_recording(tmp_path, name, duration=6.0)
    cols = columns.read_columns(path)
    assert not cols.truncated and cols.rows == sc.n_steps and not cols.rejected and cols.malformed == 0
    assert_columns_equal_reference(cols, reader.read(path))
    assert np.array_equal(cols.get("encoder", "E"), res.E_enc) and np.array_equal(cols.get("plant", "x"), res.x)


@pytest.mark.slow  # half a second or more on a warm cache
def test_a_file_cut_mid_chunk_reads_like_the_reference(tmp_path):
    sc = scenario.with_overrides(scenario.load("paper"), {"duration": 20.0})
    res = simulate_scenario(sc)
    path = tmp_path / "full.mcap"
    recording.record_simulation(path, sc, res, overrides={"duration": 20.0}, flush_interval=0.0)
    data = path.read_bytes()
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    c = chunks[len(chunks) // 2]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:c.chunk_start_offset + c.chunk_length // 2])   # in the middle of a chunk
    cols = columns.read_columns(cut)
    rec = reader.read(cut)
    assert cols.truncated and rec.truncated and 0 < cols.last_k("plant") < len(res.t) - 1
    assert_columns_equal_reference(cols, rec)
    r = tb_run_here("report", cut)
    assert r.returncode == 0 and "TRUNCATED" in r.stdout, r.stderr
    s = report(cut)
    assert s["recording"]["truncated"] and s["samples"] == cols.last_k("plant") + 1


def test_streamed_json_equals_the_report(tmp_path):
    _, _, path = sim_recording(tmp_path, "paper-escape", duration=8.0)
    buf = io.StringIO()
    write_json(report(path, arrays=True), buf)
    assert json.loads(buf.getvalue()) == json.loads(json.dumps(report(path)))


def test_telemetry_outside_0_N_is_rejected_and_counted(tmp_path):
    """The crafted file of issue 11 (k = 1e7 in a 9 KB recording): nothing is sized by it."""
    sc = scenario.with_overrides(scenario.load("paper"), {"duration": 2.0})
    path = tmp_path / "crafted.mcap"
    w = recording.RecordingWriter(path)
    recording.write_text_metadata(w, sc, source="simulate", run_id="crafted", extra={"scenario_overrides":
                                                                                     {"duration": 2.0}})
    for k in (0, 1, 10_000_000, 2**32 - 1, 20):
        w.write("/telemetry/plant", msg.PlantTelemetry(k=k, t_ns=k, sensor_tx_ns=0, u_rx_ns=0, delay_ns=0, theta=0,
                                                       flags=0, flow_status=0, x=(0.1, 0.2), u=(0.0,)), k)
    w.write("/telemetry/plant", msg.PlantTelemetry(k=3, t_ns=0, sensor_tx_ns=0, u_rx_ns=0, delay_ns=0, theta=0,
                                                   flags=0, flow_status=0, x=(0.1, 0.2, 0.3), u=(0.0,)), 3)
    w.close()
    assert path.stat().st_size < 20_000
    cols = columns.read_columns(path)
    assert cols.rows == 20 and cols.rejected == {"plant": 3} and cols.malformed == 1   # k >= N; a 3-vector
    r = tb_run_here("report", path, "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["samples"] == 2 and s["recording"]["rejected"] == {"plant": 3}
    r = tb_run_here("report", path)
    assert "WARNING: 3 telemetry messages rejected" in r.stdout


# ---------------------------------------------------------------------------- bad input, every command
def _foreign_mcap(path):
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("x", "jsonschema", b"{}")
        ch = w.register_channel("/other", "json", sid)
        w.add_message(ch, 1, b"{}", 1)
        w.finish()


def _bad_files(tmp_path) -> dict[str, Path]:
    _, _, good = sim_recording(tmp_path, "paper", duration=3.0)
    data = bytearray(good.read_bytes())
    out = {}
    (tmp_path / "text.mcap").write_bytes(b"hello, not a recording")
    out["not MCAP"] = tmp_path / "text.mcap"
    out["missing"] = tmp_path / "missing.mcap"
    out["directory"] = tmp_path
    _foreign_mcap(tmp_path / "foreign.mcap")
    out["foreign"] = tmp_path / "foreign.mcap"
    flipped = bytearray(data)
    flipped[len(data) // 3] ^= 0x10           # in a closed file
    (tmp_path / "flipped.mcap").write_bytes(bytes(flipped))
    out["bit-flipped"] = tmp_path / "flipped.mcap"
    return out


def _flipped(tmp_path, data: bytes, at: int):
    """A copy of a recording's bytes with one bit of byte ``at`` flipped, as ``bad.mcap``."""
    flipped = bytearray(data)
    flipped[at] ^= 0x01
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(flipped))
    return bad


def _read_until_corrupt(path, bodies: set[int], match: str) -> list[int]:
    """The offsets ``read_ahead`` yields from ``path`` before it raises the ``CorruptRecording`` ``match`` says."""
    from testbed.record import mcapfile

    seen = []
    with pytest.raises(mcapfile.CorruptRecording, match=match):
        for off, _op, _, _ in mcapfile.read_ahead(mcapfile._File(path), bodies=bodies, crc=[0]):
            seen.append(off)
    return seen


@pytest.mark.slow  # half a second or more on a warm cache
def test_the_read_ahead_raises_in_the_readers_thread_and_leaves_no_thread(tmp_path, monkeypatch):
    """Chunks are decompressed on a second thread (``mcapfile.read_ahead``): a chunk that fails its CRC is
    the reader's ``CorruptRecording``, at the chunk where it happened, and a reader that stops early (an
    error, or it stops iterating) stops the thread; a good file reads the same chunk for chunk as in turn."""
    import threading

    from testbed.record import mcapfile

    sc = scenario.with_overrides(scenario.load("paper"), {"duration": 6.0})
    good = tmp_path / "good.mcap"
    recording.record_simulation(good, sc, simulate_scenario(sc), flush_interval=0.0)  # a chunk a flush: dozens
    data = good.read_bytes()
    bodies = {mcapfile.OP_CHUNK, mcapfile.OP_DATA_END, mcapfile.OP_FOOTER}

    def alive() -> list:
        return [t for t in threading.enumerate() if t.name == "mcap-read-ahead"]

    fh = mcapfile._File(good)
    crc: list = [0]
    plain = [(off, op, mcapfile._decompress(fh, off, body)[0] if op == mcapfile.OP_CHUNK else body, crc[0])
             for off, op, body in mcapfile._records(fh, bodies=bodies, crc=crc) if op in bodies]
    ahead = list(mcapfile.read_ahead(mcapfile._File(good), bodies=bodies, crc=[0]))
    assert ahead == plain and sum(op == mcapfile.OP_CHUNK for _, op, _, _ in ahead) > 2 * mcapfile.AHEAD
    chunks = [off for off, op, _, _ in ahead if op == mcapfile.OP_CHUNK]
    it = mcapfile.read_ahead(mcapfile._File(good), bodies=bodies, crc=[0])
    next(it)
    it.close()  # stopped after one record: the thread ends with it
    assert not alive()
    # the last chunk's records changed (its CRC no longer holds): the chunks before it are read, then the error
    last = chunks[-1]
    bad = _flipped(tmp_path, data, last + 9 + 60)  # a byte of its compressed records (its header is 48 bytes)
    assert _read_until_corrupt(bad, bodies, f"at byte {last}") == chunks[:-1] and not alive()
    with pytest.raises(mcapfile.CorruptRecording):
        columns.read_columns(bad)
    assert not alive()
    # an error of the reader's own (here: the third chunk's records), while its traceback is still held
    walked = []

    def records(self, buf, where):
        walked.append(where)
        if len(walked) == 4:  # the first call loads the parser
            raise mcapfile.CorruptRecording("a record runs past the chunk's end")
        return orig(self, buf, where)

    orig = columns._Reader.records
    monkeypatch.setattr(columns._Reader, "records", records)
    with pytest.raises(mcapfile.CorruptRecording) as err:
        columns.read_columns(good)
    assert err.value is not None and not alive()


@pytest.mark.slow  # half a second or more on a warm cache
@pytest.mark.parametrize("hand", ["never", "always"])
def test_a_chunk_crc_is_checked_whichever_thread_checks_it(tmp_path, monkeypatch, hand):
    """A chunk's CRC is checked by the read-ahead's thread or, when that thread is not far ahead, by the reader
    (``mcapfile.HAND_CRC``): a chunk whose records decompress but whose stored CRC no longer matches them is
    ``CorruptRecording`` at that chunk either way, and a good file reads the same."""
    from testbed.record import mcapfile

    sc = scenario.with_overrides(scenario.load("paper"), {"duration": 6.0})
    good = tmp_path / "good.mcap"
    recording.record_simulation(good, sc, simulate_scenario(sc), flush_interval=0.0)
    monkeypatch.setattr(mcapfile, "HAND_CRC", 0 if hand == "never" else mcapfile.AHEAD + 1)
    checked: list[int] = []
    orig = mcapfile._check_crc
    monkeypatch.setattr(mcapfile, "_check_crc", lambda fh, off, inner, crc: (checked.append(crc), orig(fh, off,
                                                                                                          inner, crc)))
    bodies = {mcapfile.OP_CHUNK, mcapfile.OP_DATA_END, mcapfile.OP_FOOTER}
    chunks = [off for off, op, _, _ in mcapfile.read_ahead(mcapfile._File(good), bodies=bodies, crc=[0])
              if op == mcapfile.OP_CHUNK]
    assert len(checked) == len(chunks) > 3 and all(checked)   # every chunk's CRC, by one thread or the other
    # the stored CRC of the third chunk changed: its records still decompress, their CRC does not match
    third = chunks[2]
    bad = _flipped(tmp_path, good.read_bytes(), third + 9 + 24)  # its body: message start and end, size, CRC
    seen = _read_until_corrupt(bad, bodies, f"chunk at byte {third} fails its CRC")
    assert [o for o in seen if o in chunks] == chunks[:2]


@pytest.mark.slow  # half a second or more on a warm cache
def test_the_read_ahead_holds_a_chunk_larger_than_its_budget_alone(tmp_path, monkeypatch):
    """A chunk declaring more than ``AHEAD_BYTES`` is decompressed only once the reader waits for it: while the
    reader holds one, no other is decompressed (here every chunk is larger than a 1-byte budget), so a file's
    largest chunks are held one at a time as when read in turn; with the budget, the thread reads ahead."""
    import time

    from testbed.record import mcapfile

    sc = scenario.with_overrides(scenario.load("paper"), {"duration": 6.0})
    path = tmp_path / "run.mcap"
    recording.record_simulation(path, sc, simulate_scenario(sc), flush_interval=0.0)
    made: list[int] = []
    orig = mcapfile._decompress
    monkeypatch.setattr(mcapfile, "_decompress",
                        lambda fh, off, body, **kw: (made.append(off), orig(fh, off, body, **kw))[1])

    def ahead_while_held(wait: float) -> int:
        """Chunks decompressed beyond the one the reader holds, the most seen over 10 chunks; the reader
        holds each until one is (at most ``wait`` seconds)."""
        made.clear()
        most = 0
        for n, (off, _op, _, _) in enumerate(
                mcapfile.read_ahead(mcapfile._File(path), bodies={mcapfile.OP_CHUNK}, crc=[0])):
            end = time.monotonic() + wait
            while len(made) - made.index(off) - 1 == 0 and time.monotonic() < end:
                time.sleep(0.002)
            most = max(most, len(made) - made.index(off) - 1)
            if n == 9:
                break
        return most

    monkeypatch.setattr(mcapfile, "AHEAD_BYTES", 1)
    assert ahead_while_held(0.02) == 0
    monkeypatch.setattr(mcapfile, "AHEAD_BYTES", 16 << 20)
    assert 1 <= ahead_while_held(10.0) <= mcapfile.AHEAD


@pytest.mark.slow  # half a second or more on a warm cache
def test_bad_recordings_give_one_line_and_exit_2_in_every_command(tmp_path, capsys):
    """Not MCAP, missing, a directory, a foreign MCAP file, a bit-flipped recording: each in report, replay,
    export, compare and resimulate (in this process), and testbed.open; report as its own process too."""
    from testbed import cli

    bad = _bad_files(tmp_path)
    assert sorted(bad) == ["bit-flipped", "directory", "foreign", "missing", "not MCAP"]
    for what, path in bad.items():
        for cmd in (["report", path], ["replay", path, "--rrd", tmp_path / "x.rrd"],
                    ["export", path, "-o", tmp_path / "x.parquet"], ["compare", path, "paper"],
                    ["resimulate", path]):
            code = cli.main([str(c) for c in cmd])
            err = capsys.readouterr().err
            assert code == 2 and len(err.strip().splitlines()) == 1, (what, cmd, err)
        with pytest.raises(BadInput, match=re.escape(str(path))):  # as docs/api.md promises, a missing file too
            testbed.open(path)
        r = tb_run_here("report", path)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr, \
            (what, r.stderr)
    assert "corrupt recording" in tb_run_here("report", bad["bit-flipped"]).stderr
    assert "no scenario" in tb_run_here("report", bad["foreign"]).stderr


@pytest.mark.slow  # half a second or more on a warm cache
def test_a_cut_recording_is_read_up_to_the_cut_by_every_command(tmp_path, capsys):
    """A file cut mid-chunk (a killed recorder): report, replay, export and compare read what it holds."""
    from mcap.reader import make_reader

    from testbed import cli

    sc = scenario.with_overrides(scenario.load("paper"), {"duration": 20.0})
    path = tmp_path / "full.mcap"
    recording.record_simulation(path, sc, simulate_scenario(sc), overrides={"duration": 20.0}, flush_interval=0.0)
    data = path.read_bytes()
    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    c = chunks[len(chunks) // 2]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:c.chunk_start_offset + c.chunk_length // 2])
    n = columns.read_columns(cut).last_k("plant") + 1
    assert 0 < n < sc.n_steps
    assert cli.main(["report", str(cut)]) == 0 and "TRUNCATED" in capsys.readouterr().out
    rrd = tmp_path / "cut.rrd"
    assert cli.main(["replay", str(cut), "--rrd", str(rrd)]) == 0 and rrd.stat().st_size > 0
    assert cli.main(["export", str(cut), "-o", str(tmp_path / "cut.csv")]) == 0
    assert len((tmp_path / "cut.csv").read_text().splitlines()) == n + 1  # a header and the samples read
    capsys.readouterr()
    assert cli.main(["compare", str(cut), "paper", "--json"]) in (0, 1)  # paper with the recording's overrides
    cmp = json.loads(capsys.readouterr().out)
    assert cmp["samples"]["a"] == cmp["samples"]["compared"] == n and cmp["max_state_error"] == 0.0, cmp
    run = testbed.open(cut)
    assert run.N == n and len(run.arrays["x"]) == n


def _live_recording(path: Path) -> tuple[recording.RecordingWriter, scenario.Scenario]:
    """A writer of a live run's recording of the paper's scenario for 100 s (N = 1000), its metadata written."""
    sc = scenario.with_overrides(scenario.load("paper"), {"duration": 100.0})
    w = recording.RecordingWriter(path, flush_interval=60.0)
    recording.write_text_metadata(w, sc, source="live", run_id=path.stem,
                                  extra={"scenario_overrides": {"duration": 100.0}})
    return w, sc


@pytest.mark.slow  # seconds: the reader fuzzed with random, cut and flipped files
def test_fuzz_random_messages_cut_and_flipped_files(tmp_path):
    """Issue 11: 1e5 random telemetry messages, then cut and bit-flipped files: no traceback, bounded memory."""
    rng = random.Random(1234)
    path = tmp_path / "fuzz.mcap"
    w, sc = _live_recording(path)
    cls = schema.classes()
    roles = list(topics.TELEMETRY_SCHEMA.items())
    n_msgs = 100_000
    for i in range(n_msgs):
        role, name = roles[i % 4]
        if i % 3:
            data = bytes(rng.getrandbits(8) for _ in range(rng.randrange(0, 40)))
        else:  # well-formed protobuf with wild values
            m = cls[name](k=rng.choice([rng.randrange(1000), rng.getrandbits(32)]))
            if name == "PlantSample":
                m.x.extend([rng.uniform(-1e300, 1e300) for _ in range(rng.choice([0, 1, 2, 2, 2, 5]))])
                m.flags = rng.getrandbits(8)
                m.theta = rng.choice([0, 1, 255, rng.getrandbits(32)])
            else:
                m.rx_ns = rng.getrandbits(63)
            data = m.SerializeToString()
            if i % 7 == 0:  # a varint cut or a length prefix gone wrong
                data = data[:rng.randrange(len(data) + 1)] + bytes([0xFF] * rng.randrange(3))
        w.write_bytes(topics.TELEMETRY_TOPICS[role], name, data, i)
    w.close()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    cols = columns.read_columns(path)
    assert sum(cols.counts[topics.TELEMETRY_TOPICS[r]] for r in topics.TELEMETRY_TOPICS) == n_msgs
    accepted = int(cols.present.sum()) + cols.duplicates
    assert accepted + cols.malformed + sum(cols.rejected.values()) + cols.finals == n_msgs
    assert cols.rows == 1000 and cols.malformed > n_msgs / 3
    report((cols, sc))                          # the summary of garbage is still a summary
    data = path.read_bytes()
    outcomes = set()
    for trial in range(60):
        b = bytearray(data)
        if trial % 2:
            b = b[:rng.randrange(8, len(b))]
        for _ in range(rng.randrange(1, 4)):
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
        p = tmp_path / f"m{trial}.mcap"
        p.write_bytes(bytes(b))
        try:
            c = columns.read_columns(p)
            outcomes.add("truncated" if c.truncated else "read")
        except BadInput as e:
            assert "\n" not in str(e)
            outcomes.add("bad input")
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert "bad input" in outcomes and grown_mb < 200, (outcomes, grown_mb)


def test_varints_of_every_width_decode_as_protobuf_reads_them(tmp_path):
    """The parser's varints against protobuf's own (the reference reader): one to ten bytes (negative int64 and
    int32 take ten), fields left out, k at the widths' edges; an eleventh byte or a varint cut at the message's end
    makes the message malformed."""
    rng = random.Random(7)
    path = tmp_path / "varints.mcap"
    w, _sc = _live_recording(path)
    cls = schema.classes()
    edges = [0, 1, 127, 128, 16383, 16384, (1 << 31) - 1, -1, -(1 << 31), (1 << 62), -(1 << 63), (1 << 63) - 1]
    ks = rng.sample(range(1, 1000), 400)
    for i, k in enumerate(ks):
        v = edges[i % len(edges)] if i < 3 * len(edges) else rng.randrange(-(1 << 63), 1 << 63) >> rng.randrange(64)
        p = cls["PlantSample"](k=k, t_ns=v, u_rx_ns=~v, flow_status=max(-(1 << 31), min(v, (1 << 31) - 1)),
                               theta=i % 2, flags=i % 8 if i % 3 else 0)
        p.x.extend([rng.uniform(-1, 1), float(v)])
        p.u.extend([float(i)])
        e = cls["EncoderSample"](k=k, tx_ns=v, symbol=max(-(1 << 31), min(~v, (1 << 31) - 1)), E=abs(float(v)),
                                 saturated=bool(i % 2))
        e.xi.extend([1.0, -2.0])
        e.q.extend([float(v), 0.5])
        for role, name, m in (("plant", "PlantSample", p), ("encoder", "EncoderSample", e)):
            w.write_bytes(topics.TELEMETRY_TOPICS[role], name, m.SerializeToString(), 2 * i)
    malformed = [bytes([0x08]) + bytes([0x85]) * 10 + bytes([0x01]),    # k: an eleven-byte varint
                 bytes([0x08, 0x05, 0x10]) + bytes([0xFF]) * 4,        # t_ns cut short at the message's end
                 bytes([0x08, 0x06, 0x10]) + bytes([0xFF]) * 9 + b"\x01" + bytes([0x18, 0x80])]  # then one cut
    for data in malformed:
        w.write_bytes(topics.TELEMETRY_TOPICS["plant"], "PlantSample", data, 10_000)
    w.close()
    cols = columns.read_columns(path)
    assert cols.malformed == len(malformed)
    assert_columns_equal_reference(cols, reader.read(path))
    assert int(cols.has("plant").sum()) == len(ks) and set(cols.get("plant", "t_ns")[ks[:len(edges)]]) >= \
        {(1 << 63) - 1, -(1 << 63), -1}


# ---------------------------------------------------------------------------- the API, export, compare
@pytest.mark.slow  # half a second or more on a warm cache
def test_open_and_simulate_give_the_same_arrays(tmp_path):
    sc, res, path = sim_recording(tmp_path, "paper", duration=5.0)
    run = testbed.open(path)
    sim = testbed.simulate("paper", duration=5.0)
    assert run.source == "simulate" and run.N == sim.N == 50
    for key in ("k", "t", "x", "u", "q", "xi", "E", "E_dec", "xi_dec", "q_enc", "theta", "symbols", "saturated",
                "attack_on", "dropped"):
        assert np.array_equal(np.asarray(run.arrays[key]), np.asarray(sim.arrays[key])), key
    assert run.to_pandas().shape == (50, len(run.columns()))
    assert run.to_polars().shape == (50, len(run.columns()))


def test_simulate_overrides_are_validated_like_the_file():
    r = testbed.simulate("paper", x0=[0.05, -0.02], E0=0.2, M=8, T=0.05, duration=2.0,
                         attack={"intervals": [[0.5, 0.25]]})
    assert r.N == 40 and r.scenario.quantizer.M == 8 and r.arrays["E"][0] == 0.2
    assert list(r.arrays["x"][0]) == [0.05, -0.02] and r.summary["dos_intervals"] == [[0.5, 0.25]]
    with pytest.raises(BadInput, match="M"):
        testbed.simulate("paper", M=1)
    with pytest.raises(BadInput, match="unknown override"):
        testbed.simulate("paper", K=[[0, 0]])


@pytest.mark.slow  # end to end: the walkthrough script in its own process
def test_the_api_walkthrough_runs_on_the_public_api_only(tmp_path):
    """docs/walkthrough.py: only ``import testbed`` and the names it exports; it saves and plots a Run."""
    import ast

    src = (ROOT / "docs" / "walkthrough.py").read_text()
    tree = ast.parse(src)
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            assert not (node.module or "").startswith("testbed"), f"line {node.lineno}: from {node.module} import"
        if isinstance(node, ast.Import):
            for a in node.names:
                assert a.name == "testbed" or not a.name.startswith("testbed"), f"line {node.lineno}: {a.name}"
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "testbed":
            assert node.attr in {"open", "simulate", "compare", "BadInput", "Run"}, f"line {node.lineno}: {node.attr}"
    assert ".save(" in src and ".plot(" in src
    r = subprocess.run([PY, str(ROOT / "docs" / "walkthrough.py"), str(tmp_path)], capture_output=True, text=True,
                       timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "True None" in r.stdout and "BadInput: override(s) x0=[0.5, 0.5]" in r.stdout
    assert testbed.open(tmp_path / "paper.mcap").N == 100
    assert (tmp_path / "paper.pdf").read_bytes()[:5] == b"%PDF-"


@pytest.mark.parametrize("fmt", ["parquet", "csv"])
def test_export_round_trips_through_pyarrow(tmp_path, fmt):
    import pyarrow.csv as pcsv
    import pyarrow.parquet as pq

    sc, res, path = sim_recording(tmp_path, "paper", duration=5.0)
    out = tmp_path / f"run.{fmt}"
    r = tb_run_here("export", path, "--format", fmt, "-o", out, "--json")
    assert r.returncode == 0, r.stderr
    t = pq.read_table(out) if fmt == "parquet" else pcsv.read_csv(out)
    cols = testbed.open(path).columns()
    assert t.column_names == list(cols) and t.num_rows == 50
    assert t.column_names[:5] == ["k", "t", "x1", "x2", "u1"]
    for name, want in cols.items():
        assert np.array_equal(t.column(name).to_numpy(), want), name   # CSV too: shortest round-trip floats
    if fmt == "parquet":
        meta = {k.decode(): v.decode() for k, v in t.schema.metadata.items()}
        assert json.loads(meta["testbed.scenario"])["toml"] == sc.source
        assert json.loads(meta["testbed.summary"])["converged"] is False


@pytest.mark.slow  # half a second or more on a warm cache
def test_compare_identical_and_different_runs(tmp_path):
    _, _, a = sim_recording(tmp_path, "paper", duration=5.0)
    r = tb_run_here("compare", a, "paper", "--json", "--plot", tmp_path / "c.png")
    c = json.loads(r.stdout)
    assert r.returncode == 0 and c["identical"] and c["first_divergence"] is None and c["max_state_error"] == 0.0
    assert c["theta_differs_at"] == [] and c["symbols_differ_at"] == [] and c["samples"]["b"] == 50
    assert (tmp_path / "c.png").read_bytes()[:4] == b"\x89PNG"
    text = tmp_path / "late.toml"
    text.write_text(scenario.load("paper").source.replace("[[1.0, 1.2], [4.0, 0.8]]", "[[1.0, 1.2], [4.1, 0.8]]"))
    c = json.loads(tb_run_here("compare", a, text, "--json").stdout)
    assert not c["identical"] and c["first_divergence"] == 40 and c["theta_differs_at"][0] == 40
    assert c["theta_differs"] == 2 and c["max_state_error"] > 0


def test_the_summary_of_a_run_whose_nodes_died_early(tmp_path):
    """A node's telemetry that stops (killed): every count comes from the role that recorded it."""
    from collections import Counter

    from testbed.loop.quantizer import Codebook
    from testbed.record.summary import build_summary

    sc, res, path = sim_recording(tmp_path, "paper", duration=5.0)
    rec = reader.read(path)
    tele = {r: dict(d) for r, d in rec.telemetry.items()}
    for role in ("encoder", "attacker"):   # both die after sample 9
        tele[role] = {k: t for k, t in tele[role].items() if k < 10}
    tele["controller"] = {k: dataclasses.replace(t, reason=msg.ControllerTelemetry.DEADLINE, theta=1)
                          if k >= 10 else t for k, t in tele["controller"].items()}
    cols = columns.from_records(sc, tele, plant_final=rec.plant_final)
    s = build_summary(sc, cols, run_id="r", ack_via_attacker=False, nodes={}, faults=[],
                      codebook=Codebook(2, 6, True))
    want = Counter(t.reason for t in tele["controller"].values())
    assert s["loss_reasons"]["deadline"] == want[msg.ControllerTelemetry.DEADLINE] == 40 + int(res.theta[:10].sum())
    assert s["theta"][10:] == [1] * 40 and s["E"][10:] == [None] * 40 and s["symbols"][10:] == [-1] * 40
    assert s["attacker_dropped_at"] == [k for k in range(10) if res.theta[k]]


@pytest.mark.slow  # half a second or more on a warm cache
def test_report_prices_an_intervals_attack_as_declared(tmp_path):
    """Three back-to-back attacks (0.1 s each) lose samples 0..5, which the attacker's log shows as one run:
    the budget check prices what was declared, three attacks of 0.3 s in all, not one of 0.5 s."""
    f = tmp_path / "three.toml"
    text = (Path(scenario.__file__).parent / "bundled" / "paper.toml").read_text()
    text = text.replace("intervals = [[1.0, 1.2], [4.0, 0.8]]",
                        "intervals = [[0.0, 0.1], [0.2, 0.1], [0.4, 0.1]]\n"
                        "budget = { kappa_F = 3.0, rho_F = 0.0, kappa_D = 0.3, rho_D = 0.0 }")
    f.write_text(text.replace("duration = 30.0", "duration = 3.0"))
    sc = scenario.load(f)
    res = simulate_scenario(sc)
    assert res.theta.tolist()[:7] == [1, 1, 1, 1, 1, 1, 0]
    path = tmp_path / "three.mcap"
    recording.record_simulation(path, sc, res)
    dos = report(path)["dos"]
    assert dos["priced"] == "declared intervals"
    assert dos["count"] == 3 and dos["total_duration"] == pytest.approx(0.3)
    assert dos["logged_intervals"] == [[0.0, 0.5]]
    assert dos["budget"]["kappa_F_min"] == pytest.approx(3.0) and dos["budget"]["kappa_D_min"] == pytest.approx(0.3)
    assert dos["budget"]["within"] is True


# ---------------------------------------------------------------------------- post-mortems' shortcuts, same answers
def _tampered(rr: dict) -> dict:
    """A copy of ``recorded_run``'s record with E_7 at the encoder and x_9 of the plant off by a little."""
    live = dict(rr["live"], E=rr["live"]["E"].copy(), x=rr["live"]["x"].copy())
    live["E"][7] *= 1 + 1e-12
    live["x"][9, 0] += 1e-9
    return dict(rr, live=live)


@pytest.mark.slow  # half a second or more on a warm cache
@pytest.mark.parametrize("name", ["paper", "paper-greedy", "paper-mismatch", "cartpole", "pendulum"])
def test_the_kernel_replay_resimulates_as_the_loop_does(tmp_path, monkeypatch, name):
    """``testbed resimulate`` / the report's resimulation re-run on the batch kernel where the replay is theta
    alone: every key of its result equals the per-sample loop's (the protocol objects), on the recording and
    on a tampered copy (then both say NOT reproduced, at the same sample, with the same plant error)."""
    from testbed.runs import resimulate

    _, _, path = sim_recording(tmp_path, name, duration=4.0)
    rr = resimulate.recorded_run(testbed.open(path))
    cases = [(rr, None), (rr, 15), (_tampered(rr), None)]
    assert resimulate.kernel_replay(rr["scenario"], rr["replay"], rr["N"]) is not None
    fast = [resimulate.compare(r, limit=n) for r, n in cases]
    monkeypatch.setattr(resimulate, "kernel_replay", lambda *a: None)
    slow = [resimulate.compare(r, limit=n) for r, n in cases]
    assert fast == slow
    assert fast[0]["reproduced"] and not fast[2]["reproduced"] and fast[2]["first_divergence"] == 7
    assert fast[2]["plant_model_error"]["max"] > 0


def test_a_replay_beyond_theta_runs_the_loop(tmp_path):
    """Withheld samples (acks via the attacker, a corrupted payload) are the protocol objects' to replay."""
    from testbed.runs import resimulate

    _, _, path = sim_recording(tmp_path, "paper", duration=4.0)
    rr = resimulate.recorded_run(testbed.open(path))
    withheld = dataclasses.replace(rr["replay"], withheld=rr["replay"].withheld.copy())
    withheld.withheld[3] = True
    assert resimulate.kernel_replay(rr["scenario"], withheld, rr["N"]) is None
    late = dataclasses.replace(rr["replay"], u_missing=rr["replay"].u_missing.copy())
    late.u_missing[3] = True
    assert resimulate.kernel_replay(rr["scenario"], late, rr["N"]) is None


@pytest.mark.slow  # half a second or more on a warm cache
def test_the_region_cache_returns_the_solved_region(tmp_path, monkeypatch):
    """Theorem 1's paper-rule solves read back from the cache are those ``min_condition_P`` gives, bit for bit;
    a damaged entry is solved again."""
    from testbed.analysis import Loop, allowable_region
    from testbed.analysis.theorem1 import min_condition_P

    monkeypatch.setenv("TESTBED_CACHE_DIR", str(tmp_path))
    loop = Loop.from_scenario(scenario.load("paper"))
    solved = allowable_region(loop, "paper")
    (entry,) = (tmp_path / "regions").glob("*.npz")
    cached = allowable_region(loop, "paper")
    k0 = [min_condition_P(loop.Phi0, p)[1] for p in solved.phi0]
    k1 = [min_condition_P(loop.Phi1, p)[1] for p in solved.phi1]
    direct = np.log(np.array(k0))[:, None] + np.log(np.array(k1))[None, :]
    for reg in (solved, cached):
        assert reg.a.tobytes() == direct.tobytes()
        assert all(np.array_equal(P, min_condition_P(loop.Phi0, p)[0]) for P, p in zip(reg.P0[:3], reg.phi0[:3]))
    assert (cached.rho_F_max, cached.rho_D_max) == (solved.rho_F_max, solved.rho_D_max)
    entry.write_bytes(b"not an npz")
    assert allowable_region(loop, "paper").a.tobytes() == direct.tobytes()


@pytest.mark.slow  # half a second or more on a warm cache
def test_the_report_is_the_same_without_its_shortcuts(tmp_path, monkeypatch):
    """The whole report (text and JSON) of a recording with the kernel replay and the region cache equals the
    one computed the long way (the per-sample loop, the LMIs solved in an empty cache)."""
    import contextlib

    from testbed.commands.report import print_text
    from testbed.runs import resimulate
    from testbed.runs.report import report_of_run, run_of

    _, _, path = sim_recording(tmp_path, "paper", duration=6.0)

    def both():
        s = report_of_run(run_of(path), resimulate=None)
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            print_text(s)
        js = io.StringIO()
        write_json(s, js)
        return out.getvalue(), js.getvalue()

    monkeypatch.setenv("TESTBED_CACHE_DIR", str(tmp_path / "warm"))
    both()
    fast = both()  # the region read back from the cache, the resimulation on the kernel
    monkeypatch.setenv("TESTBED_CACHE_DIR", str(tmp_path / "cold"))
    monkeypatch.setattr(resimulate, "kernel_replay", lambda *a: None)
    slow = both()
    assert "reproduced bit for bit" in fast[0] and fast == slow


def test_export_streams_the_whole_table(tmp_path, monkeypatch):
    """``testbed export`` writes a few rows at a time: the CSV is the bytes of the whole table written at once,
    the Parquet file (``testbed.common.parquet``) reads back as that table, metadata included, in pyarrow and
    polars."""
    import pyarrow.csv as pcsv
    import pyarrow.parquet as pq

    from testbed.runs import export as ex

    _, _, path = sim_recording(tmp_path, "paper", duration=4.0)
    run = testbed.open(path)
    monkeypatch.setattr(ex, "ROWS", 7)
    whole = ex.table(run)
    pcsv.write_csv(whole, tmp_path / "whole.csv")
    ex.export(run, tmp_path / "rows.csv", "csv")
    assert (tmp_path / "rows.csv").read_bytes() == (tmp_path / "whole.csv").read_bytes()
    ex.export(run, tmp_path / "rows.parquet", "parquet")
    back = pq.read_table(tmp_path / "rows.parquet")
    assert back.equals(whole) and back.schema.metadata == whole.schema.metadata and back.num_rows == run.N > 7
    # plain pages: a dictionary of a run's floats (one value a row) is larger and slower than the values
    meta = pq.ParquetFile(tmp_path / "rows.parquet", page_checksum_verification=True).metadata
    used = {e for g in range(meta.num_row_groups) for c in range(meta.num_columns)
            for e in meta.row_group(g).column(c).encodings}
    assert meta.num_row_groups > 1 and not used & {"PLAIN_DICTIONARY", "RLE_DICTIONARY"}, used
    # a second reader, which shares no code with pyarrow, reads the same values
    import polars as pl

    df = pl.read_parquet(tmp_path / "rows.parquet")
    assert df.columns == whole.column_names
    for name in whole.column_names:
        assert np.array_equal(df[name].to_numpy(), whole.column(name).to_numpy(), equal_nan=True), name


@pytest.mark.slow  # a process of its own: what the JSON output imports
def test_the_streamed_json_does_not_import_pandas():
    """``write_json`` formats numbers with Arrow over numpy buffers (``summary.arrow_array``): ``pa.array`` would
    import pandas (40 MB in every ``--json`` of a run or a report)."""
    import subprocess
    import sys

    code = ("import io, sys, numpy as np\nfrom testbed.record.summary import write_json\n"
            "write_json({'x': np.array([1.0, 2.5, np.nan, 3.0, 1e-7, 2.0**60]), 'k': np.arange(5)}, io.StringIO())\n"
            "print('pyarrow' in sys.modules, 'pandas' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split() == ["True", "False"], r.stdout


@pytest.mark.parametrize("timing", ["ideal", "physical"])
def test_the_report_decodes_what_it_reads_and_reads_the_same_as_with_every_field(tmp_path, timing):
    """``summary.load`` leaves out the columns of a simulation's recording that nothing reads (x_meas without a
    sensor; delay_ns under ideal timing): the memory of a long recording. It reads the arrival of u_k under
    physical timing (the actuation section's). The report is the report of every field decoded."""
    from testbed.record.summary import load

    _, _, path = sim_recording(tmp_path, "paper", duration=4.0, timing=timing)
    cols, sc = load(path)
    assert ("plant", "x_meas") not in cols.lay.cols
    assert (("plant", "delay_ns") in cols.lay.cols) == (timing == "physical")
    every = load(path, fields=None)
    assert ("plant", "delay_ns") in every[0].lay.cols and ("plant", "x_meas") in every[0].lay.cols
    assert report((cols, sc)) == report(every)


@pytest.mark.parametrize("fmt", ["parquet", "csv"])
def test_an_export_that_cannot_be_written_is_bad_input_and_leaves_no_parquet_without_its_footer(tmp_path, fmt):
    """A missing folder and a full disk (/dev/full): one line (``BadInput``, exit 2), no half-written Parquet."""
    from testbed.runs import export as ex

    _, _, path = sim_recording(tmp_path, "paper", duration=2.0)
    run = testbed.open(path)
    with pytest.raises(BadInput, match="cannot write"):
        ex.export(run, tmp_path / "no" / "such" / f"x.{fmt}", fmt)
    if Path("/dev/full").exists():
        with pytest.raises(BadInput, match="cannot write /dev/full"):
            ex.export(run, "/dev/full", fmt)
        assert Path("/dev/full").is_char_device()
