"""Methods from the command line: versus, methods, a user's method next to its scenario, traces, bad methods.

The commands run in their own processes, from a working directory that is not the method's folder.
"""

from __future__ import annotations

import json
import math
import os
import secrets
import shutil
from pathlib import Path

import helpers.cli
import numpy as np
import pytest

EXAMPLES = Path(__file__).resolve().parents[2] / "docs" / "examples"


def tb(*args, cwd, timeout=helpers.cli.TIMEOUT):
    return helpers.cli.tb(*args, cwd=cwd, env={"MPLBACKEND": "Agg"}, timeout=timeout)


@pytest.fixture
def method_dir(tmp_path):
    """``<tmp>/methoddir/{mymethod.py, mymethod.toml}`` (the docs' worked example) and ``<tmp>/elsewhere``."""
    d = tmp_path / "methoddir"
    d.mkdir()
    for f in ("mymethod.py", "mymethod.toml"):
        shutil.copy(EXAMPLES / f, d / f)
    (tmp_path / "elsewhere").mkdir()
    return d


@pytest.mark.slow  # end to end: testbed versus in its own process
def test_versus_paper_zoom_unquantized(tmp_path):
    """The paper's method converges, the zoom quantizer saturates (and recovers by its zoom-out), the
    unquantized loop converges, and all three faced the same attack."""
    rc, out, err = tb("versus", "paper", "--methods", "paper,zoom,unquantized", "--json", "--plot",
                      tmp_path / "v.png", cwd=tmp_path)
    assert rc == 0, err
    d = json.loads(out)
    rows = {r["method"]: r for r in d["rows"]}
    assert list(rows) == ["paper", "zoom", "unquantized"]
    for r in d["rows"]:
        assert set(r) == {"method", "seed", "converged", "escaped", "final_norm", "max_norm", "saturations",
                          "samples_lost", "bits", "settle_samples"}
        assert r["seed"] is None
    assert rows["paper"]["converged"] and rows["paper"]["saturations"] == 0
    assert rows["zoom"]["saturations"] > 0
    assert rows["unquantized"]["converged"] and rows["unquantized"]["bits"] == 128
    assert rows["paper"]["samples_lost"] == rows["zoom"]["samples_lost"] == rows["unquantized"]["samples_lost"] == 22
    assert rows["paper"]["settle_samples"] is not None and rows["paper"]["settle_samples"] > 48
    assert "ignores [quantizer]" in err and (tmp_path / "v.png").stat().st_size > 1000


