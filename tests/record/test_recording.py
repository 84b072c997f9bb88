"""Recordings (fast tier): protobuf schemas, MCAP writer and reader, truncation, ``testbed report``."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import textwrap
import time

import numpy as np
import pytest
from failclosed import require
from helpers.cli import PY, tb_run_here
from helpers.sims import sim_recording

from testbed import scenario
from testbed.record import reader, recording, schema
from testbed.runs.report import report
from testbed.sim.batch import simulate_scenario, summarize
from testbed.wire import messages as msg


# ---------------------------------------------------------------------------- schemas
def test_every_schema_builds_and_round_trips_its_dataclass():
    cls = schema.classes()
    assert set(cls) == set(schema.SPEC)
    samples = [
        msg.PlantTelemetry(k=7, t_ns=700, sensor_tx_ns=msg.NO_TIME, u_rx_ns=712, delay_ns=3, theta=1, flags=9,
                           flow_status=0, x=(0.1, -2.5), u=(0.25,)),
        msg.EncoderTelemetry(k=1, sensor_tx_ns=1, rx_ns=2, tx_ns=msg.NO_TIME, symbol=36, saturated=1, silent=0,
                             E=1e-300, xi=(0.0, 1.0), q=(0.5, 0.5)),
        msg.ControllerTelemetry(k=2, sym_stamp_ns=msg.NO_TIME, rx_ns=msg.NO_TIME, tx_ns=5, symbol=-1, theta=1,
                                reason=1, E=2.0, xi=(1.0, 2.0), q=(0.0, 0.0), u=(0.0,)),
        msg.AttackerTelemetry(k=3, rx_ns=4, tx_ns=msg.NO_TIME, dropped=1, corrupted=0, attack_on=1,
                              dropped_total=9, forwarded_total=2),
        msg.Symbol(k=4, stamp_ns=8, data=b"\x07"), msg.Ack(k=4, stamp_ns=9, theta=0, last_rx=4),
        msg.Event(node="encoder", kind="saturation", k=5, t_ns=msg.NO_TIME, detail="x"),
        msg.Start(run_id="r", t0_ns=1, T_ns=2, n_steps=3, digest="d", timing="ideal", ack_via_attacker=True),
    ]
    for obj in samples:
        name = schema.SCHEMA_OF[type(obj)]
        data = schema.to_pb(obj).SerializeToString()
        back = schema.from_pb(cls[name].FromString(data), name)
        assert back == obj, name
    # an absent time is an absent field, not a sentinel number
    m = schema.to_pb(samples[0])
    assert not m.HasField("sensor_tx_ns") and m.HasField("u_rx_ns")


def test_the_stored_descriptor_set_is_self_contained():
    built = schema.classes_from(schema.file_descriptor_set())
    assert set(built) == {f"testbed.{n}" for n in schema.SPEC} | {"google.protobuf.Timestamp"}
    assert "| `E` | f64 |" in schema.describe()


# ---------------------------------------------------------------------------- simulate --out and report
@pytest.mark.parametrize("name", ["paper", "paper-escape", pytest.param("cartpole", marks=pytest.mark.slow)])  # cartpole: seconds
def test_report_of_a_simulation_equals_simulate_json(tmp_path, name):
    sc, res, path = sim_recording(tmp_path, name, duration=8.0)
    want = json.loads(json.dumps(summarize(sc, res)))
    got = report(path)
    assert got["source"] == "simulate" and not got["recording"]["truncated"] and got["recording"]["complete"]
    for key, value in want.items():
        assert got[key] == value, key
    assert got["agreement"]["all_agree"] and got["agreement"]["compared"] == len(res.t)
    assert got["dropped_by_attacker"] == int(res.theta.sum())
    assert [iv[0] for iv in got["dos"]["intervals"]] == [iv[0] for iv in res.intervals().intervals]


def test_overrides_are_stored_and_reapplied(tmp_path):
    sc, res, path = sim_recording(tmp_path, "paper", duration=3.0, mode="ideal")
    rec = reader.read(path)
    back = rec.scenario()
    assert back.run.duration == 3.0 and back.quantizer.mode == "ideal" and back.n_steps == 30
    assert rec.metadata["testbed.scenario"]["toml"] == scenario.load("paper").source
    assert rec.metadata["testbed.software"]["mcap"]


def test_budget_of_a_greedy_attack_is_checked(tmp_path):
    sc, res, path = sim_recording(tmp_path, "paper-greedy", duration=20.0)
    b = report(path)["dos"]["budget"]
    assert b["declared"] == dict(zip(("kappa_F", "rho_F", "kappa_D", "rho_D"), sc.attack.budget))
    assert b["within"] and b["kappa_F_min"] <= b["declared"]["kappa_F"] + 1e-9


def test_budget_violation_is_reported(tmp_path):
    """A scenario whose declared budget its own intervals exceed: the report says EXCEEDED."""
    text = scenario.load("paper").source.replace(
        'intervals = [[1.0, 1.2], [4.0, 0.8]]   # [start, length] in seconds',
        'intervals = [[1.0, 1.2], [4.0, 0.8]]\nbudget = { kappa_F = 1.0, rho_F = 0.0, kappa_D = 0.5, rho_D = 0.0 }')
    assert "budget" in text
    f = tmp_path / "tight.toml"
    f.write_text(text)
    sc = scenario.with_overrides(scenario.load(str(f)), {"duration": 6.0})
    res = simulate_scenario(sc)
    recording.record_simulation(tmp_path / "t.mcap", sc, res)
    b = report(tmp_path / "t.mcap")["dos"]["budget"]
    assert not b["within"] and b["kappa_F_min"] == pytest.approx(2.0) and b["kappa_D_min"] > 0.5  # two attacks


def test_plain_mcap_reader_opens_and_decodes_it(tmp_path):
    from mcap.reader import make_reader

    sc, res, path = sim_recording(tmp_path, "paper", duration=5.0)
    with open(path, "rb") as f:
        r = make_reader(f)
        summ = r.get_summary()
        assert summ.statistics.message_count == sum(reader.read(path).counts.values())
        enc = []
        for sch, ch, m in r.iter_messages(topics=["/telemetry/encoder"]):
            assert sch.encoding == "protobuf" and ch.message_encoding == "protobuf"
            cls = schema.classes_from(sch.data)[sch.name]
            enc.append(cls.FromString(m.data).E)
        assert {md.name for md in r.iter_metadata()} >= {"testbed.scenario", "testbed.software", "testbed.run",
                                                         "testbed.recorder"}
    assert np.array_equal(np.array(enc), res.E_enc)


@pytest.mark.slow  # half a second or more on a warm cache
def test_report_cli_json_and_plot(tmp_path):
    _, _, path = sim_recording(tmp_path, "paper", duration=6.0)
    png = tmp_path / "fig.png"
    r = tb_run_here("report", path, "--json", "--plot", png)
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["scenario"] == "paper" and len(s["t"]) == 60
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow  # seconds: a whole recording re-simulated
def test_report_resimulates_the_first_samples_by_default_and_all_when_asked(tmp_path, monkeypatch, capsys):
    """The report's resimulation check covers RESIMULATE_SAMPLES samples by default (the API's and the
    command's default, read when the report is made) and says so; all or none on request."""
    import testbed.runs.report as rep_mod
    from testbed import cli

    _, res, path = sim_recording(tmp_path, "paper")
    N = len(res.t)
    assert rep_mod.RESIMULATE_SAMPLES == 10_000 > N
    assert rep_mod.report(path)["resimulation"]["checked"] == N  # the real default: all of a 30 s run
    monkeypatch.setattr(rep_mod, "RESIMULATE_SAMPLES", 100)
    part = rep_mod.report(path)["resimulation"]  # the default, not an argument
    assert part["checked"] == 100 and part["samples"] == N and part["reproduced"] is True
    assert f"samples 0 to 99 of {N}" in part["verdict"] and part["first_divergence"] is None
    assert cli.main(["report", str(path), "--json"]) == 0  # the command's default too
    assert json.loads(capsys.readouterr().out)["resimulation"]["checked"] == 100
    full = rep_mod.report(path, resimulate=None)["resimulation"]
    assert full["checked"] == N and full["reproduced"] is True and "of" not in full["verdict"]
    none = rep_mod.report(path, resimulate=0)["resimulation"]
    assert none["reproduced"] is None and "not resimulated" in none["verdict"]
    r = tb_run_here("report", path, "--json", "--resimulate", "all")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["resimulation"]["checked"] == N
    r = tb_run_here("report", path, "--resimulate", "-3")
    assert r.returncode == 2 and "Traceback" not in r.stderr and "--resimulate" in r.stderr


