"""The strongest attacker (testbed.analysis.worst): schedules, counts, exactness, the paper's example.

The paper check runs ``testbed simulate`` on scenario files with the returned interval written into
``[attack] intervals``: it escapes, and the same interval one sample shorter at either end does not.
"""

from __future__ import annotations

import functools
import itertools
import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from helpers.cli import tb_run

from attackers import budget
from attackers.schedule import Schedule
from testbed import scenario
from testbed.analysis.worst import (
    Loop,
    all_schedules,
    count_schedules,
    evaluate,
    least_duration_samples,
    realize,
    runs_to_intervals,
    theta_table,
    worst_attack,
)


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


def test_back_to_back_attacks_lose_the_same_samples_for_less_duration():
    """The issue's example: one attack [0.3, +0.5] and two back to back, [0.3, +0.2] and [0.6, +0.2], lose
    samples 3..8; attackers.budget.check prices them 1 attack of 0.5 s and 2 attacks of 0.4 s."""
    T, N = 0.1, 20
    one = Schedule.from_list([[0.3, 0.5]])
    two = Schedule.from_list([[0.3, 0.2], [0.6, 0.2]])
    np.testing.assert_array_equal(one.theta_samples(T, N), two.theta_samples(T, N))
    assert list(np.flatnonzero(one.theta_samples(T, N))) == [3, 4, 5, 6, 7, 8]
    r1, r2 = budget.check(one, 0.0, 0.0), budget.check(two, 0.0, 0.0)
    assert (r1.n_attacks, r2.n_attacks) == (1, 2)
    assert r1.total_duration == pytest.approx(0.5) and r2.total_duration == pytest.approx(0.4)
    # what the search writes for 6 lost samples in one run with at most 2 attacks
    assert runs_to_intervals(realize(((3, 6),), 2), T) == [[0.3, 0.2], [0.6, 0.2]]
    assert least_duration_samples(6, 2) == 4


def _min_duration_brute(runs, attacks, N):
    """Least total length (in samples) of at most ``attacks`` sample-aligned intervals [a, a + l] whose
    union of sampling instants is exactly the runs' samples (None: impossible); by enumeration."""
    want = 0
    for k0, L in runs:
        want |= ((1 << L) - 1) << k0
    ivs = [(a, l) for a in range(N) for l in range(N - a) if (((1 << (l + 1)) - 1) << a) & ~want == 0]
    best = None
    for n in range(1, min(attacks, len(ivs)) + 1):  # the same interval twice never helps
        for combo in itertools.combinations(ivs, n):
            m = 0
            for a, l in combo:
                m |= ((1 << (l + 1)) - 1) << a
            if m == want:
                d = sum(l for _, l in combo)
                best = d if best is None else min(best, d)
    return best


@pytest.mark.parametrize("runs,attacks", [(((3, 6),), 1), (((3, 6),), 2), (((0, 6),), 3), (((0, 6),), 6),
                                          (((0, 6),), 8), (((1, 2), (5, 4)), 2), (((1, 2), (5, 4)), 3),
                                          (((0, 1), (2, 3), (7, 4)), 4), (((0, 1), (2, 3), (7, 4)), 9)])
def test_realize_attains_the_least_duration(runs, attacks):
    T, N = 0.1, 12
    S = sum(L for _, L in runs)
    iv = runs_to_intervals(realize(runs, attacks), T)
    sch = Schedule.from_list(iv)
    np.testing.assert_array_equal(sch.theta_samples(T, N), theta_table([runs], N)[0])
    rep = budget.check(sch, 0.0, 0.0)
    assert rep.n_attacks == min(attacks, S) <= attacks
    assert rep.total_duration == pytest.approx(least_duration_samples(S, attacks) * T, abs=1e-9)
    assert _min_duration_brute(runs, attacks, N) == least_duration_samples(S, attacks) == S - min(attacks, S)


def test_more_runs_than_attacks_cannot_be_realized():
    with pytest.raises(ValueError):
        realize(((0, 1), (3, 1)), 1)


