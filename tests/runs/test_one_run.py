"""One whole-run type (fast tier): ``testbed.open``'s ``Run`` is what ``testbed report``, ``testbed resimulate``
and the Rerun view start from, so they cannot disagree about a recording."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers.sims import sim_recording

import testbed
from testbed.runs.report import report, report_of_run, run_of
from testbed.runs.resimulate import compare, recorded_run


@pytest.mark.parametrize("name", ["paper", "paper-greedy"])
def test_report_is_the_runs_summary_plus_its_own_sections(tmp_path, name):
    """Every key of ``Run.summary`` is in the report with the same value; the report's ``dos`` is priced from
    the Run's ``attack_on`` (the attacker's log); its saturations are the Run's events."""
    from attackers.schedule import Schedule

    sc, res, path = sim_recording(tmp_path, name)
    run = testbed.open(path)
    rep = report(path, resimulate=0)
    plain = json.loads(json.dumps(rep))
    for key, value in run.summary.items():
        if key == "t0_ns":  # the one key of Run.summary the report does not print
            continue
        got = json.loads(json.dumps(value, default=lambda a: a.tolist()))
        assert got == plain[key], key
    logged = Schedule.from_theta(run.arrays["attack_on"].astype(np.uint8), sc.T)
    assert rep["dos"]["logged_intervals"] == [list(iv) for iv in logged.intervals]
    assert rep["saturation_events"] == [e["k"] for e in run.events if e["kind"] == "saturation"]
    # the report's own Run (the fields the report reads) has the same arrays as testbed.open's, but q_k at the
    # encoder, which the report does not read
    own = run_of(str(path))
    for key, a in run.arrays.items():
        if key != "q_enc":
            assert np.array_equal(own.arrays[key], a, equal_nan=a.dtype.kind == "f"), key
    assert report_of_run(own, resimulate=0)["dos"] == rep["dos"]


def test_resimulation_reads_the_runs_arrays(tmp_path):
    """``recorded_run`` takes what a recording says happened from a Run; testbed.open's Run reproduces bit for bit,
    and a changed value in its arrays is found at its sample."""
    _sc, _res, path = sim_recording(tmp_path, "paper")
    run = testbed.open(path)
    ok = compare(recorded_run(run))
    assert ok["reproduced"] and ok["verdict"] == "reproduced bit for bit" and ok["checked"] == run.N
    run.arrays["E"] = run.arrays["E"].copy()
    run.arrays["E"][57] *= 2
    bad = compare(recorded_run(run))
    assert not bad["reproduced"] and bad["first_divergence"] == 57 and not bad["E_identical"]


@pytest.mark.parametrize("plant", ["model", "recorded"])
def test_a_limited_resimulation_keeps_only_what_it_checks_and_says_the_same(tmp_path, plant):
    """``recorded_run(run, limit)`` keeps the compared values of samples 0 .. limit only (a report of a long
    recording holds a dozen per-sample columns fewer), and ``compare`` says exactly what it says from the
    whole record: a divergence inside the limit found at its sample, one past it unseen, the replay's counts
    the whole run's."""
    _sc, _res, path = sim_recording(tmp_path, "paper")
    run = testbed.open(path)
    limit = 40
    short = recorded_run(run, limit)
    assert all(v is None or len(v) == limit + 1 for v in short["live"].values())
    assert short["N"] == run.N and len(short["replay"].reason) == run.N
    assert compare(short, limit=limit, plant=plant) == compare(recorded_run(run), limit=limit, plant=plant)
    for k, found in ((limit - 3, True), (limit + 5, False)):
        run.arrays["E"] = run.arrays["E"].copy()
        run.arrays["E"][k] *= 2
        got = compare(recorded_run(run, limit), limit=limit, plant=plant)
        assert got == compare(recorded_run(run), limit=limit, plant=plant)
        assert got["reproduced"] is not found and (got["first_divergence"] == k) is found
        run.arrays["E"][k] /= 2