def test_simulate_out_flag_writes_a_recording(tmp_path):
    out = tmp_path / "s.mcap"
    r = tb_run_here("simulate", "paper", "--duration", "2", "--out", out)
    assert r.returncode == 0, r.stderr
    assert len(reader.read(out).telemetry["plant"]) == 20


# ---------------------------------------------------------------------------- bad input
def test_not_an_mcap_file_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"hello, not a recording")
    with pytest.raises(ValueError, match="not an MCAP file"):
        reader.read(bad)
    r = tb_run_here("report", bad)
    assert r.returncode == 2 and "not an MCAP file" in r.stderr
    r = tb_run_here("report", tmp_path / "missing.mcap")
    assert r.returncode == 2 and "No such file" in r.stderr


def test_garbage_messages_are_counted_not_fatal(tmp_path):
    path = tmp_path / "g.mcap"
    w = recording.RecordingWriter(path)
    w.write("/telemetry/encoder", msg.EncoderTelemetry(k=0, sensor_tx_ns=0, rx_ns=0, tx_ns=0, symbol=1, saturated=0,
                                                       silent=0, E=1.0, xi=(0.0,), q=(0.0,)), 10)
    w.write_bytes("/telemetry/encoder", "EncoderSample", b"\xff\xff\xff\xff", 20)  # not protobuf
    w.close()
    rec = reader.read(path)
    assert len(rec.telemetry["encoder"]) == 1 and len(rec.malformed) == 1
    with pytest.raises(ValueError, match="no scenario"):
        rec.scenario()