# ---------------------------------------------------------------------------- brute force
def _interval_masks(N, n_max):
    """{mask: [least total length with at most n intervals, n = 1..n_max]} over every tuple of at most
    n_max sample-aligned intervals [a, a + l] (overlapping, touching, back to back: all of them)."""
    ivs = [(a, l) for a in range(N) for l in range(N - a)]
    bits = np.array([((1 << (l + 1)) - 1) << a for a, l in ivs], dtype=np.int64)
    lens = np.array([l for _, l in ivs], dtype=np.int64)
    best: dict = {}
    masks, durs = bits, lens
    for n in range(1, n_max + 1):
        if n > 1:  # one more interval, indices non-decreasing (every multiset once)
            masks = (masks[:, None] | bits[None, :]).ravel()
            durs = (durs[:, None] + lens[None, :]).ravel()
        order = np.lexsort((durs, masks))
        m, d = masks[order], durs[order]
        first = np.ones(len(m), dtype=bool)
        first[1:] = m[1:] != m[:-1]
        for mm, dd in zip(m[first].tolist(), d[first].tolist()):
            row = best.setdefault(mm, [None] * n_max)
            for j in range(n - 1, n_max):
                if row[j] is None or dd < row[j]:
                    row[j] = dd
        if n < n_max:  # keep the distinct masks of n intervals with their least length for the next step
            masks, durs = m[first], d[first]
    return best


def _brute_front(loop, x0, n_max, masks):
    """Per n = 1..n_max: (least lost samples, least duration in samples) over every escaping schedule of at
    most n sample-aligned attacks, by increasing lost samples (stops once no schedule can do better:
    n intervals of total length D lose at most D + n samples)."""
    N = loop.n_steps
    by_S: dict = {}
    for m in masks:
        by_S.setdefault(bin(m).count("1"), []).append(m)
    S_best = [None] * n_max
    D_best = [None] * n_max
    X0 = np.asarray(x0, dtype=float)[None, :]
    e0 = float(np.maximum(loop.qp.E0, np.abs(X0).max()))
    for S in sorted(by_S):
        if all(D_best[j] is not None and S - (j + 1) >= D_best[j] for j in range(n_max)):
            break
        ms = by_S[S]
        tab = np.array([[(m >> k) & 1 for k in range(N)] for m in ms], dtype=np.uint8)
        esc, _ = evaluate(loop, np.repeat(X0, len(ms), 0), np.full(len(ms), e0), tab, np.arange(len(ms)))
        for m, e in zip(ms, esc):
            if not e:
                continue
            for j, d in enumerate(masks[m]):
                if d is None:
                    continue
                if S_best[j] is None or S < S_best[j]:
                    S_best[j] = S
                if D_best[j] is None or d < D_best[j]:
                    D_best[j] = d
    return S_best, D_best


def _check_against_brute_force(loop, x0, n_max, masks):
    w = worst_attack(loop, x0, attacks=n_max, greedy=False, exhaustive_limit=10 ** 7)
    S_bf, D_bf = _brute_front(loop, x0, n_max, masks)
    assert len(w.front) == n_max
    for j, f in enumerate(w.front):
        assert f["attacks"] == j + 1
        assert f["exact"], (x0, f, w.proof)
        if w.unattacked_escapes:
            assert f["samples_lost"] == 0
            continue
        assert f["samples_lost"] == S_bf[j], (x0, j + 1, f, S_bf)
        if S_bf[j] is None:
            assert not f["escaped"]
            continue
        assert f["total_duration"] == pytest.approx(D_bf[j] * loop.T, abs=1e-9), (x0, j + 1, f, D_bf)
        sch = Schedule.from_list(f["intervals"])
        assert len(sch) <= j + 1
        assert budget.check(sch, 0.0, 0.0).total_duration == pytest.approx(f["total_duration"], abs=1e-9)
    return w


@pytest.mark.slow  # half a second or more on a warm cache
def test_the_front_agrees_with_brute_force_on_a_short_horizon(paper):
    """Every sample-aligned schedule of at most 3 attacks within 12 samples, from x0 = (0.1, 0.1)."""
    loop = replace(Loop.from_scenario(paper), n_steps=12)
    w = _check_against_brute_force(loop, np.array([0.1, 0.1]), 3, _interval_masks(12, 3))
    assert w.front[0]["escaped"]
    # more attacks never need more lost samples
    S = [f["samples_lost"] for f in w.front]
    assert S == sorted(S, reverse=True)