@pytest.mark.slow  # end to end: three testbed versus processes
def test_versus_seeds_summary(tmp_path):
    """--seeds: every method on the same random attack per seed; success rate, Wilson interval, paired
    difference to the first method (checked against the rows)."""
    from testbed.campaign.engine import wilson

    sc = tmp_path / "rand.toml"
    sc.write_text((EXAMPLES.parents[0].parent / "testbed" / "scenario" / "bundled" / "paper.toml").read_text()
                  .replace('kind = "intervals"\nintervals = [[1.0, 1.2], [4.0, 0.8]]   # [start, length] in seconds',
                           'kind = "random"\nkappa_F = 1.0\nrho_F = 0.2\nkappa_D = 0.4\nrho_D = 0.1')
                  .replace("duration = 30.0", "duration = 10.0"))
    rc, out, err = tb("versus", sc, "--methods", "paper,unquantized-hold", "--seeds", "4", "--seed", "7", "--json",
                      cwd=tmp_path)
    assert rc == 0, err
    assert "drew seed" not in err    # the rows use seeds 7..10: nothing is drawn
    d = json.loads(out)
    assert d["seeds"] == [7, 8, 9, 10] and len(d["rows"]) == 8
    lost = {}
    for r in d["rows"]:
        lost.setdefault(r["seed"], set()).add(r["samples_lost"])
    assert all(len(v) == 1 for v in lost.values())            # the same attack per seed
    assert len({next(iter(v)) for v in lost.values()}) > 1    # different attacks across seeds
    for m in ("paper", "unquantized-hold"):
        ok = [r["converged"] for r in d["rows"] if r["method"] == m]
        s = d["summary"][m]
        assert s["n"] == 4 and s["successes"] == sum(ok)
        assert s["wilson95"] == pytest.approx(list(wilson(sum(ok), 4)))
    pd = d["summary"]["unquantized-hold"]["paired_difference"]
    a = [r["converged"] for r in d["rows"] if r["method"] == "unquantized-hold"]
    b = [r["converged"] for r in d["rows"] if r["method"] == "paper"]
    assert pd["vs"] == "paper" and pd["difference"] == pytest.approx((sum(a) - sum(b)) / 4)
    # the exact McNemar p of the discordant pairs, from the binomial pmf; Newcombe's interval is never a point
    x, y = sum(p and not q for p, q in zip(a, b)), sum(q and not p for p, q in zip(a, b))
    m = x + y
    p_hand = 1.0 if m == 0 else min(1.0, 2 * sum(math.comb(m, i) for i in range(min(x, y) + 1)) / 2 ** m)
    assert (pd["a_only"], pd["b_only"]) == (x, y) and pd["mcnemar_p"] == pytest.approx(p_hand)
    lo, hi = pd["ci95"]
    assert lo <= pd["difference"] <= hi and lo < hi
    for m_ in ("paper", "unquantized-hold"):
        s = d["summary"][m_]
        assert s["converged"] + s["bounded"] + s["escaped"] == 4
    cont = d["summary"]["unquantized-hold"]["paired_continuous"]
    assert set(cont) == {"settle_samples", "max_norm", "saturations"}
    mx = [r["max_norm"] for r in d["rows"] if r["method"] == "unquantized-hold"]
    mp = [r["max_norm"] for r in d["rows"] if r["method"] == "paper"]
    assert cont["max_norm"]["n"] == 4 and cont["max_norm"]["median_difference"] == pytest.approx(
        float(np.median(np.subtract(mx, mp))))
    rc, out, err = tb("versus", sc, "--methods", "paper,unquantized-hold", "--seeds", "4", "--seed", "7", cwd=tmp_path)
    assert rc == 0 and "minus paper on the same seeds (4 pairs): converged" in out and "McNemar p" in out
    # without --seeds: one seed drawn, named on stderr, and every method (a swapped one too) faces it
    rc, out, err = tb("versus", sc, "--methods", "paper,unquantized-hold", "--json", cwd=tmp_path)
    assert rc == 0, err
    drawn = int(err.split("drew seed = ")[1].split()[0])
    rows = json.loads(out)["rows"]
    assert [r["seed"] for r in rows] == [drawn, drawn] and rows[0]["samples_lost"] == rows[1]["samples_lost"]


@pytest.mark.slow  # half a second or more on a warm cache
def test_wilson_against_a_direct_computation():
    from testbed.campaign.engine import wilson

    lo, hi = wilson(7, 10)
    # Wilson (1927): (p + z^2/2n -+ z sqrt(p(1-p)/n + z^2/4n^2)) / (1 + z^2/n), p = 0.7, z = 1.96
    assert lo == pytest.approx(0.3968, abs=1e-4) and hi == pytest.approx(0.8922, abs=1e-4)
    assert wilson(0, 5)[0] == 0.0 and wilson(5, 5)[1] == 1.0


@pytest.mark.slow  # its own processes (an interpreter start-up each)
def test_methods_command():
    rc, out, err = tb("methods", "--json", cwd=".")
    assert rc == 0, err
    rows = {m["name"]: m for m in json.loads(out)["methods"]}
    assert set(rows) >= {"paper", "zoom", "static", "unquantized", "unquantized-hold"}
    assert rows["paper"]["bits"] == 6 and rows["unquantized"]["bits"] == 128
    assert all("batch" in rows[n]["runs"] for n in rows)


@pytest.mark.slow  # end to end: a user's method loaded by four processes
def test_user_method_next_to_scenario_simulate_and_report(method_dir):
    """A method from a module next to its scenario: simulate from another folder, record, and report the
    recording from a third; the recording stores the method's reference, source and hash."""
    work = method_dir.parent / "elsewhere"
    rc, out, err = tb("simulate", "../methoddir/mymethod.toml", "--json", "--out", "../run.mcap", cwd=work)
    assert rc == 0, err
    sim = json.loads(out)
    assert sim["method"] == "mymethod:CenteredZoom" and sim["converged"] and sim["encoder_decoder_agree"]
    assert sim["bits"] == 6
    rc, out, err = tb("report", method_dir.parent / "run.mcap", "--json", cwd="/")
    assert rc == 0, err
    rep = json.loads(out)
    assert rep["x"] == sim["x"] and rep["method"] == "mymethod:CenteredZoom"
    from testbed.record.columns import read_metadata

    meta, _ = read_metadata(method_dir.parent / "run.mcap")
    m = meta["testbed.scenario"]
    assert m["method_ref"] == "mymethod:CenteredZoom" and m["method_class"] == "CenteredZoom"
    assert "class CenteredZoom" in m["method_source"] and len(m["method_sha256"]) == 64
    # the method's folder gone: with --trust-code the report loads the source stored in the recording (and
    # says so; without it, tests/runs/test_trust_code.py)
    shutil.move(method_dir, method_dir.parent / "moved")
    rc, out, err = tb("report", method_dir.parent / "run.mcap", "--json", "--trust-code", cwd="/")
    assert rc == 0, err
    assert json.loads(out)["x"] == sim["x"] and "loaded the source stored in" in err
    shutil.move(method_dir.parent / "moved", method_dir)
    # batch commands say clearly that a user's method has no kernel
    rc, out, err = tb("sweep", "../methoddir/mymethod.toml", cwd=work)
    assert rc == 2 and "no batch kernel" in err and len(err.strip().splitlines()) == 1


