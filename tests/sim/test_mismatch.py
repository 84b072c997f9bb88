"""Model mismatch: a scenario's [model] (the predictions, the design, the analysis) apart from its [plant].

The per-sample loop, the batch kernel, the analysis and a live run all integrate
the true plant and predict with the model; with [model] equal to [plant] nothing
changes, bit for bit.  The bundled ``paper-mismatch`` (true b = 0.03, model
b = 0.02) is the case the docs explain: the resilient quantizer's OVERFLOW
recaptures the state the paper's saturating quantizer loses.
"""

from __future__ import annotations

import json
import os
import secrets

import numpy as np
import pytest

from testbed import cli, scenario
from testbed.sim.batch import simulate_batch, simulate_scenario, summarize

LOOP_ARRAYS = ("x", "u", "q", "q_enc", "xi_enc", "E_enc", "xi_dec", "E_dec", "theta", "symbols", "saturated",
               "x_final")


def _same_run(a, b) -> None:
    for k in LOOP_ARRAYS:
        assert np.array_equal(getattr(a, k), getattr(b, k), equal_nan=True), k


def _batch(sc, *, model=True, **kw):
    """The scenario's loop in the batch kernel: the true plant, predictions on the model (or on the plant)."""
    return simulate_batch(sc.make_plant(), sc.K, sc.quantizer, sc.x0[None], sc.n_steps, theta=sc.theta(),
                          model=sc.make_model() if model else None, record=True, flow=sc.flow, **kw)


@pytest.fixture(scope="module")
def mismatch():
    sc = scenario.load("paper-mismatch")
    return sc, simulate_scenario(sc)


def test_model_equal_to_plant_reproduces_the_run_without_model():
    """[model] = [plant] (written out, or with the plant's name only): the loop and the kernel, bit for bit."""
    base = scenario.load("paper")
    ref = simulate_scenario(base)
    ref_b = _batch(base, model=False)
    params = "params = { a = 0.3333333333333333, b = 0.02 }\n"
    for model in ('[model]\nname = "lienard"\n' + params, '[model]\nname = "lienard"\n'):
        sc = scenario.loads(base.source + "\n" + model, name="paper")
        assert sc.model.explicit and sc.make_model() == base.make_model()
        _same_run(simulate_scenario(sc), ref)
        b = _batch(sc)
        for k in ("x", "E", "theta", "x_final", "E_final", "saturations", "mismatch"):
            assert np.array_equal(getattr(b, k), getattr(ref_b, k)), k
    out = summarize(sc, ref)
    assert (out["plant"], out["model"]) == ("lienard", "lienard") and out["plant_params"] == out["model_params"]


def test_mismatched_run_keeps_lockstep_in_the_loop_and_the_kernel(mismatch):
    """paper-mismatch: encoder and decoder agree at every sample; loop and batch kernel agree bit for bit."""
    sc, res = mismatch
    assert sc.make_plant().b == 0.03 and sc.make_model().b == 0.02
    out = summarize(sc, res)
    assert out["encoder_decoder_agree"] is True and res.agree
    assert out["plant_params"]["b"] == 0.03 and out["model_params"]["b"] == 0.02
    b = _batch(sc)
    assert b.mismatch[0] == 0 and b.saturations[0] == res.saturations
    assert np.array_equal(b.x[0], res.x) and np.array_equal(b.theta[0], res.theta)
    assert np.array_equal(b.E[0], res.E_enc) and np.array_equal(b.x_final[0], res.x_final)
    # the analysis' batches (testbed.analysis.parallel.run_batch: the specialized kernel) are the same runs
    from testbed.analysis.parallel import run_batch

    rb = run_batch(sc.make_plant(), sc.K, sc.quantizer, sc.x0[None], sc.n_steps, theta=sc.theta(),
                   model=sc.make_model(), flow=sc.flow, fields=("x_final", "saturations", "mismatch"))
    assert np.array_equal(rb["x_final"][0], res.x_final) and rb["saturations"][0] == res.saturations
    assert rb["mismatch"][0] == 0
    # and without the model the kernel is another loop (no saturations): the model is really used
    assert _batch(sc, model=False).saturations[0] == 0


def test_paper_mismatch_overflow_recaptures_what_the_ideal_quantizer_loses(mismatch):
    """The outcome docs/own-plant.md explains (``testbed simulate paper-mismatch [--mode ideal]``)."""
    sc, res = mismatch
    out = summarize(sc, res)
    assert out["converged"] and out["saturated_at"] == [63, 69, 87, 92, 97, 102, 122, 137, 163]
    ideal = scenario.with_overrides(sc, {"mode": "ideal"})
    lost = summarize(ideal, simulate_scenario(ideal))
    assert lost["saturations"] == 237 and lost["saturated_at"][:3] == [63, 64, 65]
    assert lost["escaped"] and lost["final_norm"] > 3.0
    # the same true plant with a matching model: no saturation in either mode
    matched = scenario.loads(sc.source.replace("b = 0.02", "b = 0.03"), name="matched")
    for mode in ("resilient", "ideal"):
        m = _batch(matched, mode=mode)
        assert m.saturations[0] == 0 and m.converged()[0]


def test_analysis_runs_the_true_plant_with_the_models_predictions(mismatch):
    """The escape search's trajectory is the simulator's run; sweep and roa JSON name plant and model."""
    from testbed.analysis.summary import trajectory
    from testbed.analysis.worst import Loop

    sc, res = mismatch
    X = trajectory(sc, sc.x0)
    assert np.array_equal(X, np.vstack([res.x, res.x_final[None]]))
    loop = Loop.from_scenario(sc)
    assert loop.plant.b == 0.03 and loop.nominal.b == 0.02


def test_sweep_and_roa_json_name_plant_and_model(capsys):
    assert cli.main(["sweep", "paper-mismatch", "--grid", "2", "2", "--seeds", "1", "--horizon", "1",
                     "--kinds", "random", "--workers", "1", "--no-progress", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert (d["plant"], d["model"], d["plant_params"]["b"], d["model_params"]["b"]) == ("lienard", "lienard",
                                                                                       0.03, 0.02)
    assert cli.main(["roa", "paper-mismatch", "--grid", "5", "--horizon", "1", "--workers", "1", "--no-progress",
                     "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["plant_params"]["b"] == 0.03 and d["model_params"]["b"] == 0.02


# ====================================================================== live
@pytest.mark.process
def test_paper_mismatch_live_equals_its_simulation():
    """testbed run paper-mismatch (ideal timing) past the first OVERFLOW (sample 63): the simulator's run."""
    from helpers.live import BIT_EXACT_KEYS, live_exact, mismatch, simulate
    from helpers.procs import reap

    rid = f"t{os.getpid()}xmm{secrets.token_hex(3)}"
    try:
        rc, s, err = live_exact(rid, "paper-mismatch", "--duration", "6.5", "--no-record")
    finally:
        assert not reap(rid)  # and its rerun's (run id rid + "r")
    assert rc == 0, (s["faults"], err[-2000:])
    assert s["complete"] and s["samples"] == 65 and s["saturated_at"] == [63]
    sim = simulate("paper-mismatch", 6.5)
    for key in BIT_EXACT_KEYS:
        assert s[key] == sim[key], mismatch(s, sim, key)
    assert s["encoder_decoder_agree"] is True
    assert (s["plant_params"]["b"], s["model_params"]["b"]) == (0.03, 0.02)
