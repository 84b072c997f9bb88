"""The escape criterion (testbed.sim.batch.EscapeCriterion, judge_escape): the quantized loop continued
without attack, one function for the per-sample simulator, a recording and the batch paths."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
from helpers.cli import tb_run_here
from helpers.sims import paper_loop_toml

from testbed import scenario
from testbed.analysis.sweep import classify
from testbed.analysis.worst import Loop, evaluate, single_table
from testbed.sim.batch import (
    EscapeCriterion,
    in_nominal_roa,
    judge_escape,
    loop_state_from_samples,
    simulate_batch,
    simulate_scenario,
    summarize,
)

SHORT = 'name = "short"\n' + paper_loop_toml(x0=(-0.497, -0.316), E0=0.497, mode="resilient") + """
[attack]
kind = "intervals"
intervals = [[0.8, 1.1]]
[run]
duration = 2.0
"""


def test_an_attack_ending_at_the_horizon_escapes_although_x_N_is_in_the_nominal_region():
    """The issue's case: 12 samples lost up to the 2 s horizon; x_N lies inside the nominal region (the old
    rule: no escape) but E_N has grown by Lambda per lost sample and the continued loop does not recover."""
    sc = scenario.loads(SHORT)
    res = simulate_scenario(sc)
    out = summarize(sc, res)
    assert out["packets_dropped"] == 12
    assert in_nominal_roa(sc.make_model(), sc.K, sc.T, res.x_final[None, :])[0]
    assert out["E"][-1] > 40
    assert out["escaped"] is True and out["converged"] is False
    crit = out["escape_criterion"]
    assert set(crit) >= {"kind", "horizon_s", "x_tol", "E_tol"}
    assert crit["horizon_s"] > 0 and crit["x_tol"] == sc.run.converge_tol
    # through the command, as a user runs it
    p = tb_run_here("simulate", "paper", "--duration", "2", "--json")
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)["escape_criterion"] == crit


def test_the_paper_run_recovers():
    sc = scenario.load("paper")
    out = summarize(sc, simulate_scenario(sc))
    assert out["converged"] and not out["escaped"]


def _cases(sc, n=12, seed=3):
    """Initial states inside the nominal region and one attack each ending at the 2 s horizon."""
    rng = np.random.default_rng(seed)
    model = sc.make_model()
    X = rng.uniform(-0.6, 0.6, size=(4 * n, 2))
    X = X[in_nominal_roa(model, sc.K, sc.T, X)][:n]
    L = rng.integers(6, 15, size=len(X))
    return X, L


def test_per_sample_recording_and_batch_paths_agree_bit_for_bit():
    """The end state (x_N and both ends' xi_N, E_N, u_{N-1}) of the per-sample simulator, the one rebuilt
    from its record (what a recording has) and the batch kernel's are identical, and so are the verdicts of
    summarize, of the analysis' batch path (worst.evaluate -> sweep.classify) and of judge_escape."""
    base = scenario.loads(SHORT)
    N = base.n_steps
    X, L = _cases(base)
    loop = Loop.from_scenario(base)
    E0 = np.maximum(base.quantizer.E0, np.max(np.abs(X), axis=1))
    tab = single_table(N - L, L, N)
    esc_batch, _ = evaluate(loop, X, E0, tab, np.arange(len(X)))
    verdicts = []
    for i, (x0, ell) in enumerate(zip(X, L)):
        sc = scenario.loads(SHORT.replace("x0 = [-0.497, -0.316]", f"x0 = [{float(x0[0])!r}, {float(x0[1])!r}]")
                            .replace("E0 = 0.497", f"E0 = {float(E0[i])!r}")
                            .replace("[[0.8, 1.1]]", f"[[{(N - ell) * 0.1:.12g}, {(ell - 1) * 0.1:.12g}]]"))
        res = simulate_scenario(sc)
        assert int(res.theta.sum()) == ell and res.theta[-1] == 1
        b = simulate_batch(sc.make_plant(), sc.K, sc.quantizer, x0[None], N, theta=tab[i][None],
                           model=sc.make_model(), flow=sc.flow)
        np.testing.assert_array_equal(b.x_final[0], res.x_final)
        np.testing.assert_array_equal(b.state_final[0], res.loop_state)
        rebuilt = loop_state_from_samples(dataclasses.replace(res, loop_state=None), sc.make_model(), sc.quantizer,
                                          sc.flow)
        np.testing.assert_array_equal(rebuilt, res.loop_state)
        s = summarize(sc, res)
        assert s["escaped"] == bool(esc_batch[i]), (x0, ell)
        crit = EscapeCriterion.for_loop(sc.make_model(), sc.quantizer, sc.run.converge_tol)
        j = judge_escape(sc.make_plant(), sc.K, sc.quantizer, b.x_final, b.state_final, b.status, crit,
                         model=sc.make_model())
        assert bool(j[0]) == s["escaped"]
        verdicts.append(s["escaped"])
    # the cases are not all alike: the check is not vacuous
    assert 0 < sum(verdicts) < len(verdicts)


def test_classify_runs_the_continuation_on_an_executor_with_the_same_result():
    from testbed.analysis.parallel import Executor, run_batch

    sc = scenario.loads(SHORT)
    X, L = _cases(sc, n=8, seed=5)
    N = sc.n_steps
    tab = single_table(N - L, L, N)
    crit = EscapeCriterion.for_loop(sc.make_model(), sc.quantizer, sc.run.converge_tol)
    out = run_batch(sc.make_plant(), sc.K, sc.quantizer, X, N, E0=np.maximum(0.497, np.abs(X).max(1)), theta=tab,
                    sched_idx=np.arange(len(X)), fields=("x_final", "status", "state_final"), model=sc.make_model())
    c1, e1 = classify(sc.make_plant(), sc.K, sc.quantizer, out, crit, model=sc.make_model())
    ex = Executor(workers=2)
    try:
        c2, e2 = classify(sc.make_plant(), sc.K, sc.quantizer, out, crit, model=sc.make_model(), executor=ex)
    finally:
        ex.close()
    np.testing.assert_array_equal(e1, e2)
    np.testing.assert_array_equal(c1, c2)
    assert not np.any(c1 & e1)


def test_the_continuation_stops_on_recovery_and_outside_the_model_region():
    sc = scenario.load("paper")
    crit = EscapeCriterion.for_loop(sc.make_model(), sc.quantizer, sc.run.converge_tol)
    assert crit.x_out == sc.make_model().lipschitz_region
    # from x = 0 with E small both ends have recovered at once; from far outside the region: out at once
    from testbed.sim.batch import loop_state_width

    W = loop_state_width(2, 1)
    S = np.zeros((2, W))
    S[:, 2] = S[:, 6] = 1e-6
    r = simulate_batch(sc.make_plant(), sc.K, sc.quantizer, np.array([[0.0, 0.0], [5.0, 0.0]]), 50, init_state=S,
                       stop=(crit.x_tol, crit.E_tol, crit.x_out))
    assert list(r.stop_k) == [0, 0]
    np.testing.assert_array_equal(r.state_final, S)
    esc = judge_escape(sc.make_plant(), sc.K, sc.quantizer, np.array([[0.0, 0.0], [5.0, 0.0]]), S, [0, 0], crit)
    assert list(esc) == [False, True]


def test_sweep_and_vulnerable_states_name_their_escape_criterion():
    from testbed.analysis.roa import nominal_roa
    from testbed.analysis.sweep import sweep, vulnerable_states

    sc = scenario.load("paper")
    p = sc.make_plant()
    sw = sweep(p, sc.K, sc.quantizer, sc.x0, [0.0, 1.0], [0.0, 0.2], seeds=1, horizon=3.0, kinds=("greedy",))
    crit = EscapeCriterion.for_loop(p, sc.quantizer).to_dict()
    assert sw.to_dict()["escape_criterion"] == crit
    roa = nominal_roa(p, sc.K, sc.T, grid=7)
    vu = vulnerable_states(p, sc.K, sc.quantizer, (1.0, 0.5, 1.0, 0.3), roa, horizon=3.0)
    assert vu.to_dict()["escape_criterion"] == crit