@pytest.mark.slow  # end to end: simulate, versus and campaign processes
def test_swapping_in_the_scenarios_own_method_keeps_its_params(method_dir):
    """One swap rule: --method with the scenario's own method keeps its [method] params (a = 0.9, not the
    default 0.96), another method names the params it drops in one stderr line, and simulate, versus and a
    campaign axis over method.name give the same row for the scenario's own method."""
    work = method_dir.parent / "elsewhere"
    sc = method_dir / "mymethod.toml"
    sc.write_text(sc.read_text().replace("params = { a = 0.96 }", "params = { a = 0.9 }")
                  .replace("duration = 30.0", "duration = 6.0"))
    (method_dir / "default.toml").write_text(sc.read_text().replace("params = { a = 0.9 }\n", ""))
    own = "mymethod:CenteredZoom"

    def simulate(*a):
        rc, out, err = tb("simulate", *a, "--json", cwd=work)
        assert rc == 0, err
        return json.loads(out), err

    base, err0 = simulate(sc)
    swapped, err1 = simulate(sc, "--method", own)
    default, _ = simulate(method_dir / "default.toml")
    assert default["final_norm"] != base["final_norm"]          # the param matters
    assert swapped["x"] == base["x"] and swapped["final_norm"] == base["final_norm"]
    assert "note" not in err0 + err1
    _, err = simulate(sc, "--method", "paper")
    notes = [ln for ln in err.splitlines() if "note" in ln]
    assert notes == ["testbed simulate: note: method 'paper' drops the [method] params a of 'mymethod:CenteredZoom'"]
    rc, out, err = tb("versus", sc, "--methods", f"{own},paper", "--json", cwd=work)
    assert rc == 0, err
    rows = {r["method"]: r for r in json.loads(out)["rows"]}
    assert rows[own]["final_norm"] == base["final_norm"] and rows[own]["saturations"] == base["saturations"]
    assert "drops the [method] params a of" in err
    (work / "c.toml").write_text(f'scenario = "{sc}"\n[axes]\n"method.name" = ["{own}", "paper"]\n')
    rc, out, err = tb("campaign", "c.toml", "--out", "o", "--workers", "1", "--no-progress", cwd=work)
    assert rc == 0, err
    import pyarrow.parquet as pq

    crow = {r["method"]: r for r in pq.read_table(work / "o" / "runs.parquet").to_pylist()}
    assert crow[own]["final_norm"] == base["final_norm"] and crow[own]["saturations"] == base["saturations"]
    assert crow["paper"]["final_norm"] == rows["paper"]["final_norm"]
    assert "testbed campaign: note: method 'paper' drops the [method] params a of 'mymethod:CenteredZoom'" in err


