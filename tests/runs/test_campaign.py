"""``testbed campaign``: the 120-run campaign against single ``testbed simulate --json`` runs, bad
input, the seeds rule, resume after SIGKILL, ``--verify`` (and a tampered row), Dask, live runs."""

from __future__ import annotations

import functools
import json
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from helpers.cli import tb_cmd, tb_run
from helpers.sims import paper_loop_toml

from testbed.campaign import folder as cmp_folder
from testbed.campaign import rows as cmp_rows
from testbed.campaign import runner as campaignrun
from testbed.campaign import spec as cmp
from testbed.loop.channel import LOSS_KINDS

ROOT = Path(__file__).resolve().parents[2]

#: the paper's example under a random DoS within a budget, 8 s (short runs: the campaign is the subject)
RANDOM_SCENARIO = """\
name = "paper-random"
description = "the paper's example under a random DoS"

""" + paper_loop_toml(mode="resilient") + """
[attack]
kind = "random"
kappa_F = 1.0
rho_F = 0.2
kappa_D = 0.3
rho_D = 0.3

[run]
duration = 8.0
"""

CAMPAIGN_120 = """\
scenario = "random.toml"
runs = "simulated"
seed = 1
[axes]
"method.name" = ["paper", "zoom"]
"attack.seed" = [{seeds}]
"""


_cli = functools.partial(tb_run, timeout=600)


def _campaign(tmp_path: Path, text: str, name: str = "c.toml") -> Path:
    (tmp_path / "random.toml").write_text(RANDOM_SCENARIO)
    p = tmp_path / name
    p.write_text(text)
    return p


def _table(folder: Path) -> list[dict]:
    return pq.read_table(folder / "runs.parquet").to_pylist()


def _strip(rows):
    return [{k: v for k, v in r.items() if k != "wall_s"} for r in rows]


@pytest.fixture(scope="module")
def c120(tmp_path_factory):
    """The 120-run campaign (2 methods x 60 seeds of a random attack), run once on 2 local workers."""
    d = tmp_path_factory.mktemp("c120")
    c = _campaign(d, CAMPAIGN_120.format(seeds=", ".join(str(s) for s in range(60))))
    p = _cli("campaign", c, "--out", d / "out", "--workers", 2, "--json", cwd=d)
    assert p.returncode == 0, p.stderr
    assert "campaign: 120/120 runs done, 0 failed, 0 left" in p.stderr  # progress on stderr
    return d, json.loads(p.stdout)


@pytest.mark.slow
def test_120_runs_equal_single_simulate_runs(c120):
    d, out = c120
    rows = _table(d / "out")
    assert len(rows) == 120 and len({r["run"] for r in rows}) == 120
    assert {(r["method.name"], r["attack.seed"]) for r in rows} == {(m, s) for m in ("paper", "zoom") for s in range(60)}
    assert all(r["status"] == "ok" and r["seeds.attack"] == r["attack.seed"] for r in rows)
    assert out["summary"]["done"] == 120 and out["summary"]["failed"] == 0
    # spot-check: the same points as separate testbed simulate processes (the scenario, --method, --seed)
    pick = np.random.default_rng(27).choice(120, size=4, replace=False)
    for i in pick:
        r = rows[int(i)]
        p = _cli("simulate", "random.toml", "--method", r["method.name"], "--seed", r["attack.seed"], "--json", cwd=d)
        assert p.returncode == 0, p.stderr
        s = json.loads(p.stdout)
        for k in cmp.OUTCOME_KEYS:
            assert r[k] == s[k], (r["run"], k, r[k], s[k])
    # the summary by method: counts and the Wilson interval from the rows
    by = {g["value"]: g for g in out["summary"]["by_axis"]["method.name"]}
    for m in ("paper", "zoom"):
        ok = sum(1 for r in rows if r["method.name"] == m and r["converged"])
        assert by[m]["successes"] == ok and by[m]["n"] == 60
        lo, hi = by[m]["wilson95"]
        assert lo <= ok / 60 <= hi
    md = (d / "out" / "summary.md").read_text()
    assert "95 % Wilson" in md and "By method.name" in md
    man = json.loads((d / "out" / "manifest.json").read_text())
    assert man["packages"]["numpy"] == np.__version__ and man["source"].startswith("sha256:")
    assert len(man["runs"]) == 120 and all((d / "out" / r["scenario"]).is_file() for r in man["runs"])


@pytest.mark.slow
def test_same_command_again_skips_finished_runs(c120):
    d, _ = c120
    before = _table(d / "out")
    p = _cli("campaign", "c.toml", "--out", "out", "--workers", 1, "--json", cwd=d)
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    assert out["ran"] == 0 and out["skipped"] == 120
    assert _table(d / "out") == before


