"""The method interface, the bundled methods, [method] in scenarios, batch kernel = per-sample simulator."""

from __future__ import annotations

import ast
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers.cli import tb_run

import testbed
from testbed import methods, scenario
from testbed.loop.params import ROUNDOFF
from testbed.sim.batch import OnlineAttacker, simulate_batch, simulate_loop

BUNDLED = ["paper", "zoom", "static", "unquantized", "unquantized-hold"]


def _paper(method: str, **over):
    sc = scenario.load("paper")
    return scenario.with_overrides(sc, {"method": method, **over})


def _loop(sc, theta=None, method=None):
    N = sc.n_steps
    th = sc.theta(N) if theta is None else theta
    return simulate_loop(sc.make_plant(), sc.K, sc.quantizer, sc.x0, N, OnlineAttacker(theta=th, T=sc.T), sc.flow,
                         model=sc.make_model(), method=method or sc.make_method(), u_max=sc.controller.u_max)


@pytest.mark.parametrize("name", BUNDLED)
@pytest.mark.parametrize("specialize", [False, True])
def test_batch_kernel_equals_per_sample(name, specialize):
    """Every bundled method: the batch kernel equals the per-sample simulator bit for bit (x_k, E_k,
    theta_k, saturations, the final loop state), under the paper's attack and a random one."""
    sc = _paper(name, duration=6.0)
    N = sc.n_steps
    rng = np.random.default_rng(3)
    thetas = [sc.theta(N), (rng.random(N) < 0.3).astype(np.uint8)]
    X0 = np.array([sc.x0, [-0.05, 0.08]])
    m = sc.make_method()
    for th in thetas:
        b = simulate_batch(sc.make_plant(), sc.K, sc.quantizer, X0, N, theta=th[None], sched_idx=[0, 0],
                           record=True, method=m, specialize=specialize, u_max=sc.controller.u_max)
        for j, x0 in enumerate(X0):
            r = simulate_loop(sc.make_plant(), sc.K, sc.quantizer, x0, N, OnlineAttacker(theta=th, T=sc.T), sc.flow,
                              model=sc.make_model(), method=m, u_max=sc.controller.u_max)
            assert r.agree
            assert np.array_equal(b.x[j], r.x), name
            assert np.array_equal(b.x_final[j], r.x_final)
            assert np.array_equal(b.theta[j], r.theta)
            assert np.array_equal(b.E[j], r.E_enc), name
            assert b.saturations[j] == r.saturations
            assert np.array_equal(b.state_final[j], r.loop_state), name


def test_paper_method_is_the_paper():
    """[method] absent = "paper": the same numbers as simulate_loop's default ends (the paper's)."""
    sc = scenario.load("paper")
    assert sc.method.name == "paper"
    a = _loop(sc, method=None)
    b = simulate_loop(sc.make_plant(), sc.K, sc.quantizer, sc.x0, sc.n_steps,
                      OnlineAttacker(theta=sc.theta(sc.n_steps), T=sc.T), sc.flow, model=sc.make_model())
    assert np.array_equal(a.x, b.x) and np.array_equal(a.E_enc, b.E_enc) and np.array_equal(a.symbols, b.symbols)


def test_registry_and_bits():
    sc = scenario.load("paper")
    for n in BUNDLED:
        assert methods.resolve(n).name == n
    assert methods.make("paper").bits(2, sc.quantizer) == 6      # 6^2 + 1 = 37 codes
    assert methods.make("static").bits(2, sc.quantizer) == 6     # 36 codes
    assert methods.make("unquantized").bits(2, sc.quantizer) == 128
    with pytest.raises(methods.MethodError, match="unknown method 'nope'"):
        methods.resolve("nope")
    with pytest.raises(methods.MethodError, match="no parameter 'width'"):
        methods.make("static", params={"width": 1})
    with pytest.raises(methods.MethodError, match="no module"):
        methods.resolve("no_such_mod_xyz:M")