@pytest.mark.slow  # end to end: six testbed processes
def test_trace_method_b_loses_method_a_samples(tmp_path):
    """Method B on method A's recording (a trace of the samples A's attacker dropped) loses exactly them;
    the trace is embedded in B's recording (report works with A's file gone); a wrong T or a trace shorter
    than the run is one line, exit 2."""
    rc, out, err = tb("simulate", "paper", "--method", "zoom", "--json", "--out", "a.mcap", cwd=tmp_path)
    assert rc == 0, err
    a = json.loads(out)
    text = (Path(__file__).resolve().parents[2] / "testbed" / "scenario" / "bundled" / "paper.toml").read_text()
    text = text.replace('kind = "intervals"\nintervals = [[1.0, 1.2], [4.0, 0.8]]   # [start, length] in seconds',
                        'kind = "trace"\nsource = "a.mcap"')
    assert 'source = "a.mcap"' in text
    (tmp_path / "b.toml").write_text(text)
    rc, out, err = tb("simulate", "b.toml", "--method", "unquantized", "--json", "--out", "b.mcap", cwd=tmp_path)
    assert rc == 0, err
    b = json.loads(out)
    lost_a = [k for k, t in enumerate(a["theta"]) if t]
    assert [k for k, t in enumerate(b["theta"]) if t] == lost_a and b["method"] == "unquantized"
    (tmp_path / "a.mcap").rename(tmp_path / "gone.mcap")
    (tmp_path / "other").mkdir()
    rc, out, err = tb("report", "../b.mcap", "--json", cwd=tmp_path / "other")
    assert rc == 0, err
    assert [k for k, t in enumerate(json.loads(out)["theta"]) if t] == lost_a
    (tmp_path / "gone.mcap").rename(tmp_path / "a.mcap")
    rc, out, err = tb("simulate", "b.toml", "--duration", "60", cwd=tmp_path)
    assert rc == 2 and "shorter than the run" in err and len(err.strip().splitlines()) == 1
    (tmp_path / "t.txt").write_text("# T = 0.2\n1 2 3\n")
    (tmp_path / "c.toml").write_text(text.replace("a.mcap", "t.txt"))
    rc, out, err = tb("simulate", "c.toml", cwd=tmp_path)
    assert rc == 2 and "T = 0.2" in err and len(err.strip().splitlines()) == 1
    (tmp_path / "d.toml").write_text(text.replace("a.mcap", "d.txt"))
    (tmp_path / "d.txt").write_text("# T = 0.1\n# samples = 300\n" + "\n".join(map(str, lost_a)) + "\n")
    rc, out, err = tb("simulate", "d.toml", "--json", cwd=tmp_path)
    assert rc == 0, err
    assert [k for k, t in enumerate(json.loads(out)["theta"]) if t] == lost_a


BAD = '''
import numpy as np
from testbed.methods import DecoderEnd, EncoderEnd, IntCodebook, Method


class Enc(EncoderEnd):
    def symbol(self, x):
        return 0, False, np.zeros(self.plant.n)

    def update(self, theta, symbol):
        self.E += 1.0          # the decoder does not: the ends disagree


class Dec(DecoderEnd):
    def control(self, symbol):
        if self.k == 7 and RAISE:
            raise ZeroDivisionError("boom")
        return np.zeros(self.plant.m), np.zeros(self.plant.n)


class Disagree(Method):
    encoder_class, decoder_class = Enc, Dec

    def codebook(self, n, qp):
        return IntCodebook(2)


RAISE = {raise_}
'''


@pytest.mark.slow  # its own processes (an interpreter start-up each)
@pytest.mark.parametrize("ref, msg", [
    ("nosuchmethod", "unknown method 'nosuchmethod'"),
    ("nomod_xyz:Thing", "no module 'nomod_xyz'"),
    ("badmeth:Missing", "has no 'Missing'"),
    ("badmeth:np", "is not a subclass of testbed.methods.Method"),
])
def test_bad_method_references_one_line(tmp_path, ref, msg):
    (tmp_path / "badmeth.py").write_text(BAD.replace("{raise_}", "False"))
    rc, out, err = tb("simulate", "paper", "--method", ref, cwd=tmp_path)
    assert rc == 2 and msg in err and len(err.strip().splitlines()) == 1, err


@pytest.mark.slow  # end to end: a user's method in its own processes
def test_method_whose_ends_disagree_or_raise(tmp_path):
    text = (Path(__file__).resolve().parents[2] / "testbed" / "scenario" / "bundled" / "paper.toml").read_text()
    for raise_, what in (("False", "broke lockstep"), ("True", "raised at sample 7: ZeroDivisionError: boom")):
        d = tmp_path / raise_
        d.mkdir()
        (d / "badmeth.py").write_text(BAD.replace("{raise_}", raise_))
        (d / "s.toml").write_text(text)
        rc, out, err = tb("simulate", d / "s.toml", "--method", "badmeth:Disagree", "--duration", "2", cwd=tmp_path)
        assert rc == 1 and what in err, err
        assert "Traceback" not in err and len([ln for ln in err.splitlines() if "testbed simulate:" in ln]) == 2


# ============================================================================ live
def _live(tmp_path, scenario, rid, *more, cwd):
    from helpers.procs import reap

    try:
        rc, out, err = tb("run", scenario, "--json", "--run-id", rid, "--run-dir", tmp_path / f"logs-{rid}", *more,
                          cwd=cwd)
    finally:
        assert not reap(rid)
    try:
        return rc, json.loads(out), err
    except json.JSONDecodeError:
        pytest.fail(f"no JSON summary (exit {rc})\nstdout: {out[-2000:]}\nstderr: {err[-3000:]}")