# ---------------------------------------------------------------------------- crash safety
def _complete_sim_file(tmp_path):
    sc = scenario.with_overrides(scenario.load("paper"), {"duration": 20.0})
    res = simulate_scenario(sc)
    path = tmp_path / "full.mcap"
    w = recording.RecordingWriter(path, flush_interval=0.0)  # a chunk per message: many cut points
    recording.write_text_metadata(w, sc, source="simulate", run_id="cut")
    for k in range(len(res.t)):
        w.write("/telemetry/encoder", msg.EncoderTelemetry(k=k, sensor_tx_ns=0, rx_ns=0, tx_ns=0, symbol=0,
                                                           saturated=0, silent=0, E=float(res.E_enc[k]),
                                                           xi=tuple(res.xi_enc[k]), q=tuple(res.q_enc[k])), k)
    w.close()
    return path, res


@pytest.mark.parametrize("frac", [0.15, 0.33, 0.5, 0.77, 0.999])
def test_a_file_cut_anywhere_reads_up_to_the_cut(tmp_path, frac):
    from mcap.reader import make_reader

    path, res = _complete_sim_file(tmp_path)
    data = path.read_bytes()
    n_cut = int(len(data) * frac)
    with open(path, "rb") as f:  # the chunks (one message each) that lie wholly before the cut
        whole = sum(1 for ci in make_reader(f).get_summary().chunk_indexes
                    if ci.chunk_start_offset + ci.chunk_length <= n_cut)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:n_cut])
    rec = reader.read(cut)
    assert rec.truncated
    ks = sorted(rec.telemetry["encoder"])
    assert ks == list(range(len(ks)))           # a prefix, nothing invented
    assert len(ks) >= whole - 1 and whole > 0   # every complete chunk before the cut (but a partial last one)
    assert all(rec.telemetry["encoder"][k].E == res.E_enc[k] for k in ks)


_WRITER = textwrap.dedent("""
    import sys, time
    from testbed.record import recording
    from testbed.wire import messages as msg
    w = recording.RecordingWriter(sys.argv[1], flush_interval=0.5)
    k = 0
    print("ready", flush=True)
    while True:
        t = time.time_ns()
        w.write("/telemetry/attacker", msg.AttackerTelemetry(k=k, rx_ns=t, tx_ns=t, dropped=0, corrupted=0,
                attack_on=0, dropped_total=0, forwarded_total=k), t)
        k += 1
        time.sleep(0.001)
""")


