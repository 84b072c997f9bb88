"""Analysis tests that run the batch simulator: region of attraction, sweep, vulnerable states, CLI.

Small grids and short horizons; the first test in a session pays the numba
compilation of the simulator kernel.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

import plants
from testbed.analysis.roa import nominal_roa
from testbed.analysis.sweep import KINDS, sweep, vulnerable_states
from testbed.loop.control import c2d, dlqr


def test_roa_of_a_stable_linear_loop_is_everything():
    lin = plants.make("linear", A=[[0.0, 1.0], [2.0, -1.0]], B=[[0.0], [1.0]])
    Ad, Bd = c2d(lin.A, lin.B, 0.1)
    K = dlqr(Ad, Bd, np.eye(2), np.eye(1))
    roa = nominal_roa(lin, K, 0.1, grid=9, window=(2.0, 2.0), horizon=30.0)
    assert roa.inside.shape == (9, 9)
    assert roa.inside.all()
    assert roa.fraction == 1.0 and roa.area == pytest.approx(16.0)
    assert roa.traj_steps == 81 * 300


def test_roa_of_the_paper_loop(paper):
    p = paper.make_plant()
    roa = nominal_roa(p, paper.K, paper.T, grid=41, horizon=30.0)
    assert roa.contains(np.zeros(2))
    # the paper: both initial states of its Figs. 2 and 3 lie in the nominal region ...
    assert roa.contains(np.array([0.1, 0.1])) and roa.contains(np.array([0.3, 0.3]))
    # ... which is bounded across the x1 axis (a band along x2 = -3 x1)
    assert not roa.contains(np.array([3.0, 0.0])) and not roa.contains(np.array([-3.0, 0.0]))
    assert 0.02 < roa.fraction < 0.2
    # agrees with the core's membership test on the grid states
    from testbed.sim.batch import in_nominal_roa

    GX, GY = np.meshgrid(roa.xs[::8], roa.ys[::8], indexing="xy")
    X = np.stack([GX.ravel(), GY.ravel()], axis=1)
    np.testing.assert_array_equal(in_nominal_roa(p, paper.K, paper.T, X, horizon=30.0),
                                  roa.inside[::8, ::8].ravel())


def test_sweep_small(paper):
    p = paper.make_plant()
    rF = np.array([0.0, 1.0])
    rD = np.array([0.0, 0.3])
    kF, kD, H = 1.0, 0.2, 20.0
    sw = sweep(p, paper.K, paper.quantizer, paper.x0, rF, rD, kappa_F=kF, kappa_D=kD, seeds=2, horizon=H)
    assert sw.kinds == KINDS
    for k in KINDS:
        assert sw.converged[k].shape == (2, 2)
        fin = np.isfinite(sw.converged[k])
        assert np.all((sw.converged[k][fin] >= 0) & (sw.converged[k][fin] <= 1))
    assert np.all(np.isnan(sw.converged["periodic"][0]))        # no periodic attack with rho_F = 0
    assert np.all(np.isfinite(sw.converged["periodic"][1]))
    assert sw.runs == 2 * 2 * 2 + 2 + 2 * 2                      # random + periodic + greedy
    assert sw.traj_steps == sw.runs * int(round(H / paper.T))
    # the greedy attacker never loses more samples than the budget allows:
    # chi(t) <= (kappa_D* + rho_D* t) / T + 1 over the horizon
    T = paper.T
    for i, f in enumerate(rF):
        for j, d in enumerate(rD):
            N = H / T
            bound = ((kD + kF * T) + (d + f * T) * H) / T + 1
            assert sw.lost["greedy"][i, j] * N <= bound + 1e-9
    # with no rates and a small initial energy every attacker is survivable from x0
    assert sw.worst()[0, 0] == 1.0
    d = sw.to_dict()
    json.dumps(d, allow_nan=False)
    assert len(sw.empirical_boundary()) == 2


@pytest.mark.slow  # half a second or more on a warm cache
def test_vulnerable_states(paper):
    p = paper.make_plant()
    roa = nominal_roa(p, paper.K, paper.T, grid=21, window=(1.0, 1.5), horizon=30.0)
    none = vulnerable_states(p, paper.K, paper.quantizer, (0.0, 0.0, 0.0, 0.0), roa, horizon=20.0)
    hard = vulnerable_states(p, paper.K, paper.quantizer, (1.0, 0.5, 1.0, 0.3), roa, horizon=20.0)
    assert np.array_equal(none.outcome >= 0, roa.inside)
    assert none.fraction_vulnerable <= hard.fraction_vulnerable
    assert hard.fraction_vulnerable > 0.5
    assert none.to_dict()["states_in_region"] == int(roa.inside.sum())


@pytest.mark.slow  # half a second or more on a warm cache
def test_cli_analyze_json(capsys):
    from testbed.cli import main

    assert main(["analyze", "paper", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    for key in ("K", "Lambda", "phi0", "phi1", "mu0", "mu1", "nu0", "nu1", "rho_D_max", "rho_F_max",
                "theorem1_holds", "delta", "E0_bound"):
        assert key in d, key
    assert d["Lambda"] == pytest.approx(math.e)
    assert d["rho_D_max"] == pytest.approx(0.0474, abs=5e-4)
    assert d["theorem1"]["tight"]["rho_F_max"] >= d["rho_F_max"] >= d["theorem1"]["plain"]["rho_F_max"]
    assert d["theorem1_holds"] is True and d["theorem2_holds"] is True
    assert 0 < d["E0_bound"] < d["delta"] < 1
    assert 1e-13 < d["gamma_for_paper_delta"] < 1e-12


@pytest.mark.slow  # half a second or more on a warm cache
def test_cli_roa_and_sweep_json(capsys):
    from testbed.cli import main

    assert main(["roa", "paper", "--grid", "11", "--json", "--no-progress"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["roa"]["grid"] == [11, 11] and 0 < d["roa"]["fraction_inside"] < 1
    assert main(["sweep", "paper", "--grid", "2", "2", "--seeds", "1", "--horizon", "10", "--json",
                 "--no-progress"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["rho_F"] == [0.0, 2.0] and d["rho_D"] == [0.0, 0.5]
    assert d["theory"]["rho_D_max"] == pytest.approx(0.0474, abs=5e-4)
    assert set(d["converged"]) == set(KINDS)


@pytest.mark.slow
def test_cli_analyze_plots(tmp_path, capsys):
    from testbed.cli import main

    assert main(["analyze", "paper", "--plot", str(tmp_path), "--escape-x0", "0.3", "0.3"]) == 0
    out = capsys.readouterr().out
    for name in ("time-series", "phase-portrait", "allowable-region", "delta"):
        f = tmp_path / f"paper-{name}.png"
        assert f.is_file() and f.stat().st_size > 10_000, name
        assert str(f) in out
    assert main(["roa", "paper", "--grid", "21", "--plot", str(tmp_path / "roa.png"), "--vulnerable",
                 "--no-progress"]) == 0
    assert (tmp_path / "roa.png").is_file()
    assert main(["sweep", "paper", "--grid", "3", "3", "--seeds", "1", "--horizon", "10", "--plot",
                 str(tmp_path / "sweep.png"), "--no-progress"]) == 0
    assert (tmp_path / "sweep.png").is_file()
