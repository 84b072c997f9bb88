"""``testbed resimulate --plant recorded`` (fast tier): the encoder, the attacker's decisions, the controller
and the method re-run on the states the plant reported, compared bit for bit (``loop_identical``), and the
plant compared step by step with the scenario's model (``plant_model_error``)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers.cli import tb_here
from helpers.sims import sim_recording

import testbed
from testbed.record import recording
from testbed.runs.report import report
from testbed.runs.resimulate import recorded_run, resimulation
from testbed.sim.batch import simulate_scenario

NEW_KEYS = ("plant", "loop_identical", "loop_first_divergence", "plant_model_error")


def test_a_healthy_run_re_runs_identically_on_its_recorded_plant(tmp_path):
    """The testbed's own plant is bit-exact: the loop is identical and every e_k is 0; ``auto`` picks the
    model for it (the plant was not external, the scenario declares no device), and says so."""
    _sc, _res, path = sim_recording(tmp_path, "paper")
    run = testbed.open(path)
    r = resimulation(run, plant="recorded")
    assert r["plant"] == "recorded" and r["loop_identical"] and r["loop_first_divergence"] is None, r["verdict"]
    assert r["reproduced"] and r["checked"] == run.N == 300 and r["loop_differs_in"] == []
    assert r["plant_model_error"]["max"] == 0.0 and r["plant_model_error"]["mean"] == 0.0
    assert r["verdict"].startswith("reproduced: the loop is identical on the recorded plant"), r["verdict"]
    auto = resimulation(run)
    assert auto["plant"] == "model" and "testbed's own" in auto["plant_why"] and auto["reproduced"]
    assert auto["verdict"] == "reproduced bit for bit" and auto["loop_identical"]
    assert auto["plant_model_error"]["max"] == 0.0
    rep = report(path)["resimulation"]
    assert all(k in rep for k in NEW_KEYS) and rep["plant"] == "model" and rep["reproduced"]
    # the API: Run.resimulate is the same dict (one computation behind the command, the report and the API)
    for plant in ("auto", "recorded"):
        api = run.resimulate(plant)
        assert api == resimulation(run, plant=plant), plant
    try:
        run.resimulate("hardware")
        raise AssertionError("an unknown plant was accepted")
    except testbed.BadInput as e:
        assert "auto, model, recorded" in str(e)


@pytest.mark.slow  # half a second or more on a warm cache
def test_a_plant_whose_physics_differ_from_the_model(tmp_path):
    """paper-mismatch: the true plant has b = 0.03, the model b = 0.02.  On the recorded plant the loop is
    identical (it did what the method says with the plant's numbers) and e_k shows the plant is not the model."""
    _sc, _res, path = sim_recording(tmp_path, "paper-mismatch")
    rc, out, err = tb_here("resimulate", path, "--plant", "recorded", "--json")
    assert rc == 0, err
    r = json.loads(out)
    assert r["plant"] == "recorded" and r["loop_identical"] is True and r["loop_first_divergence"] is None, r
    pm = r["plant_model_error"]
    assert pm["max"] > 1e-6 and 0 <= pm["at"] < 300 and 0 < pm["mean"] < pm["max"], pm
    rc, out, err = tb_here("resimulate", path, "--plant", "recorded")
    assert rc == 0 and "re-run on the recorded plant (--plant recorded)" in out, (out, err)
    assert "reproduced: the loop is identical on the recorded plant" in out and "plant vs model" in out, out


def _tampered(tmp_path, what: str, k: int):
    """The paper's run recorded with one value the loop computed changed at sample k."""
    from testbed import scenario

    sc = scenario.load("paper")
    res = simulate_scenario(sc)
    if what == "u":  # the controller sent (and the plant applied) a u_k the law does not give
        res.u = res.u.copy()
        res.u[k] += 0.05
    else:  # the encoder sent another symbol than Algorithm 1's
        res.symbols = res.symbols.copy()
        res.symbols[k] = (res.symbols[k] + 1) % 36
    path = tmp_path / f"tampered-{what}.mcap"
    recording.record_simulation(path, sc, res)
    return path


@pytest.mark.slow  # half a second or more on a warm cache
def test_a_controller_that_breaks_the_law_diverges_at_its_sample(tmp_path):
    path = _tampered(tmp_path, "u", 40)
    r = resimulation(testbed.open(path), plant="recorded")
    assert r["loop_identical"] is False and r["loop_first_divergence"] == 40 and "u" in r["loop_differs_in"], r
    assert not r["reproduced"] and "differs from sample 40 (u)" in r["verdict"], r["verdict"]
    rc, out, err = tb_here("resimulate", path, "--plant", "recorded", "--json")
    assert rc == 1 and json.loads(out)["loop_first_divergence"] == 40, err
    path = _tampered(tmp_path, "symbol", 77)
    r = resimulation(testbed.open(path), plant="recorded")
    assert r["loop_first_divergence"] == 77 and r["loop_differs_in"] == ["symbols"], r
    assert not r["symbols_identical"] and r["symbols_differ_at"] == [77]


def test_the_replay_reads_what_each_node_recorded(tmp_path):
    """``recorded_run`` holds the controller's u_k and the plant's applied u_k apart (the one the law gives,
    the one that acted), and takes the choice for ``auto`` from the recording."""
    _sc, res, path = sim_recording(tmp_path, "paper")
    rr = recorded_run(testbed.open(path))
    assert np.array_equal(rr["live"]["u"], res.u) and np.array_equal(rr["live"]["u_acted"], res.u)
    assert rr["external_plant"] is False and rr["live"]["x_meas"] is None


@pytest.mark.slow  # half a second or more on a warm cache
def test_a_device_scenario_is_re_run_on_its_recorded_plant_by_default(tmp_path):
    """A scenario that declares its plant a device ([plant.sensor]): ``auto`` re-runs the loop on the recorded
    plant, with the encoder fed the recorded x_meas; noise-free physics: e_k = 0."""
    from testbed import scenario

    text = (scenario.load("paper").source.replace("duration = 30.0", "duration = 5.0")
            + '\n[plant.sensor]\ndistribution = "normal"\nscale = 1e-6\nseed = 9\n')
    f = tmp_path / "noisy.toml"
    f.write_text(text)
    sc = scenario.load(str(f))
    rec = tmp_path / "noisy.mcap"
    recording.record_simulation(rec, sc, simulate_scenario(sc))
    r = resimulation(testbed.open(rec))
    assert r["plant"] == "recorded" and "device" in r["plant_why"] and r["loop_identical"], r
    assert r["reproduced"] and r["plant_model_error"]["max"] == 0.0


def test_physical_timing_steps_the_model_with_the_held_input(tmp_path):
    """Under physical timing u_k-1 acts for the recorded delta_k, then u_k: the model's step from each reported
    state, so taken, is the plant's own bit for bit (e_k = 0) and the loop is identical."""
    _sc, _res, path = sim_recording(tmp_path, "paper", timing="physical", duration=10.0)
    r = resimulation(testbed.open(path), plant="recorded")
    assert r["timing_mode"] == "physical" and r["replayed"]["delays_ns"]["max"] > 0, r
    assert r["loop_identical"] and r["reproduced"] and r["plant_model_error"]["max"] == 0.0, r