@pytest.mark.slow  # its own processes (an interpreter start-up each)
def test_sigkill_of_a_writer_loses_at_most_the_last_second(tmp_path):
    path = tmp_path / "killed.mcap"
    p = subprocess.Popen([PY, "-c", _WRITER, str(path)], stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "ready"
        time.sleep(2.5)
        t_kill = time.time_ns()
        os.kill(p.pid, signal.SIGKILL)
        p.wait(10)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    rec = reader.read(path)
    assert rec.truncated
    ks = sorted(rec.telemetry["attacker"])
    assert len(ks) > 500 and ks == list(range(len(ks)))
    last = rec.telemetry["attacker"][ks[-1]].rx_ns
    assert t_kill - last < 1.0e9, f"lost {(t_kill - last) / 1e9:.2f} s"


def test_the_format_document_is_current():
    from pathlib import Path

    doc = Path(__file__).resolve().parents[2] / "docs" / "recording-format.md"
    assert doc.read_text() == recording.markdown(), "regenerate: python -m testbed.record.recording > docs/recording-format.md"


def test_rerun_decodes_the_protobuf_channels(tmp_path):
    """Rerun's own MCAP importer reads the file and decodes our schemas (not raw bytes)."""
    rerun_cli = os.path.join(os.path.dirname(PY), "rerun")
    if not os.path.exists(rerun_cli):
        require("rerun", "rerun CLI not installed next to this Python")
    _, _, path = sim_recording(tmp_path, "paper", duration=2.0)
    rrd = tmp_path / "conv.rrd"
    r = subprocess.run([rerun_cli, "mcap", "convert", str(path), "-o", str(rrd)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    r = subprocess.run([rerun_cli, "rrd", "print", str(rrd)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0
    for name in ("PlantSample", "EncoderSample", "ControllerSample", "AttackerSample"):
        assert f"testbed.{name}:message" in r.stdout, name


def test_the_launcher_waits_longer_for_the_recorder_than_it_drains():
    """A recorder behind on a long run drains its queue within its own grace after the SIGINT; the launcher
    waits longer than that before it kills it, so the file is closed by the recorder, never cut."""
    from testbed.live.recorder import STOP_WAIT_S
    from testbed.nodes.recorder import RECORDER_STOP_GRACE_S

    assert STOP_WAIT_S > RECORDER_STOP_GRACE_S


@pytest.mark.parametrize("compression", ["lz4", "none"])
def test_lz4_and_uncompressed_chunks_read_as_zstd_ones(tmp_path, compression):
    """A recording whose chunks another tool wrote with lz4 or no compression (mcap's own ``Writer``, the same
    records): the columnar reader and the reference reader read it as the zstd original."""
    from helpers.recordings import assert_columns_equal_reference
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    from testbed.record import columns

    _sc, _res, path = sim_recording(tmp_path, "paper", duration=6.0)
    out = tmp_path / f"{compression}.mcap"
    with open(path, "rb") as f, open(out, "wb") as g:
        r = make_reader(f)
        w = Writer(g, chunk_size=16 << 10, compression=getattr(CompressionType, compression.upper()))
        header = r.get_header()
        w.start(profile=header.profile, library=header.library)
        schemas: dict[int, int] = {}
        chans: dict[int, int] = {}
        for sch, ch, m in r.iter_messages(log_time_order=False):
            if sch is not None and sch.id not in schemas:
                schemas[sch.id] = w.register_schema(sch.name, sch.encoding, sch.data)
            if ch.id not in chans:
                chans[ch.id] = w.register_channel(ch.topic, ch.message_encoding, schemas.get(ch.schema_id, 0),
                                                  ch.metadata)
            w.add_message(chans[ch.id], m.log_time, m.data, m.publish_time, m.sequence)
        for md in r.iter_metadata():
            w.add_metadata(md.name, md.metadata)
        w.finish()
    with open(out, "rb") as g:
        assert len(make_reader(g).get_summary().chunk_indexes) > 3   # several chunks, each of that compression
    cols, ref = columns.read_columns(out), columns.read_columns(path)
    assert not cols.truncated and not cols.rejected and cols.malformed == 0 and cols.rows == ref.rows
    for t in cols.tables:
        assert np.array_equal(cols.tables[t], ref.tables[t], equal_nan=t == 3)
    assert np.array_equal(cols.present, ref.present) and cols.counts == ref.counts
    assert_columns_equal_reference(cols, reader.read(out))