@pytest.mark.slow
@pytest.mark.parametrize("n_max", [2, 3])
def test_the_front_agrees_with_brute_force_on_a_grid_of_initial_states(paper, n_max):
    """The issue's check: N = 2 and 3 attacks, a 5 x 5 grid of initial states inside the nominal region, every
    sample-aligned schedule within a 20-sample horizon."""
    from testbed.sim.batch import in_nominal_roa

    loop = replace(Loop.from_scenario(paper), n_steps=20)
    g = np.linspace(-0.3, 0.3, 5)
    X = np.array([[a, b] for b in g for a in g])
    assert in_nominal_roa(loop.nominal, loop.K, loop.T, X).all()
    masks = _interval_masks(20, n_max)
    for x0 in X:
        _check_against_brute_force(loop, x0, n_max, masks)


# ============================================================================ slow: the paper
def _simulate(tmp_path: Path, base: str, intervals, name: str) -> dict:
    text = re.sub(r"^intervals = .*$", f"intervals = {json.dumps(intervals)}", base, flags=re.M)
    f = tmp_path / f"{name}.toml"
    f.write_text(text)
    p = tb_run("simulate", f, "--json", timeout=300)
    assert p.returncode == 0, p.stderr
    return json.loads(p.stdout)


@pytest.mark.slow
def test_worst_attack_on_the_paper_is_minimal_in_testbed_simulate(tmp_path):
    p = tb_run("worst-attack", "paper", "--json", "--no-progress", "--workers", "1", timeout=600)
    assert p.returncode == 0, p.stderr
    d = json.loads(p.stdout)
    for key in ("intervals", "total_duration", "samples_lost", "escaped", "exact", "greedy", "search", "front",
                "proof", "escape_criterion"):
        assert key in d, key
    assert d["method"] == "paper"  # ``method`` names the coding-and-control method; the search is ``search``
    assert d["escaped"] and d["exact"] and len(d["intervals"]) == 1
    assert d["front"] == [{"attacks": 1, "samples_lost": d["samples_lost"], "total_duration": d["total_duration"],
                           "intervals": d["intervals"], "exact": True, "escaped": True}]
    assert d["proof"][0]["samples_lost_below"] == d["samples_lost"]
    (a, tau), = d["intervals"]
    assert d["total_duration"] == pytest.approx(tau)
    # shorter than the paper's two attacks (2.0 s in all), which the loop survives
    assert tau < 2.0
    base = (Path(scenario.__file__).parent / "bundled" / "paper.toml").read_text()
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
    assert d["escape_criterion"]["kind"] and d["show"] == "duration"
    # at most two attacks, the map of lost samples: the same search and pricing per state
    png2 = tmp_path / "v2.png"
    assert main(["vulnerability", "paper", "--grid", "9", "--attacks", "2", "--show", "samples", "--json",
                 "--no-progress", "--exhaustive-limit", "2000", "--plot", str(png2)]) == 0
    d2 = json.loads(capsys.readouterr().out)
    assert d2["attacks"] == 2 and d2["show"] == "samples" and png2.stat().st_size > 1000
    S1, S2 = np.array(d["samples"]), np.array(d2["samples"])
    assert np.array_equal(S1 > -2, S2 > -2)
    hit = S2 > 0
    assert np.all(S2[hit] <= np.where(S1[hit] > 0, S1[hit], np.inf))  # two attacks never need more samples
    dur2 = np.array([[np.nan if v is None else v for v in row] for row in d2["duration"]])
    np.testing.assert_allclose(dur2[hit], (S2[hit] - np.minimum(2, S2[hit])) * d2["T"], atol=1e-9)
    ex2 = np.array(d2["exact"])
    assert d2["states_exact"] == int(ex2[S2 > -2].sum())


_cli = functools.partial(tb_run, timeout=900)


