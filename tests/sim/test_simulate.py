"""Simulators: the paper's example, batch = per-sample loop, the CLI's JSON."""

import dataclasses
import json

import numpy as np
import pytest
from helpers.cli import tb_run

import plants
from testbed import cli, scenario
from testbed.loop.flow import FLOW_OK, phi_T
from testbed.sim.batch import in_nominal_roa, simulate_batch, simulate_scenario, summarize
from testbed.sim.loop import OnlineAttacker, simulate_loop


def _open_loop_limit_cycle(p):
    x = np.array([0.1, 0.0])
    for _ in range(3000):  # 30 s onto the cycle
        x, _ = phi_T(p, x, np.zeros(1), 0.01)
    pts = []
    for _ in range(1500):
        x, _ = phi_T(p, x, np.zeros(1), 0.01)
        pts.append(x)
    return np.array(pts)


def test_paper_converges():
    sc = scenario.load("paper")
    out = summarize(sc, simulate_scenario(sc))
    assert out["converged"] and not out["escaped"]
    assert out["final_norm"] < 1e-4
    assert out["packets_dropped"] > 0 and len(out["dos_intervals"]) == 2
    assert out["encoder_decoder_agree"]
    assert len(out["t"]) * sc.T <= 30.0 + 1e-9


def test_dos_intervals_are_the_realized_schedule():
    """``dos_intervals`` (made from the tally's arrays, no object per interval) = the realized schedule
    ``SimResult.intervals`` (a second implementation: ``Schedule.from_theta``), float for float."""
    sc = scenario.with_overrides(scenario.load("paper"), {"duration": 30.0, "attack": {
        "kind": "periodic", "period": 0.35, "length": 0.15, "offset": 0.05}})
    res = simulate_scenario(sc)
    out = summarize(sc, res)
    assert len(out["dos_intervals"]) > 50 and out["dos_intervals"] == res.intervals().to_list()
    assert all(type(v) is float for iv in out["dos_intervals"] for v in iv)


def test_paper_escape_leaves_the_region_and_ends_near_the_limit_cycle():
    sc = scenario.load("paper-escape")
    p = sc.make_plant()
    assert in_nominal_roa(p, sc.K, sc.T, sc.x0[None])[0], "x0 = [0.3 0.3] is inside the nominal region"
    res = simulate_scenario(sc)
    out = summarize(sc, res)
    assert not out["converged"] and out["escaped"]
    lc = _open_loop_limit_cycle(p)
    assert np.min(np.max(np.abs(lc - res.x_final), axis=1)) < 0.1
    # same story with the paper's (saturating) quantizer
    sc_ideal = dataclasses.replace(sc, quantizer=dataclasses.replace(sc.quantizer, mode="ideal"))
    assert summarize(sc_ideal, simulate_scenario(sc_ideal))["escaped"]


@pytest.mark.parametrize("name", ["paper", "paper-escape", "paper-greedy", "pendulum", "cartpole"])
def test_batch_equals_per_sample_loop_bit_for_bit(name):
    sc = scenario.load(name)
    p = sc.make_plant()
    res = simulate_scenario(sc)
    th = sc.theta()
    gp = sc.attack.greedy_params() if sc.attack.online else None
    b = simulate_batch(p, sc.K, sc.quantizer, sc.x0[None], sc.n_steps,
                       theta=None if th is None else th[None], greedy_params=gp, score=sc.attack.score,
                       u_max=sc.controller.u_max, record=True)
    assert np.array_equal(b.x[0], res.x)
    assert np.array_equal(b.E[0], res.E_enc)
    assert np.array_equal(b.theta[0], res.theta)
    assert np.array_equal(b.x_final[0], res.x_final)
    assert b.saturations[0] == res.saturations
    assert b.mismatch[0] == 0


def test_batch_many_states_and_schedules():
    sc = scenario.load("paper")
    p = sc.make_plant()
    rng = np.random.default_rng(0)
    X0 = rng.uniform(-0.1, 0.1, (40, 2))
    tab = np.zeros((3, sc.n_steps), np.uint8)
    tab[1, 10:20] = 1
    tab[2, 5:60] = 1
    idx = np.arange(40) % 3
    b = simulate_batch(p, sc.K, sc.quantizer, X0, sc.n_steps, theta=tab, sched_idx=idx)
    assert np.all(b.attacked == tab.sum(axis=1)[idx])
    assert np.all(b.mismatch == 0)
    for i in (0, 7, 23):
        r = simulate_loop(p, sc.K, sc.quantizer, X0[i], sc.n_steps, OnlineAttacker(theta=tab[idx[i]], T=sc.T))
        assert np.array_equal(r.x_final, b.x_final[i])
    # a 5.5 s attack (samples 5..59) loses the loop: the flow diverges; no attack, and a 1 s one, converge
    from testbed.loop.params import FLOW_DIVERGED

    assert b.converged()[idx != 2].all()
    assert not b.converged()[idx == 2].any() and (b.status[idx == 2] == FLOW_DIVERGED).all()


def test_divergence_is_reported_not_nan():
    p = plants.make("linear", A=[[3.0, 0.0], [0.0, 3.0]], B=[[1.0], [0.0]])
    sc = scenario.load("paper")
    qp = dataclasses.replace(sc.quantizer, L=3.0)
    b = simulate_batch(p, [[-0.1, 0.0]], qp, [[0.1, 0.1]], 2000)
    assert b.status[0] != FLOW_OK and b.stop_k[0] < 2000
    assert np.all(np.isfinite(b.x_final))


def test_nominal_roa_contains_origin_not_far_states():
    sc = scenario.load("paper")
    inside = in_nominal_roa(sc.make_plant(), sc.K, sc.T, np.array([[0.05, 0.0], [3.0, 3.0]]))
    assert inside.tolist() == [True, False]


def test_cli_simulate_json(capsys):
    assert cli.main(["simulate", "paper", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    for key in ("t", "x", "u", "E", "theta", "symbols", "saturations", "final_norm", "converged",
                "escaped", "K"):
        assert key in out
    n = len(out["t"])
    assert len(out["x"]) == n and len(out["E"]) == n and len(out["theta"]) == n
    assert out["converged"] is True and out["final_norm"] < 1e-4
    assert all(0 <= s < 37 for s in out["symbols"])


def test_cli_reports_bad_scenario(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[plant]\nname = 'lienard'\n")
    assert cli.main(["simulate", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("testbed simulate: ") and "[quantizer] section missing" in err
    assert len(err.strip().splitlines()) == 1


@pytest.mark.slow  # its own processes (an interpreter start-up each)
def test_console_script_runs():
    r = tb_run("simulate", "paper-escape", "--json", timeout=120)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["escaped"] is True and out["converged"] is False
