"""Process tier: live runs record to MCAP; the recording survives SIGKILL of any node, the recorder included.

Run with ``pytest -m process``.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time

import numpy as np
import pytest
from helpers.cli import TIMEOUT, tb_cmd
from helpers.live import BIT_EXACT_KEYS, TOPOLOGIES, live, live_exact, simulate
from helpers.procs import cmdlines, procs_with
from helpers.recordings import assert_columns_equal_reference

import testbed
from testbed.record import columns, reader
from testbed.runs.compare import compare
from testbed.runs.report import report

pytestmark = pytest.mark.process


@pytest.mark.parametrize("topology", TOPOLOGIES)
def test_live_recording_reports_what_the_simulator_computes(run_id, tmp_path, topology):
    path = tmp_path / "live.mcap"
    rc, s, err = live_exact(run_id, "paper", "--duration", "5", "--out", str(path), *topology)
    assert rc == 0, (s["faults"], err[-2000:])
    assert s["recording"]["complete"] and s["recording"]["path"] == str(path)
    r = report(path)
    sim = simulate("paper", 5.0)
    assert s["timing"]["deadline_misses"] == 0, (s["timing"], s["event_log"])  # else the loops differ
    for key in BIT_EXACT_KEYS:          # the recording alone gives the simulator's numbers, bit for bit
        assert r[key] == sim[key], key
    for key in ("converged", "escaped", "packets_dropped", "dos_intervals", "encoder_decoder_agree", "final_norm"):
        assert r[key] == sim[key], key
    assert r["agreement"]["all_agree"] and r["agreement"]["compared"] == 50
    assert r["source"] == "live" and r["outcome"] == "done" and not r["recording"]["truncated"]
    assert r["timing"]["sampling_jitter_us"]["n"] == 50
    # what crossed the network is there too (T = 0.1 s: the control path is recorded)
    msgs = reader.read(path).counts
    assert msgs["/loop/symbol/tx"] == 50 and msgs["/loop/actuation"] == 50
    # four messages a sample (the ack rides on the actuation), three when the encoder is colocated
    assert msgs.get("/loop/sensor", 0) == (0 if topology else 50) and "/loop/ack/tx" not in msgs
    assert msgs["/loop/symbol/rx"] == 50 - sim["packets_dropped"]
    assert {"/summary/plant", "/summary/encoder", "/summary/attacker", "/summary/controller",
            "/summary/launcher"} <= set(msgs)
    # and the report's timing equals the launcher's
    assert r["timing"]["sensor_to_actuator_us"] == s["timing"]["sensor_to_actuator_us"]
    # the columnar reader equals the reference reader on a live recording, and the run is the simulation
    assert_columns_equal_reference(columns.read_columns(path), reader.read(path))
    c = compare(path, "paper")
    assert c["identical"] and c["first_divergence"] is None and c["samples"]["a"] == 50, c
    run = testbed.open(path)
    assert run.source == "live" and np.isfinite(run.arrays["sensor_to_actuator"]).sum() == 50 - sim["packets_dropped"]
    assert np.nanmax(run.arrays["stage_encoder"]) > 0 and not run.arrays["deadline_miss"].any()
    # the Foxglove topics: one phase-plane update a sample, the run's events in the Log panel's topic
    assert msgs["/phase"] == 50 and msgs["/phase/roa"] == 1 and msgs["/log"] >= 4


def test_recorder_killed_the_run_goes_on_and_the_file_reads(run_id, tmp_path):
    path = tmp_path / "rk.mcap"
    rc, s, err = live(run_id, "paper", "--duration", "5", "--out", str(path), "--kill", "recorder@2.5")
    assert rc == 3  # the run was clean, its recording incomplete (testbed.live.recorder.RECORDING_INCOMPLETE)
    (f,) = [f for f in s["faults"] if f["node"] == "recorder"]
    assert f["kind"] == "killed" and f["injected"]
    assert s["complete"] and not s["recording"]["complete"]
    assert "recorder died" in err
    rec = reader.read(path)
    assert rec.truncated
    ks = sorted(rec.telemetry["plant"])
    assert ks == list(range(len(ks)))
    last_t = ks[-1] * 0.1
    assert last_t >= 2.5 - 1.0, f"recording ends at {last_t} s, recorder killed at 2.5 s"
    r = report(path)                      # the post-mortem still works on what is there
    assert r["recording"]["truncated"] and r["samples"] == len(ks)


def test_plant_killed_the_recording_is_complete_and_says_so(run_id, tmp_path):
    path = tmp_path / "pk.mcap"
    rc, s, err = live(run_id, "paper", "--duration", "5", "--out", str(path), "--kill", "plant@1.5")
    assert rc == 1
    rec = reader.read(path)
    assert not rec.truncated and "testbed.recorder" in rec.metadata
    ks = sorted(rec.telemetry["plant"])
    assert 13 <= len(ks) <= 19 and ks == list(range(len(ks)))  # killed at 1.5 s (sample 15)
    launcher_events = [e for e in rec.events if e.node == "launcher"]
    assert any(e.kind == "plant_killed" for e in launcher_events)
    r = report(path)
    assert any(f["node"] == "plant" and f["kind"] == "killed" for f in r["faults"])
    assert any(lv[1] == "plant" and not lv[3] for lv in rec.liveliness)  # its token went away


def test_launcher_sigkilled_the_recorder_still_finishes_the_file(run_id, tmp_path):
    path = tmp_path / "lk.mcap"
    p = subprocess.Popen(tb_cmd("run", "paper", "--json", "--run-id", run_id, "--duration", "30",
                                "--out", str(path)),
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        end = time.monotonic() + TIMEOUT
        while time.monotonic() < end and not (path.exists() and len(reader.read(path).telemetry["plant"]) >= 10):
            time.sleep(0.5)
        os.kill(p.pid, signal.SIGKILL)
        p.wait(10)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    end = time.monotonic() + 30
    while procs_with(run_id) and time.monotonic() < end:   # nodes and recorder die with the launcher
        time.sleep(0.2)
    assert procs_with(run_id) == [], cmdlines(procs_with(run_id))
    rec = reader.read(path)
    assert not rec.truncated, rec.read_error          # PDEATHSIG: the recorder closed the file properly
    assert len(rec.telemetry["plant"]) >= 10
    assert json.loads(rec.metadata["testbed.recorder"]["received"]) > 0
