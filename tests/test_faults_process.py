"""The quiet faults of a lab, with real processes: a frozen and resumed node (``--stall``), a full disk
under the recorder, an overloaded host."""

from __future__ import annotations

import json

import pytest
from helpers import live, run_cli, tb_cmd

pytestmark = pytest.mark.process


def test_stalled_plant_encoder_and_controller_ride_through_and_resimulate(run_id, tmp_path):
    """Each of plant, encoder and controller frozen for 1 s mid-run (SIGSTOP, then SIGCONT): the run ends
    on time, each stall is recorded with its interval, encoder and decoder agree, resimulate reproduces."""
    out = tmp_path / "stalled.mcap"
    stalls = {"plant": 1.5, "encoder": 3.5, "controller": 5.5}
    args = [a for r, t in stalls.items() for a in ("--stall", f"{r}@{t}:1")]
    rc, s, err = live(run_id, "paper", "--duration", "8", "--out", str(out), *args)
    assert rc == 0, err[-2000:]
    assert s["outcome"] == "done" and s["complete"] and s["samples"] == 80
    got = {f["node"]: f for f in s["faults"] if f["kind"] == "stalled"}
    assert set(got) == set(stalls), s["faults"]
    assert all(f["kind"] == "stalled" for f in s["faults"]), s["faults"]
    for role, t in stalls.items():
        f = got[role]
        assert f["injected"]
        # from its last sample before the freeze (at most one period earlier) to its first after it
        assert t - 0.25 <= f["from_s"] <= t + 0.05 and 0.9 <= f["duration_s"] <= 1.6, f
        assert f"node {role} stalled" in err
    assert s["timing_degraded"] is True and "stalled" in s["timing_degraded_why"]
    assert s["encoder_decoder_agree_where_known"]
    # the samples a frozen node missed are losses at both ends: the controller decided them at its deadline
    assert s["loss_reasons"]["deadline"] >= 3 * 8
    rc, o, e = run_cli(tb_cmd("resimulate", str(out), "--json"))
    r = json.loads(o)
    assert rc == 0 and r["verdict"].startswith("reproduced") and r["first_divergence"] is None, (o, e[-2000:])
    rc, o, e = run_cli(tb_cmd("report", str(out), "--json"))
    rep = json.loads(o)
    assert rc == 0 and {f["node"] for f in rep["faults"] if f["kind"] == "stalled"} == set(stalls), rep["faults"]
    assert rep["timing_degraded"] is True


def test_stall_bad_input_is_one_line_exit_2(run_id):
    for bad in ("plant@2", "plant@x:1", "nobody@1:1", "plant@1:0"):
        rc, o, e = run_cli(tb_cmd("run", "paper", "--duration", "1", "--no-record", "--run-id", run_id,
                                  "--stall", bad), timeout=60)
        assert rc == 2 and "--stall must be ROLE@SECONDS:DURATION" in e and "Traceback" not in e, (bad, e)
    rc, o, e = run_cli(tb_cmd("run", "paper", "--duration", "1", "--no-record", "--run-id", run_id,
                              "--colocate", "encoder", "--stall", "encoder@0.5:1"), timeout=60)
    assert rc == 2 and "stall that one" in e and "Traceback" not in e, e