def test_a_registered_method_resolves_by_its_name(monkeypatch):
    """``methods.register`` keys the registry by the class's ``name`` (it once keyed it by the class: the
    name did not resolve and ``names()`` held a class)."""
    from testbed.methods import registry

    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))

    class Mine(registry.BUNDLED["paper"]):
        name = "mine-registered"

    assert methods.register(Mine) is Mine
    assert methods.resolve("mine-registered") is Mine
    assert methods.names()[-1] == "mine-registered"


def test_unused_key_is_an_error_for_the_own_method_and_a_note_when_swapped():
    text = scenario.load("paper").source
    with pytest.raises(scenario.ScenarioError, match=r"\[quantizer.L\] is not used by the method 'static'"):
        scenario.loads(text + '\n[method]\nname = "static"\n')
    sc = _paper("unquantized")
    assert sc.method.name == "unquantized"
    assert "ignores [quantizer] M, L, E0, mode" in sc.method_note


def test_unquantized_scenario_without_M():
    text = """
[plant]
name = "pendulum"
x0 = [0.1, 0.1]
[quantizer]
T = 0.1
[controller]
lqr = { Q = [[1, 0], [0, 1]], R = [[1]] }
[run]
duration = 5
[method]
name = "unquantized-hold"
"""
    sc = scenario.loads(text)
    r = _loop(sc)
    assert r.final_norm < 1e-3
    with pytest.raises(Exception, match="M"):
        scenario.with_overrides(sc, {"method": "paper"})


def test_zoom_saturates_under_the_papers_attack_paper_does_not():
    z = _loop(_paper("zoom"))
    p = _loop(_paper("paper"))
    assert p.saturations == 0 and z.saturations > 0
    assert np.array_equal(z.theta, p.theta)


@pytest.mark.slow  # seconds of numerics: testbed worst-attack end to end
def test_worst_attack_with_a_method_agrees_with_the_per_sample_simulator(tmp_path):
    """worst-attack --method (batch kernel, escape by the method's own loop) against testbed.simulate
    (per-sample simulator): the schedule it returns escapes, the same one shortened by one sample does not."""
    import json

    import testbed

    r = tb_run("worst-attack", "paper", "--method", "unquantized", "--json", "--no-progress", cwd=tmp_path,
               timeout=900)
    assert r.returncode == 0, r.stderr
    w = json.loads(r.stdout)
    assert w["method"] == "unquantized" and w["escaped"]
    (a, tau), = w["intervals"]
    run = testbed.simulate("paper", method="unquantized", attack={"kind": "intervals", "intervals": [[a, tau]]})
    assert run.summary["escaped"] and run.summary["samples_lost"] == w["samples_lost"] and run.summary["method"] == "unquantized"
    short = testbed.simulate("paper", method="unquantized",
                             attack={"kind": "intervals", "intervals": [[a, max(tau - 0.1, 0.0)]]})
    assert not short.summary["escaped"]


@pytest.mark.parametrize("name", BUNDLED)
def test_contract_every_bundled_method(name):
    """Contract over the registry: the ends are deterministic (two runs, the same numbers), stay in
    lockstep under random losses, every symbol sent fits the declared bits, and the method declares
    where it runs, its description and its source."""
    sc = _paper(name, duration=4.0)
    m = sc.make_method()
    assert m.description and m.source and m.kernel_code(sc.quantizer) is not None
    th = (np.random.default_rng(11).random(sc.n_steps) < 0.4).astype(np.uint8)
    a, b = _loop(sc, th), _loop(sc, th)
    assert np.array_equal(a.x, b.x) and np.array_equal(a.u, b.u)
    assert a.agree and not a.lockstep_breaks
    cb = m.codebook(2, sc.quantizer)
    enc = m.make_encoder(sc.make_model(), sc.K, sc.quantizer, sc.flow)
    for x in np.random.default_rng(2).normal(scale=0.3, size=(20, 2)):
        s, _sat = enc.encode(x)
        assert len(cb.pack(s)) * 8 >= cb.bits >= 1
        assert cb.unpack(cb.pack(s)) == s
        enc.ack(0)