@pytest.mark.slow
def test_three_attacks_on_the_paper_cost_at_most_0_3_s_and_the_scenario_escapes(tmp_path):
    """The issue's case: [0, +0.5] escapes from (0.1, 0.1); three attacks losing the same samples cost 0.3 s."""
    out = tmp_path / "worst.toml"
    p = _cli("worst-attack", "paper", "--attacks", "3", "--json", "--no-progress", "--no-greedy",
             "--scenario-out", str(out))
    assert p.returncode == 0, p.stderr
    d = json.loads(p.stdout)
    assert d["escaped"] and 1 <= len(d["intervals"]) <= 3
    assert d["total_duration"] <= 0.3 + 1e-9
    assert [f["attacks"] for f in d["front"]] == [1, 2, 3] and [q["attacks"] for q in d["proof"]] == [1, 2, 3]
    S = [f["samples_lost"] for f in d["front"]]
    assert S == sorted(S, reverse=True) and S[-1] == d["samples_lost"]
    for f in d["front"]:  # priced (S - min(n, S)) T, and budget.check agrees with the intervals
        assert f["total_duration"] == pytest.approx((f["samples_lost"] - min(f["attacks"], f["samples_lost"])) * 0.1)
        rep = budget.check(Schedule.from_list(f["intervals"]), 0.0, 0.0)
        assert rep.n_attacks <= f["attacks"] and rep.total_duration == pytest.approx(f["total_duration"], abs=1e-9)
        # exact only where the proof reaches the answer
        assert f["exact"] == (d["proof"][f["attacks"] - 1]["samples_lost_below"] >= f["samples_lost"])
    # testbed simulate confirms: the paper with these intervals escapes, and so does the written scenario
    base = (Path(scenario.__file__).parent / "bundled" / "paper.toml").read_text()
    assert _simulate(tmp_path, base, d["intervals"], "three")["escaped"] is True
    written = scenario.load(out)
    assert written.attack.kind == "intervals" and written.n_steps == d["n_steps"]
    assert list(written.x0) == d["x0"] and written.quantizer.E0 == d["E0"]
    p = _cli("simulate", str(out), "--json")
    assert p.returncode == 0, p.stderr
    sim = json.loads(p.stdout)
    assert sim["escaped"] is True and sim["packets_dropped"] == d["samples_lost"]
    # an existing file is refused without --force, and left as it was
    before = out.read_text()
    p = _cli("worst-attack", "paper", "--no-greedy", "--no-progress", "--scenario-out", str(out))
    assert p.returncode == 2 and "--force" in p.stderr and out.read_text() == before


@pytest.mark.slow  # end to end: worst-attack in its own process
def test_scenario_out_when_nothing_escapes_exits_1_and_writes_nothing(tmp_path):
    out = tmp_path / "none.toml"
    p = _cli("worst-attack", "paper", "--max-length", "0.1", "--no-greedy", "--no-progress", "--workers", "1",
             "--json", "--scenario-out", str(out))
    assert p.returncode == 1, p.stderr
    d = json.loads(p.stdout)
    assert d["escaped"] is False and d["scenario_out"] is None and not out.exists()
    assert "not written" in p.stderr
    out.write_text("keep")
    p = _cli("worst-attack", "paper", "--max-length", "0.1", "--no-greedy", "--no-progress", "--workers", "1",
             "--scenario-out", str(out), "--force")
    assert p.returncode == 1 and out.read_text() == "keep"
    assert not list(tmp_path.glob(".worst-*"))


@pytest.mark.slow  # end to end: worst-attack and simulate in their own processes
@pytest.mark.parametrize("method", ["zoom", "unquantized"])
def test_scenario_out_of_a_swapped_method_names_the_method_and_escapes(tmp_path, method):
    """``--method`` with ``--scenario-out``: the file's [method] is the one searched, its [quantizer]
    keeps only the keys that method uses (so it loads), and testbed simulate confirms the escape."""
    out = tmp_path / "worst.toml"
    p = _cli("worst-attack", "paper", "--method", method, "--json", "--no-progress", "--no-greedy",
             "--scenario-out", str(out))
    assert p.returncode == 0, p.stderr
    d = json.loads(p.stdout)
    assert d["escaped"] and d["method"] == method
    written = scenario.load(out)  # no unused-key error: only the method's own keys were written
    assert written.method.name == method
    p = _cli("simulate", str(out), "--json")
    assert p.returncode == 0, p.stderr
    sim = json.loads(p.stdout)
    assert sim["method"] == method and sim["escaped"] is True and sim["packets_dropped"] == d["samples_lost"]
