"""The strongest attacker (testbed.analysis.worst): schedules, counts, exactness, the paper's example.

The paper check runs ``testbed simulate`` on scenario files with the returned interval written into
``[attack] intervals``: it escapes, and the same interval one sample shorter at either end does not.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from attackers.schedule import Schedule
from testbed import scenario
from testbed.analysis.worst import (Loop, all_schedules, count_schedules, least_single, runs_to_intervals,
                                    theta_table, worst_attack)


@pytest.fixture(scope="module")
def paper_sc():
    return scenario.load("paper")


# ============================================================================ fast: schedules
def test_runs_are_the_intervals_a_scenario_reads():
    T, N = 0.1, 60
    runs = ((3, 1), (10, 13), (40, 9))
    iv = runs_to_intervals(runs, T)
    assert iv == [[0.3, 0.0], [1.0, 1.2], [4.0, 0.8]]
    np.testing.assert_array_equal(theta_table([runs], N)[0], Schedule.from_list(iv).theta_samples(T, N))
    np.testing.assert_allclose(Schedule.from_theta(theta_table([runs], N)[0], T).to_list(), iv, atol=1e-12)


@pytest.mark.parametrize("m,extra,N", [(1, 0, 9), (1, 3, 9), (2, 0, 9), (2, 2, 12), (3, 1, 14)])
def test_schedule_count_matches_enumeration(m, extra, N):
    sch = list(all_schedules(m, extra, N))
    assert len(sch) == count_schedules(m, extra, N)
    assert len(set(sch)) == len(sch)
    for runs in sch:
        assert len(runs) == m and sum(L - 1 for _, L in runs) == extra
        th = theta_table([runs], N)[0]
        # m separate runs (no two touching), inside the horizon
        assert len(Schedule.from_theta(th, 1.0)) == m and th.sum() == m + extra


def _short_loop(paper_sc, n_steps):
    return replace(Loop.from_scenario(paper_sc), n_steps=n_steps)


def test_two_attacks_exact_against_brute_force(paper_sc):
    """On a short horizon every schedule of <= 2 runs fits: the search's answer is the true minimum."""
    loop = _short_loop(paper_sc, 16)
    x0 = np.array([0.1, 0.1])
    w = worst_attack(loop, x0, attacks=2, greedy=False, exhaustive_limit=10 ** 6)
    assert w.exact
    cands = [((k, L),) for L in range(1, 17) for k in range(0, 17 - L)]
    cands += [c for e in range(0, 8) for c in all_schedules(2, e, 16)]
    from testbed.analysis.worst import evaluate

    esc, _ = evaluate(loop, np.repeat(x0[None], len(cands), 0), np.full(len(cands), w.E0), theta_table(cands, 16),
                      np.arange(len(cands)))
    best = min(sum(L - 1 for _, L in c) for c, e in zip(cands, esc) if e) if esc.any() else None
    assert w.escaped == (best is not None)
    if best is not None:
        assert sum(L - 1 for _, L in w.runs) == best
    one = least_single(loop, x0[None])
    # here two attacks need less duration than one (a delivered packet between them is cheap)
    assert one.L[0] > 0 and sum(L - 1 for _, L in w.runs) < one.L[0] - 1 and len(w.runs) == 2


# ============================================================================ slow: the paper
def _simulate(tmp_path: Path, base: str, intervals, name: str) -> dict:
    text = re.sub(r"^intervals = .*$", f"intervals = {json.dumps(intervals)}", base, flags=re.M)
    f = tmp_path / f"{name}.toml"
    f.write_text(text)
    p = subprocess.run([sys.executable, "-m", "testbed.cli", "simulate", str(f), "--json"], capture_output=True,
                       text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    return json.loads(p.stdout)


@pytest.mark.slow
def test_worst_attack_on_the_paper_is_minimal_in_testbed_simulate(tmp_path):
    p = subprocess.run([sys.executable, "-m", "testbed.cli", "worst-attack", "paper", "--json", "--no-progress",
                        "--workers", "1"], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    d = json.loads(p.stdout)
    for key in ("intervals", "total_duration", "escaped", "exact", "greedy"):
        assert key in d, key
    assert d["escaped"] and d["exact"] and len(d["intervals"]) == 1
    (a, tau), = d["intervals"]
    assert d["total_duration"] == pytest.approx(tau)
    # shorter than the paper's two attacks (2.0 s in all), which the loop survives
    assert tau < 2.0
    base = (Path(scenario.__file__).parent / "scenarios" / "paper.toml").read_text()
    assert _simulate(tmp_path, base, [[1.0, 1.2], [4.0, 0.8]], "paper")["escaped"] is False
    hit = _simulate(tmp_path, base, d["intervals"], "worst")
    assert hit["escaped"] is True
    np.testing.assert_allclose(hit["dos_intervals"], d["intervals"], atol=1e-9)
    T = d["T"]
    if tau > 0:  # one sample shorter at the start, and at the end
        shorter = [[[round(a + T, 12), round(tau - T, 12)]], [[a, round(tau - T, 12)]]]
    else:       # a single lost packet: shorter is no attack at all
        shorter = [[]]
    for i, iv in enumerate(shorter):
        r = _simulate(tmp_path, base, iv, f"shorter{i}")
        assert r["escaped"] is False, iv
    g = d["greedy"]
    assert g["escaped"] is False or g["total_duration"] >= d["total_duration"] - 1e-9


@pytest.mark.slow
def test_cli_vulnerability_json_and_plot(tmp_path, capsys):
    from testbed.cli import main

    png = tmp_path / "v.png"
    assert main(["vulnerability", "paper", "--grid", "9", "--json", "--no-progress", "--workers", "1",
                 "--plot", str(png)]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["grid"] == [9, 9] and d["states_in_region"] > 0 and d["all_exact"]
    assert 0 < d["delta"] < 1 and png.stat().st_size > 1000
    inside = np.array(d["samples"]) > -2
    dur = np.array([[np.nan if v is None else v for v in row] for row in d["duration"]])
    assert np.all(np.isnan(dur[~inside]))