# ------------------------------------------------------------------ a method written from docs/methods.md alone
EXAMPLES = Path(__file__).resolve().parents[2] / "docs" / "examples"
#: what docs/methods.md lets a method import: the documented base classes (and numpy, math)
DOCUMENTED = {"Method", "EncoderEnd", "DecoderEnd", "IntCodebook", "FloatCodebook", "MethodError"}


def _predictive(tmp_path, params: str = "") -> Path:
    """The paper's scenario with docs/examples/mymethod.py's PredictiveZoom as its method (``[quantizer]
    mode`` left out: a key the method does not use)."""
    shutil.copy(EXAMPLES / "mymethod.py", tmp_path / "mymethod.py")
    text = scenario.load("paper").source.replace('mode = "resilient"\n', "")
    path = tmp_path / "predictive.toml"
    path.write_text(text + f'\n[method]\nname = "mymethod:PredictiveZoom"\n{params}')
    return path


def test_the_docs_example_imports_only_the_documented_interface():
    tree = ast.parse((EXAMPLES / "mymethod.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            assert {a.name for a in node.names} <= {"math", "numpy"}, ast.dump(node)
        elif isinstance(node, ast.ImportFrom):
            assert node.module == "testbed.methods", node.module
            assert {a.name for a in node.names} <= DOCUMENTED, ast.dump(node)


def test_a_method_written_from_the_docs_equals_the_paper(tmp_path):
    """docs/examples/mymethod.py's PredictiveZoom, written against the documented end API alone (phi_T,
    feedback, floor_E, K, qp, u_prev), configured like the paper (hold = false), equals ``paper`` bit for bit
    over the paper's scenario: symbols, theta, q, u, xi and E at both ends, x, the run's summary."""
    paper = testbed.simulate("paper")
    mine = testbed.simulate(_predictive(tmp_path))
    assert mine.summary["method"] == "mymethod:PredictiveZoom" and mine.summary["simulator"] == "per-sample"
    assert set(mine.arrays) == set(paper.arrays)
    for k, a in paper.arrays.items():
        assert np.array_equal(a, mine.arrays[k], equal_nan=a.dtype.kind == "f"), k
    assert np.count_nonzero(paper.arrays["theta"]) == 22 and not paper.arrays["saturated"].any()
    E, xi = mine.arrays["E_dec"], mine.arrays["xi_dec"]
    assert np.any(E == ROUNDOFF * np.max(np.abs(xi), axis=1))   # the floor of rule (E) was reached
    same = {k for k in paper.summary if paper.summary[k] == mine.summary.get(k)}
    assert set(paper.summary) - same == {"method", "simulator"}
    # the per-sample simulator on both (the paper's ends against the user's): the ends' final state too
    sp, su = scenario.load("paper"), scenario.load(_predictive(tmp_path))
    a, b = _loop(sp), _loop(su)
    assert np.array_equal(a.loop_state, b.loop_state) and np.array_equal(a.E_enc, b.E_enc) and b.agree


def test_the_docs_example_holding_the_input_through_a_loss(tmp_path):
    """hold = true (docs/examples/predictive.toml): u_k = u_{k-1} through every loss, in lockstep, and it
    is no longer the paper's loop."""
    r = _loop(scenario.load(_predictive(tmp_path, "params = { hold = true }\n")))
    lost = np.flatnonzero(r.theta == 1)
    assert len(lost) == 22 and r.agree and not r.lockstep_breaks
    assert all(np.array_equal(r.u[k], r.u[k - 1]) for k in lost)
    assert np.any(r.u[lost] != 0.0) and r.final_norm < 1e-4
    assert dict(scenario.load(EXAMPLES / "predictive.toml").method.params) == {"hold": True}