@pytest.mark.slow
def test_verify_and_a_tampered_row(c120, tmp_path):
    import shutil

    import pyarrow as pa

    d, _ = c120
    p = _cli("campaign", "--verify", d / "out", "--sample", 10, "--seed", 3, "--json", cwd=d)
    assert p.returncode == 0, p.stdout + p.stderr
    v = json.loads(p.stdout)
    assert v["identical"] and v["checked_simulated"] == 10 and v["differences"] == []
    # a reviewer's copy with one row changed (the last bit of one final norm)
    cp = tmp_path / "copy"
    shutil.copytree(d / "out", cp)
    t = pq.read_table(cp / "runs.parquet")
    fn = t.column("final_norm").to_pylist()
    fn[17] = float(np.nextafter(fn[17], np.inf))
    t = t.set_column(t.schema.get_field_index("final_norm"), "final_norm", pa.array(fn))
    pq.write_table(t, cp / "runs.parquet")
    man = json.loads((cp / "manifest.json").read_text())
    man["packages"]["numpy"] = "0.0"
    (cp / "manifest.json").write_text(json.dumps(man))
    p = _cli("campaign", "--verify", cp, cwd=tmp_path)  # every row: the tampered one among them
    assert p.returncode == 1, p.stdout + p.stderr
    run17 = t.column("run").to_pylist()[17]
    assert f"DIFFERS: run {run17} final_norm" in p.stdout
    assert p.stdout.count("DIFFERS") == 1
    assert f"version: numpy 0.0 in the manifest, {np.__version__} here" in p.stdout


@pytest.mark.slow  # end to end: a campaign process per bad value
def test_bad_value_is_one_line_naming_axis_value_reason(tmp_path):
    c = _campaign(tmp_path, 'scenario = "random.toml"\n[axes]\n"method.name" = ["paper"]\n'
                            '"plant.x0" = [[0.1, 0.1], [9.0, 0.0]]\n')
    p = _cli("campaign", c, "--out", tmp_path / "o", cwd=tmp_path)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "axis 'plant.x0' value [9.0, 0.0]" in lines[0] and "E0" in lines[0], p.stderr
    assert not (tmp_path / "o").exists()  # nothing ran, no folder
    for text, words in [('scenario = "random.toml"\n[axes]\n"quantizer.M" = [6, -1]\n', ["'quantizer.M'", "-1"]),
                        ('scenario = "random.toml"\n[axes]\n"method.name" = ["paper", "nope"]\n', ["'method.name'",
                                                                                                   '"nope"']),
                        ('scenario = "random.toml"\nrepeat = 0\n', ["repeat"]),
                        ('scenario = "random.toml"\n[axes]\n"x0" = [1]\n', ["'x0'"]),
                        ('scenario = "nowhere.toml"\n', ["nowhere.toml"]),
                        ('scenario = "paper"\n[axes]\n"attack.seed" = [1, 2]\n', ["'attack.seed'", "varies nothing",
                                                                                  "'intervals'"])]:
        c.write_text(text)
        p = _cli("campaign", c, "--out", tmp_path / "o", cwd=tmp_path)
        lines = p.stderr.strip().splitlines()
        assert p.returncode == 2 and len(lines) == 1 and all(w in lines[0] for w in words), (text, p.stderr)


@pytest.mark.slow  # half a second or more on a warm cache
def test_each_method_its_own_params(tmp_path):
    """[methods.NAME] params give one method of a method.name axis its params (over the scenario's own when
    it is the scenario's method, under a method.params axis); a bad one is one line before anything runs,
    and a method.params axis that one method lacks says how to give it to one method only."""
    (tmp_path / "own.toml").write_text(RANDOM_SCENARIO.replace("[run]", '[method]\nname = "static"\n'
                                                               'params = { range = 0.7 }\n\n[run]')
                                       .replace('L = 10.0\nE0 = 0.1\nmode = "resilient"\n', ""))
    base = 'scenario = "own.toml"\nseed = 2\n[axes]\n"method.name" = ["static", "unquantized"]\n'
    c = tmp_path / "m.toml"
    c.write_text(base)
    runs, notes = cmp.plan(cmp.parse(c))
    assert "range = 0.7" in runs[0].text and "[method]" in runs[1].text and "range" not in runs[1].text
    assert notes == ["method 'unquantized' ignores [quantizer] M of this scenario and drops the [method] params "
                     "range of 'static'"]
    c.write_text(base + '[methods.static]\nparams = { range = 0.5 }\n')
    runs, _ = cmp.plan(cmp.parse(c))
    assert "range = 0.5" in runs[0].text and "range" not in runs[1].text
    c.write_text(base.replace('"unquantized"]', '"paper"]\n"method.params.range" = [0.4]') + '[methods.static]\n'
                 'params = { range = 0.5 }\n')
    with pytest.raises(cmp.BadInput, match=r"has no parameter 'range'.*\[methods\.\"NAME\"\] params"):
        cmp.plan(cmp.parse(c))
    c.write_text(base.replace(', "unquantized"]', "]\n\"method.params.range\" = [0.4, 0.3]") + '[methods.static]\n'
                 'params = { range = 0.5 }\n')
    runs, _ = cmp.plan(cmp.parse(c))
    assert ["range = 0.4" in runs[0].text, "range = 0.3" in runs[1].text] == [True, True]
    for extra, words in [('[methods.unquantized]\nparams = { range = 1.0 }\n', ['[methods."unquantized"] params', "range"]),
                         ('[methods.zoom]\nparams = {}\n', ['[methods."zoom"]', "runs no method 'zoom'"]),
                         ('[methods.static]\nparams = { range = -1.0 }\n', ['[methods."static"] params', "range"]),
                         ('[methods.static]\nrange = 1.0\n', ['[methods."static"]', "params"])]:
        c.write_text(base + extra)
        p = _cli("campaign", c, "--out", tmp_path / "o", cwd=tmp_path)
        lines = p.stderr.strip().splitlines()
        assert p.returncode == 2 and len(lines) == 1 and all(w in lines[0] for w in words), (extra, p.stderr)
        assert not (tmp_path / "o").exists()


