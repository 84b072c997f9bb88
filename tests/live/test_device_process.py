"""Process tier: a plant that is a device, live.  A noisy-sensor run of the paper's example equals the
simulator bit for bit (the same seeded draws per sample in the live plant node and the per-sample
loop), records the true and the measured state, and re-simulates exactly."""

from __future__ import annotations

import json
import os
import secrets

import numpy as np
import pytest
from helpers.cli import run_cli, tb_cmd
from helpers.live import BIT_EXACT_KEYS, TOPOLOGIES, live_exact, mismatch, simulate
from helpers.procs import reap

from testbed import scenario
from testbed.record.columns import read_columns
from testbed.sim.trajectory import simulate_scenario

pytestmark = pytest.mark.process

NOISY = scenario.load("paper").source.replace("E0 = 0.1\n", "E0 = 0.12\nE_min = 3e-5\n") + """
[plant.sensor]
distribution = "uniform"
scale = 1e-5
seed = 4
resolution = 1e-6

[plant.actuator]
saturation = 1.0
rate = 8.0

[plant.disturbance]
constant = [1e-7, 0.0]
scale = 1e-7
seed = 5
"""


@pytest.mark.parametrize("topology", TOPOLOGIES)
def test_noisy_sensor_paper_live_equals_simulator_and_resimulates(tmp_path, topology):
    f = tmp_path / "paper-noisy.toml"
    f.write_text(NOISY)
    rid = f"t{os.getpid()}xnoisy{secrets.token_hex(3)}"
    try:
        rc, s, err = live_exact(rid, str(f), "--duration", "5", *topology)
    finally:
        assert not reap(rid)
    assert rc == 0, (s["faults"], err[-2000:])
    assert s["complete"] and s["samples"] == 50
    sim = simulate(str(f), 5)
    assert sim["simulator"] == "per-sample"
    for key in (*BIT_EXACT_KEYS, "x_meas"):
        assert s[key] == sim[key], mismatch(s, sim, key)
    assert s["x_meas"] != s["x"]
    # the recording: the true and the measured state, and the input that acted (after the actuator)
    res = simulate_scenario(scenario.loads(NOISY), n_steps=50)
    cols = read_columns(s["recording"]["path"])
    assert np.array_equal(cols.get("plant", "x")[:50], res.x)
    assert np.array_equal(cols.get("plant", "x_meas")[:50], res.x_meas)
    assert np.array_equal(cols.get("plant", "u")[:50], res.u_plant)
    assert not np.array_equal(res.u_plant, res.u)  # the actuator's limits acted
    # the scenario declares the plant a device: auto re-runs the loop on the recorded plant; the model, whose
    # sensor and disturbance draw the same seeded numbers, re-runs the whole loop bit for bit
    rc, out, err = run_cli(tb_cmd("resimulate", s["recording"]["path"], "--json"))
    r = json.loads(out)
    assert rc == 0 and r["plant"] == "recorded" and r["reproduced"] and r["loop_identical"], r
    assert r["plant_model_error"]["max"] > 0, r  # the disturbance is not in the model's flow map
    rc, out, err = run_cli(tb_cmd("resimulate", s["recording"]["path"], "--plant", "model", "--json"))
    r = json.loads(out)
    assert rc == 0 and r["plant"] == "model", r
    assert r["reproduced"] and r["max_state_error"] == 0 and r["symbols_identical"] and r["E_identical"], r