@pytest.mark.process
def test_live_user_method_equals_simulation(method_dir):
    """A live run of a user's method (module next to the scenario, run from another folder) equals its
    simulation bit for bit; testbed report reads the recording from a third folder."""
    from failclosed import rerun_flags, rerun_while_stalled
    from helpers.live import BIT_EXACT_KEYS, mismatch

    work = method_dir.parent / "elsewhere"
    rec = method_dir.parent / "live.mcap"
    rid = f"t{os.getpid()}xmeth{secrets.token_hex(3)}"

    def attempt(n):
        return _live(method_dir.parent, "../methoddir/mymethod.toml", rid + "r" * n, "--duration", "3", "--out", rec,
                     *(("--force",) if n else ()), *rerun_flags(n), cwd=work)

    rc, s, err = rerun_while_stalled(attempt, "user method")
    assert rc == 0, (s.get("faults"), err[-2000:])
    rc, out, err = tb("simulate", "../methoddir/mymethod.toml", "--duration", "3", "--json", cwd=work)
    assert rc == 0, err
    sim = json.loads(out)
    for key in BIT_EXACT_KEYS:
        assert s[key] == sim[key], mismatch(s, sim, key)
    rc, out, err = tb("report", rec, "--json", cwd="/")
    assert rc == 0, err
    assert json.loads(out)["method"] == "mymethod:CenteredZoom"


@pytest.mark.process
@pytest.mark.parametrize("method", ["zoom", "unquantized-hold"])
def test_live_bundled_method_equals_simulation(tmp_path, method):
    from failclosed import rerun_flags, rerun_while_stalled
    from helpers.live import BIT_EXACT_KEYS, mismatch

    rid = f"t{os.getpid()}xbm{secrets.token_hex(3)}"

    def attempt(n):
        return _live(tmp_path, "paper", rid + "r" * n, "--duration", "3", "--method", method, *rerun_flags(n),
                     cwd=tmp_path)

    rc, s, err = rerun_while_stalled(attempt, method)
    assert rc == 0, (s.get("faults"), err[-2000:])
    rc, out, err = tb("simulate", "paper", "--duration", "3", "--method", method, "--json", cwd=tmp_path)
    sim = json.loads(out)
    for key in BIT_EXACT_KEYS:
        assert s[key] == sim[key], mismatch(s, sim, key)


@pytest.mark.process
def test_live_method_that_raises_ends_the_run_recording_intact(tmp_path):
    text = (Path(__file__).resolve().parents[2] / "testbed" / "scenario" / "bundled" / "paper.toml").read_text()
    (tmp_path / "badmeth.py").write_text(BAD.replace("{raise_}", "True").replace("self.E += 1.0", "pass"))
    (tmp_path / "s.toml").write_text(text)
    rid = f"t{os.getpid()}xraise{secrets.token_hex(3)}"
    rc, s, err = _live(tmp_path, tmp_path / "s.toml", rid, "--duration", "3", "--method", "badmeth:Disagree",
                       "--out", tmp_path / "r.mcap", cwd=tmp_path)
    assert rc != 0
    assert any("boom" in json.dumps(f) for f in s.get("faults", [])), s.get("faults")
    rc, out, err = tb("report", tmp_path / "r.mcap", "--json", cwd=tmp_path)
    assert rc == 0, err
    assert json.loads(out)["method"] == "badmeth:Disagree"


@pytest.mark.process
def test_versus_live(tmp_path):
    """--live: each method live, one after the other, each recorded; the rows come from the recordings,
    the same attack for both (the same lost samples where none was withheld), equal to the simulation
    where the live run was bit exact."""
    rc, out, err = tb("versus", "paper", "--methods", "paper,unquantized", "--live", "--out", tmp_path / "recs",
                      "--json", "--plot", tmp_path / "v.png", cwd=tmp_path, timeout=2 * helpers.cli.TIMEOUT)
    assert rc == 0, err
    d = json.loads(out)
    assert [r["method"] for r in d["rows"]] == ["paper", "unquantized"]
    for r in d["rows"]:
        rec = Path(r["recording"]) if Path(r["recording"]).is_absolute() else tmp_path / r["recording"]
        assert r["converged"] and r["samples_lost"] >= 22   # late or withheld samples count too, live
        rc, out, err = tb("report", rec, "--json", cwd=tmp_path)
        assert rc == 0, err
        assert json.loads(out)["dropped_by_attacker"] == 22  # the attacker dropped the same samples
    assert (tmp_path / "v.png").stat().st_size > 1000
    rc, out, err = tb("versus", "paper", "--methods", "paper", "--live", "--out", tmp_path / "recs", cwd=tmp_path)
    assert rc == 2 and "never overwritten" in err