@pytest.mark.slow  # half a second or more on a warm cache
def test_changed_campaign_refused_and_default_folder(tmp_path):
    c = _campaign(tmp_path, 'scenario = "random.toml"\n[axes]\n"attack.seed" = [1, 2]\n', "mine.toml")
    p = _cli("campaign", c.name, "--no-progress", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    folder = tmp_path / "recordings" / "campaign-mine"
    assert len(_table(folder)) == 2
    c.write_text('scenario = "random.toml"\n[axes]\n"attack.seed" = [1, 2, 3]\n')
    p = _cli("campaign", c.name, cwd=tmp_path)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1 and "another campaign" in p.stderr


def test_seeds_rule(tmp_path):
    """An unseeded random attack (and repeat > 1) draws its seed from the campaign's seed by the
    documented rule, and every row records it; the scenario's own seed stays with repeat = 1."""
    c = _campaign(tmp_path, 'scenario = "random.toml"\nseed = 5\nrepeat = 3\n[axes]\n"method.name" = ["paper"]\n')
    runs, _ = cmp.plan(cmp.parse(c))
    assert [r.seeds["seeds.attack"] for r in runs] == [cmp.derived_seed(5, "attack.seed", {"method.name": "paper"}, r)
                                                       for r in range(3)]
    assert len({r.seeds["seeds.attack"] for r in runs}) == 3
    import hashlib

    doc = json.dumps([5, "attack.seed", [["method.name", "paper"]], 1], sort_keys=True, separators=(",", ":"))
    assert runs[1].seeds["seeds.attack"] == int.from_bytes(hashlib.sha256(doc.encode()).digest()[:8], "big") % 2**31
    assert f"seed = {runs[1].seeds['seeds.attack']}" in runs[1].text
    (tmp_path / "seeded.toml").write_text(RANDOM_SCENARIO.replace('rho_D = 0.3', 'rho_D = 0.3\nseed = 42'))
    c.write_text('scenario = "seeded.toml"\nseed = 5\n[axes]\n"method.name" = ["paper", "zoom"]\n')
    runs, notes = cmp.plan(cmp.parse(c))
    assert [r.seeds["seeds.attack"] for r in runs] == [42, 42]
    assert notes == ["method 'zoom' ignores [quantizer] mode of this scenario"]  # the one swap note (testbed.scenario.methodswap)


@pytest.mark.slow
def test_sigkill_and_resume_every_run_once(tmp_path):
    """SIGKILL of a 300-run campaign (its process group) at moments drawn from a fixed seed, four times, then
    the same command to the end: every run exactly once, and the table equals an uninterrupted run's."""
    c = _campaign(tmp_path, CAMPAIGN_120.format(seeds=", ".join(str(s) for s in range(150))))
    (tmp_path / "random.toml").write_text(RANDOM_SCENARIO.replace("duration = 8.0", "duration = 30.0"))
    journal_path = tmp_path / "out" / cmp_folder.JOURNAL
    # the moments count from the first run this process journals (start-up time varies with the machine's load)
    moments = np.random.default_rng(2027).uniform(0.0, 1.2, size=4)
    killed = 0
    for t in moments:
        size0 = journal_path.stat().st_size if journal_path.exists() else 0
        p = subprocess.Popen(tb_cmd("campaign", str(c), "--out", "out", "--workers", "2", "--no-progress"), cwd=tmp_path,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                             start_new_session=True)
        t0 = time.monotonic()
        while p.poll() is None and time.monotonic() - t0 < 120:
            if journal_path.exists() and journal_path.stat().st_size > size0:
                break
            time.sleep(0.02)
        time.sleep(float(t))
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            killed += 1
        p.wait(timeout=60)
    assert killed >= 2
    journal = [json.loads(x) for x in (tmp_path / "out" / "journal.jsonl").read_text().splitlines() if x.strip()]
    assert len({r["run"] for r in journal}) == len(journal)  # no run journaled twice
    p = _cli("campaign", c, "--out", "out", "--workers", 2, "--json", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    rows = _table(tmp_path / "out")
    assert sorted(r["run"] for r in rows) == sorted({r["run"] for r in rows}) and len(rows) == 300
    journal = [json.loads(x) for x in (tmp_path / "out" / "journal.jsonl").read_text().splitlines()]
    assert len(journal) == 300 == len({r["run"] for r in journal})
    p = _cli("campaign", c, "--out", "fresh", "--workers", 1, "--no-progress", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert _strip(_table(tmp_path / "fresh")) == _strip(rows)


def test_journal_cut_mid_line(tmp_path):
    """A kill in the middle of a journal line: that line is dropped and cut off, the others stay."""
    (tmp_path / cmp_folder.JOURNAL).write_text('{"run": "p00000r0", "status": "ok"}\n{"run": "p00001r0", "sta')
    rows = cmp_folder.read_journal(tmp_path)
    assert list(rows) == ["p00000r0"]
    assert (tmp_path / cmp_folder.JOURNAL).read_text() == '{"run": "p00000r0", "status": "ok"}\n'


@pytest.mark.slow  # half a second or more on a warm cache
def test_a_crashed_run_is_a_failed_row_and_exit_1(tmp_path):
    """A run that raises is a failed row (the others are results); a failed run is run again on resume."""
    c = _campaign(tmp_path, 'scenario = "random.toml"\n[axes]\n"attack.seed" = [1, 2]\n')
    runs, _ = cmp.plan(cmp.parse(c))
    rows = cmp_rows.simulate_runs([(runs[0].id, runs[0].text, "x", ""), ("p9", "not toml [", "x", "")])
    assert rows[0]["status"] == "ok" and rows[1]["status"] == "failed" and "TOML" in rows[1]["error"]
    # exit code of a campaign with a failed row
    c.write_text('scenario = "random.toml"\n[axes]\n"attack.seed" = [1]\n')
    out = campaignrun.run(cmp.parse(c), tmp_path / "o", progress=False)
    assert out["summary"]["failed"] == 0
    j = tmp_path / "o" / cmp_folder.JOURNAL
    j.write_text(j.read_text().replace('"status": "ok"', '"status": "failed"'))
    out = campaignrun.run(cmp.parse(c), tmp_path / "o", progress=False)  # a failed run is run again
    assert out["ran"] == 1 and out["summary"]["failed"] == 0 and len(out["rows"]) == 1


@pytest.mark.process
def test_dask_gives_the_identical_table(c120):
    """The 120-run campaign on a local Dask cluster (2 worker processes): the same table."""
    import logging

    from failclosed import import_or_require

    distributed = import_or_require("distributed", "dask")
    d, _ = c120
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                  env={"NUMBA_NUM_THREADS": "1"}, silence_logs=logging.ERROR) as cl:
        p = _cli("campaign", "c.toml", "--out", "dask", "--scheduler", cl.scheduler_address, "--json", cwd=d)
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)["parallel"]["kind"] == "dask"
    assert _strip(_table(d / "dask")) == _strip(_table(d / "out"))


@pytest.mark.slow
def test_plot(c120, tmp_path):
    d, _ = c120
    c = cmp.parse(d / "c.toml")
    s = json.loads((d / "out" / "summary.json").read_text())
    png = campaignrun.plot(tmp_path / "rate.png", c, dict(s, folder=str(d / "out")))
    assert png.stat().st_size > 1000


# ============================================================================ live
LIVE_CAMPAIGN = """\
scenario = "paper"
runs = "live"
[axes]
"method.name" = ["paper", "zoom"]
"plant.x0" = [[0.1, 0.1], [0.1, -0.1]]
"run.duration" = [2.0]
"""


@pytest.mark.process
def test_live_campaign_four_runs_recorded_and_resimulated(tmp_path):
    """4 short live runs, one at a time, each recorded; --verify re-simulates each from its recording; each
    run equals the simulator of its scenario bit for bit (the live tests' rerun policy: a campaign whose run
    reports a stall of the machine is run again)."""
    from failclosed import rerun_while_stalled, stalled
    from helpers.live import BIT_EXACT_KEYS, mismatch

    from testbed.runs.report import report

    c = tmp_path / "live.toml"
    c.write_text(LIVE_CAMPAIGN)

    def run(attempt):
        p = _cli("campaign", c, "--out", f"out{attempt}", "--json", cwd=tmp_path, timeout=600)
        assert p.returncode == 0, p.stderr
        reps = [report(str(tmp_path / f"out{attempt}" / r["recording"]), resimulate=0)
                for r in _table(tmp_path / f"out{attempt}")]
        bad = [s for s in reps if stalled(s)]
        return p.returncode, (bad or reps)[0], (attempt, reps)

    _, _, (attempt, reps) = rerun_while_stalled(run, "live campaign")
    out = tmp_path / f"out{attempt}"
    rows = _table(out)
    assert len(rows) == 4 and all(r["status"] == "ok" and (out / r["recording"]).is_file() for r in rows)
    assert all(json.loads(r["timing"]) for r in rows)
    for r, s in zip(rows, reps):
        sim = json.loads(_cli("simulate", out / "scenarios" / f"{r['run']}.toml", "--json", cwd=tmp_path).stdout)
        for k in BIT_EXACT_KEYS:
            assert s[k] == sim[k], (r["run"], mismatch(s, sim, k))
        assert r["converged"] == sim["converged"] and r["final_norm"] == sim["final_norm"]
    p = _cli("campaign", "--verify", out, "--json", cwd=tmp_path)
    assert p.returncode == 0, p.stdout + p.stderr
    v = json.loads(p.stdout)
    assert v["checked_live"] == 4 and v["identical"]


@pytest.mark.slow  # half a second or more on a warm cache
def test_batch_kernel_rows_equal_per_sample_rows(tmp_path):
    """Every bundled method, converging, escaping and diverging runs: the rows the batch kernel gives equal
    the per-sample simulator's (testbed simulate's) bit for bit, in every outcome column and settle_samples."""
    from testbed import methods

    names = list(methods.names())
    c = _campaign(tmp_path, 'scenario = "random.toml"\nseed = 3\n[axes]\n'
                            f'"method.name" = {json.dumps(names)}\n"attack.seed" = [1, 2]\n'
                            '"plant.x0" = [[0.1, 0.1], [0.3, 0.3], [-0.6, 0.6]]\n"quantizer.E0" = [0.6]\n'
                            '"quantizer.allow_x0_outside" = [true]\n"run.duration" = [30.0]\n')
    runs, _ = cmp.plan(cmp.parse(c))
    items = [(r.id, r.text, r.name, r.base_dir) for r in runs]
    batch = cmp_rows.simulate_runs(items)
    single = cmp_rows.simulate_runs(items, batch=False)
    assert sum(r["simulator"] == "batch" for r in batch) >= len(runs) // 2
    assert all(r["simulator"] == "per-sample" for r in single)
    assert len({r["converged"] for r in single}) == 2 and any(r["escaped"] for r in single)
    for a, b in zip(batch, single):
        assert a["status"] == b["status"] == "ok", (a, b)
        for k in (*cmp.OUTCOME_KEYS, "settle_samples"):
            assert a[k] == b[k], (a["run"], a["method"], k, a[k], b[k])
    assert any(r["settle_samples"] is not None for r in single) and any(r["settle_samples"] is None for r in single)


@pytest.mark.slow  # end to end: campaigns in their own processes
def test_a_users_method_runs_per_sample_and_a_crash_is_exit_1(tmp_path):
    """A user's method (docs/examples/mymethod.py) has no batch kernel: its runs go through the per-sample
    simulator and equal testbed simulate --json; a run that raises (a method whose codebook fails for one
    parameter value) is a failed row with its error, the others are results, and the exit code is 1."""
    import shutil

    shutil.copy(ROOT / "docs" / "examples" / "mymethod.py", tmp_path / "mymethod.py")
    shutil.copy(ROOT / "docs" / "examples" / "mymethod.toml", tmp_path / "mymethod.toml")
    (tmp_path / "crashy.py").write_text(
        "from mymethod import CenteredZoom\n\n\n"
        "class Crashy(CenteredZoom):\n"
        "    defaults = {'a': 0.96}\n\n"
        "    def codebook(self, n, qp):\n"
        "        if self.params['a'] < 0.9:\n"
        "            raise RuntimeError('no codebook below a = 0.9')\n"
        "        return super().codebook(n, qp)\n")

    def campaign(out: str, axes: str):
        """The campaign of mymethod.toml over ``axes`` (TOML lines) in ``tmp_path/out``: (process, rows or None)."""
        (tmp_path / f"{out}.toml").write_text(f'scenario = "mymethod.toml"\n[axes]\n{axes}"run.duration" = [6.0]\n')
        p = _cli("campaign", f"{out}.toml", "--out", out, "--workers", 1, "--json", cwd=tmp_path)
        return p, _table(tmp_path / out) if (tmp_path / out / "runs.parquet").exists() else None

    p, rows = campaign("o", '"method.params.a" = [0.96, 0.92]\n')
    assert p.returncode == 0, p.stderr
    assert [r["simulator"] for r in rows] == ["per-sample", "per-sample"]
    for r in rows:
        s = json.loads(_cli("simulate", tmp_path / "o" / "scenarios" / f"{r['run']}.toml", "--json",
                            cwd=tmp_path).stdout)
        assert all(r[k] == s[k] for k in cmp.OUTCOME_KEYS)
    assert rows[0]["final_norm"] != rows[1]["final_norm"]
    p, rows = campaign("o2", '"method.name" = ["crashy:Crashy"]\n"method.params.a" = [0.96, 0.8]\n')
    assert p.returncode == 1, p.stderr
    assert [r["status"] for r in rows] == ["ok", "failed"]
    assert "no codebook below a = 0.9" in rows[1]["error"] and rows[1]["converged"] is None
    assert json.loads(p.stdout)["summary"]["failed"] == 1


@pytest.mark.slow  # end to end: campaigns of a user's method in their own processes
def test_a_campaign_with_a_users_method_reruns_from_its_folder_alone(tmp_path):
    """The folder stores the method's module (manifest: source and sha256; a copy beside the scenarios):
    from another folder, with only the project root on PYTHONPATH, `testbed simulate DIR/scenarios/RUN.toml`
    repeats a row, and `--verify DIR` reruns every row from the stored source only with --trust-code
    (never importing the folder's copy: a copy with a side effect at import is named, and runs nothing);
    a row whose re-run fails says why (the exception), not "re-run None"."""
    import hashlib
    import shutil

    import testbed

    src = tmp_path / "methoddir"
    src.mkdir()
    for f in ("mymethod.py", "mymethod.toml"):
        shutil.copy(ROOT / "docs" / "examples" / f, src / f)
    (src / "c.toml").write_text('scenario = "mymethod.toml"\n[axes]\n"method.name" = ["mymethod:CenteredZoom", '
                                '"paper"]\n"plant.x0" = [[0.1, 0.1], [0.2, -0.1]]\n"run.duration" = [4.0]\n')
    p = _cli("campaign", "c.toml", "--out", tmp_path / "out", "--workers", 1, "--no-progress", cwd=src)
    assert p.returncode == 0, p.stderr
    out = tmp_path / "out"
    man = json.loads((out / "manifest.json").read_text())
    text = (src / "mymethod.py").read_text()
    assert man["code"] == [{"kind": "method", "ref": "mymethod:CenteredZoom", "module": "mymethod",
                            "class": "CenteredZoom", "sha256": hashlib.sha256(text.encode()).hexdigest(),
                            "source": text, "copy": "scenarios/mymethod.py"}]
    assert (out / "scenarios" / "mymethod.py").read_text() == text
    (src / "mymethod.py").write_text(text + "\n# edited\n")  # resuming with another module is refused
    p = _cli("campaign", "c.toml", "--out", out, "--no-progress", cwd=src)
    errs = [ln for ln in p.stderr.strip().splitlines() if ": note: " not in ln]
    assert p.returncode == 2 and len(errs) == 1, p.stderr
    assert "method 'mymethod:CenteredZoom' changed since the campaign started" in errs[0]
    shutil.rmtree(src)  # the method's folder gone
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {"PYTHONPATH": str(Path(testbed.__file__).resolve().parents[1])}
    rows = {r["run"]: r for r in _table(out)}
    run = next(r for r in rows.values() if r["method"] == "mymethod:CenteredZoom")["run"]
    p = _cli("simulate", out / "scenarios" / f"{run}.toml", "--json", cwd=elsewhere, env=env)
    assert p.returncode == 0, p.stderr
    assert all(json.loads(p.stdout)[k] == rows[run][k] for k in cmp.OUTCOME_KEYS)
    p = _cli("campaign", "--verify", out, cwd=elsewhere, env=env)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1 and "--trust-code" in p.stderr, p.stderr
    assert "mymethod:CenteredZoom" in p.stderr
    p = _cli("campaign", "--verify", out, "--trust-code", "--json", cwd=elsewhere, env=env)
    assert p.returncode == 0, p.stdout + p.stderr
    v = json.loads(p.stdout)
    assert v["identical"] and v["checked_simulated"] == 4 and not v["differences"]
    # a copy beside the scenarios that is not the stored module (and writes a file when imported)
    flag = tmp_path / "imported"
    (out / "scenarios" / "mymethod.py").write_text(text + f"\nopen({str(flag)!r}, 'w').close()\n")
    for cwd in (elsewhere, out / "scenarios"):
        p = _cli("campaign", "--verify", out, "--trust-code", cwd=cwd, env=env)
        assert p.returncode == 1 and "PROBLEM: scenarios/mymethod.py: differs from the manifest's sha256" in p.stdout
        assert "DIFFERS" not in p.stdout and not flag.exists(), p.stdout
    (out / "scenarios" / "mymethod.py").write_text(text)
    # a folder whose manifest stores no code (as before): each row says why its re-run failed
    man.pop("code")
    (out / "manifest.json").write_text(json.dumps(man))
    p = _cli("campaign", "--verify", out, cwd=elsewhere, env=env)
    differs = [ln for ln in p.stdout.splitlines() if "DIFFERS" in ln]
    assert p.returncode == 1 and len(differs) == 2, p.stdout
    assert all("the re-run failed: " in ln and "method 'mymethod:CenteredZoom': no module 'mymethod'" in ln
               for ln in differs), differs


@pytest.mark.process
def test_live_campaign_on_dask_brings_the_recordings_back(tmp_path):
    """runs = "live" with --scheduler: each run on a Dask worker (one at a time per host: a LocalCluster's
    two workers share this host), its recording sent back into the folder; --verify re-simulates them."""
    import logging

    from failclosed import import_or_require

    distributed = import_or_require("distributed", "dask")
    (tmp_path / "c.toml").write_text('scenario = "paper"\nruns = "live"\n[axes]\n"method.name" = ["paper", "zoom"]\n'
                                     '"run.duration" = [1.5]\n')
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                  silence_logs=logging.ERROR) as cl:
        p = _cli("campaign", "c.toml", "--out", "o", "--scheduler", cl.scheduler_address, "--json", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    rows = _table(tmp_path / "o")
    assert [r["status"] for r in rows] == ["ok", "ok"]
    assert all((tmp_path / "o" / r["recording"]).stat().st_size > 1000 for r in rows)
    p = _cli("campaign", "--verify", "o", "--json", cwd=tmp_path)
    assert p.returncode == 0, p.stdout + p.stderr
    assert json.loads(p.stdout)["checked_live"] == 2


@pytest.mark.slow  # half a second or more on a warm cache
def test_the_slurm_example_renders_the_job_script_it_describes():
    """docs/campaigns.md's SLURM cluster, made as written (its scheduler on a free port, nothing
    submitted): the job script asks for what the page says."""
    import ast
    import re

    from failclosed import import_or_require

    jobqueue = import_or_require("dask_jobqueue", "dask")
    page = (Path(__file__).resolve().parents[2] / "docs" / "campaigns.md").read_text()
    m = re.search(r"cluster = SLURMCluster\((.*?)\n\)\n", page, re.S)
    assert m, "docs/campaigns.md has no 'cluster = SLURMCluster(...)' example"
    call = ast.parse(f"f({m.group(1)})", mode="eval").body
    kwargs = {k.arg: ast.literal_eval(k.value) for k in call.keywords}
    assert kwargs["scheduler_options"]["port"] == 8786
    kwargs["scheduler_options"] = dict(kwargs["scheduler_options"], port=0)  # a free port here
    cluster = jobqueue.SLURMCluster(**kwargs)
    try:
        script = cluster.job_script()
    finally:
        cluster.close()
    assert "#SBATCH --cpus-per-task=8" in script and "#SBATCH -t 02:00:00" in script, script
    assert "source ~/testbed/.venv/bin/activate" in script and "export NUMBA_NUM_THREADS=1" in script, script
    assert "--nworkers 8" in script and "--nthreads 1" in script, script  # one thread per worker process


@pytest.mark.slow  # seconds: a campaign's runs
def test_rows_count_the_lost_samples_by_cause(tmp_path):
    """``losses``: a campaign over a symbol link with and without losses: each row's causes add up to
    ``samples_lost`` and equal ``testbed simulate --json`` of its scenario (the batch kernel's rows:
    ``test_batch_kernel_rows_equal_per_sample_rows`` and the 120 runs compare every outcome key)."""
    (tmp_path / "random.toml").write_text(RANDOM_SCENARIO.replace("[run]", "[network]\nseed = 3\n\n[run]"))
    (tmp_path / "c.toml").write_text('scenario = "random.toml"\nruns = "simulated"\nseed = 1\n[axes]\n'
                                     '"network.symbol" = [{ loss = 0.0 }, { loss = 0.2 }]\n"attack.seed" = [1, 2]\n')
    p = _cli("campaign", "c.toml", "--out", "o", "--workers", 1, "--json", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    rows = _table(tmp_path / "o")
    assert len(rows) == 4 and all(r["status"] == "ok" for r in rows)
    for r in rows:
        ls = r["losses"]
        assert tuple(ls) == LOSS_KINDS and sum(ls.values()) == r["samples_lost"], r
        s = json.loads(_cli("simulate", tmp_path / "o" / "scenarios" / f"{r['run']}.toml", "--json",
                            cwd=tmp_path).stdout)
        assert ls == s["losses"], (r["run"], ls, s["losses"])
    lossy = [r for r in rows if r["losses"]["channel"] > 0]
    assert len(lossy) == 2 and all(r["losses"]["attacker"] > 0 for r in rows)


# ============================================================================ summary, comparisons, progress
@pytest.mark.slow  # seconds: a campaign's runs
def test_summary_pairs_the_runs_and_the_table_shows_them(tmp_path):
    """The summary's paired comparison of two methods equals the one counted here from the rows paired by
    seed; every group tells converged, bounded and escaped apart; --table prints it as Markdown and LaTeX.
    Without an axis of seeds and with repeat = 2 the methods face other attacks: no pairs, said so."""
    import math
    import statistics

    from testbed.campaign import tables

    c = _campaign(tmp_path, 'scenario = "random.toml"\nseed = 4\n[axes]\n"method.name" = ["paper", "zoom"]\n'
                            '"attack.seed" = [0, 1, 2, 3, 4, 5]\n"plant.x0" = [[0.1, 0.1], [0.3, 0.3]]\n'
                            '"quantizer.E0" = [0.6]\n"quantizer.allow_x0_outside" = [true]\n"run.duration" = [30.0]\n')
    out = campaignrun.run(cmp.parse(c), tmp_path / "o", progress=False)
    s, rows = out["summary"], out["rows"]
    for g in [s["total"], *s["by_axis"]["method.name"], *s["points"]]:
        assert g["converged"] + g["bounded"] + g["escaped"] == g["n"]
    assert any(r["escaped"] for r in rows) and any(r["converged"] for r in rows)
    assert set(s["comparisons"]) == {"method.name", "plant.x0"}  # not the seeds
    comp = s["comparisons"]["method.name"]
    assert comp["reference"] == "paper" and len(comp["values"]) == 1
    d = comp["values"][0]
    by = {(r["method.name"], r["attack.seed"], json.dumps(r["plant.x0"])): r for r in rows}
    keys = [(s_, x) for (m, s_, x) in by if m == "zoom"]
    a_only = sum(1 for k in keys if by[("zoom", *k)]["converged"] and not by[("paper", *k)]["converged"])
    b_only = sum(1 for k in keys if by[("paper", *k)]["converged"] and not by[("zoom", *k)]["converged"])
    pd = d["paired_difference"]
    assert (d["pairs"], d["unpaired"], pd["a_only"], pd["b_only"]) == (12, 0, a_only, b_only)
    m = a_only + b_only
    p = 1.0 if m == 0 else min(1.0, 2 * sum(math.comb(m, i) for i in range(min(a_only, b_only) + 1)) / 2 ** m)
    assert pd["mcnemar_p"] == pytest.approx(p) and pd["difference"] == pytest.approx((a_only - b_only) / 12)
    mx = d["paired_continuous"]["max_norm"]
    assert mx["median_difference"] == pytest.approx(statistics.median(
        by[("zoom", *k)]["max_norm"] - by[("paper", *k)]["max_norm"] for k in keys))
    assert mx["ci95"][0] <= mx["median_difference"] <= mx["ci95"][1]
    on_disk = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert on_disk["comparisons"] == json.loads(json.dumps(s["comparisons"]))
    assert "## Paired comparisons" in (tmp_path / "o" / "summary.md").read_text()
    md = tables.markdown(s)
    assert "| zoom | 12 | " in md and "| paper (reference) | 12 | " in md and "Newcombe" in md
    tex = tables.latex(s, "c")
    assert tex.count(r"\begin{tabular}") == 2 and r"\label{tab:c-method-name}" in tex and "zoom & 12 &" in tex
    p = _cli("campaign", c, "--out", tmp_path / "o", "--table", "markdown", "--no-progress", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert p.stdout == md
    p = _cli("campaign", c, "--out", tmp_path / "o", "--table", "latex", "--json", cwd=tmp_path)
    assert p.returncode == 2 and "--json or --table" in p.stderr
    # other seeds per method (derived from the axis values): nothing to pair, and the summary says it
    c2 = _campaign(tmp_path, 'scenario = "random.toml"\nrepeat = 2\n[axes]\n"method.name" = ["paper", "zoom"]\n',
                   name="c2.toml")
    s2 = campaignrun.run(cmp.parse(c2), tmp_path / "o2", progress=False)["summary"]
    d2 = s2["comparisons"]["method.name"]["values"][0]
    assert (d2["pairs"], d2["unpaired"]) == (0, 2)
    assert d2["paired_difference"]["difference"] is None and d2["paired_continuous"]["max_norm"]["wilcoxon_p"] is None
    assert "| zoom | 2 |" in tables.markdown(s2)


def test_progress_estimates_from_the_runs_after_the_first():
    """The first run pays the kernels' loading or compiling: the estimate of the time left starts at its
    end, and is known only once another run has ended."""
    p = campaignrun.Progress(10, 0, enabled=False)
    assert p.eta(0, 5.0) is None
    p(1, 0)  # the first run ended
    t1, d1 = p.clock
    assert d1 == 1 and p.eta(1, t1 + 50.0) is None
    assert p.eta(3, t1 + 2.0) == pytest.approx(1.0 * 7)   # 2 runs in 2 s after the first: 7 left, 7 s
    q = campaignrun.Progress(10, 4, enabled=False)         # resumed: 4 found done
    q(4, 0)
    assert q.clock is None                                 # nothing ran yet
    q(5, 0)
    assert q.clock[1] == 5


@pytest.mark.slow
def test_ctrl_c_says_how_to_resume(tmp_path):
    """SIGINT to a running campaign (its process group, as Ctrl-C in a terminal): exit 130 and one line that
    names how many runs are stored and the command that resumes; that command finishes the campaign."""
    c = _campaign(tmp_path, CAMPAIGN_120.format(seeds=", ".join(str(s) for s in range(150))))
    (tmp_path / "random.toml").write_text(RANDOM_SCENARIO.replace("duration = 8.0", "duration = 30.0"))
    journal_path = tmp_path / "out" / cmp_folder.JOURNAL
    p = subprocess.Popen(tb_cmd("campaign", str(c), "--out", "out", "--workers", "2"), cwd=tmp_path,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    t0 = time.monotonic()
    # after a worker's first chunk (the workers are forked and busy or idle: either way they end silently)
    while p.poll() is None and time.monotonic() - t0 < 120:
        if journal_path.exists() and journal_path.read_bytes().count(b"\n") > 1:
            break
        time.sleep(0.02)
    assert p.poll() is None, p.communicate()
    os.killpg(p.pid, signal.SIGINT)
    out, err = p.communicate(timeout=120)
    assert p.returncode == 130, err
    line = [x for x in err.splitlines() if "interrupted" in x]
    assert len(line) == 1 and "Traceback" not in err, err
    stored = len(cmp_folder.read_journal(tmp_path / "out"))
    assert f"interrupted; {stored} of 300 runs are stored in out; the same command resumes: testbed campaign " \
           f"{c} --out out" in line[0]
    assert "campaign: the first run loads the simulator" in err  # the setup said what it did
    p = _cli("campaign", c, "--out", "out", "--workers", 2, "--json", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert len(_table(tmp_path / "out")) == 300
