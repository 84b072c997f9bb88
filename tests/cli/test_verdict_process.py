"""One verdict per question in live runs (issue 35 items 3 and 4), process tier.

* a live run's escape verdict is the simulator's and its recording's (``testbed run``, ``report``,
  ``testbed.open``) for a bundled baseline and a user's method;
* a method whose ends break lockstep: a fault at its first sample, one stderr line, exit 1;
* a method that raises in ``control()``: the run ends with a method fault at that sample (exit 1, one
  stderr line), ``method_fault`` and ``method_fault_at`` the same in the run's summary, its report and
  ``testbed.open``, no loss invented, and the re-simulation reproduces the run up to the fault.

The simulated counterparts are in ``tests/cli/test_verdict.py``.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
from pathlib import Path

import helpers.cli
import helpers.live
import helpers.procs
import pytest
from helpers.faulty_method import FAULTY

pytestmark = pytest.mark.process

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "docs" / "examples"



def tb(*args, cwd):
    return helpers.cli.tb(*args, cwd=cwd, env={"MPLBACKEND": "Agg"})


def _live(tmp_path, scenario, rid, *more, cwd):
    try:
        rc, out, err = tb("run", scenario, "--json", "--run-id", rid, "--run-dir", tmp_path / f"logs-{rid}", *more,
                          cwd=cwd)
    finally:
        assert not helpers.procs.reap(rid)
    try:
        return rc, json.loads(out), err
    except json.JSONDecodeError:
        pytest.fail(f"no JSON summary (exit {rc})\nstdout: {out[-2000:]}\nstderr: {err[-3000:]}")


def _lines(err: str) -> list[str]:
    """stderr of testbed run without its notes."""
    return [ln for ln in err.splitlines() if ln.startswith("testbed run:") and "note:" not in ln
            and "INSECURE" not in ln]


@pytest.mark.parametrize("scenario, method", [("paper", "unquantized"), ("mymethod.toml", None)])
def test_live_escape_verdict_is_the_simulators_and_the_recordings(tmp_path, scenario, method):
    from failclosed import rerun_flags, rerun_while_stalled

    for f in ("mymethod.py", "mymethod.toml"):
        shutil.copy(EXAMPLES / f, tmp_path / f)
    over = ("--duration", "4") + (("--method", method) if method else ())
    rid = f"t{os.getpid()}xverdict{secrets.token_hex(3)}"
    rec = tmp_path / "live.mcap"

    def attempt(n):
        return _live(tmp_path, scenario, rid + "r" * n, *over, "--out", rec, *(("--force",) if n else ()),
                     *rerun_flags(n), cwd=tmp_path)

    rc, s, err = rerun_while_stalled(attempt, f"{scenario} {method}")
    assert rc == 0, (s.get("faults"), err[-2000:])
    rc, out, err = tb("simulate", scenario, *over, "--json", cwd=tmp_path)
    assert rc == 0, err
    sim = json.loads(out)
    assert s["final_norm"] == sim["final_norm"], helpers.live.mismatch(s, sim, "final_norm")
    rc, out, err = tb("report", rec, "--json", cwd=tmp_path)
    assert rc == 0, err
    rep = json.loads(out)
    assert s["escaped"] == sim["escaped"] == rep["escaped"], (s["escaped"], sim["escaped"], rep["escaped"])
    verdict = "ESCAPED" if sim["escaped"] else ("converged" if sim["converged"] else "not converged")
    rc, out, err = tb("report", rec, cwd=tmp_path)
    assert f"-> {verdict}" in out


def _faulty_dir(tmp_path, raise_at=-1, drift=0.0) -> Path:
    (tmp_path / "faultymeth.py").write_text(FAULTY.format(raise_at=raise_at, drift=drift))
    (tmp_path / "s.toml").write_text((ROOT / "testbed" / "scenario" / "bundled" / "paper.toml").read_text())
    return tmp_path


def test_live_lockstep_break_is_a_fault_at_its_sample(tmp_path):
    d = _faulty_dir(tmp_path, drift=1.0)
    rid = f"t{os.getpid()}xlockstep{secrets.token_hex(3)}"
    rc, s, err = _live(d, d / "s.toml", rid, "--duration", "3", "--method", "faultymeth:Faulty", "--out",
                       d / "r.mcap", cwd=d)
    assert rc == 1, (s.get("faults"), err[-2000:])
    n = len(s["lockstep_breaks"])
    assert _lines(err) == ["testbed run: method 'faultymeth:Faulty' broke lockstep: its encoder and decoder disagree "
                           f"from sample 1 ({n} samples)"], err
    f = [f for f in s["faults"] if f["kind"] == "lockstep_break"]
    assert len(f) == 1 and f[0]["at_sample"] == 1
    assert s["lockstep_breaks"][0] == 1 and n > 20 and s["encoder_decoder_agree"] is False
    rc, out, err = tb("simulate", d / "s.toml", "--duration", "3", "--method", "faultymeth:Faulty", "--json", cwd=d)
    assert rc == 1 and json.loads(out)["lockstep_breaks"][0] == 1
    rc, out, err = tb("report", d / "r.mcap", "--json", cwd=d)
    rep = json.loads(out)
    assert rep["lockstep_breaks"] == s["lockstep_breaks"]
    assert any(e["kind"] == "run_lockstep_break" and e["k"] == 1 for e in rep["event_log"]), rep["event_log"]


def test_live_raise_ends_the_run_with_a_method_fault_at_its_sample(tmp_path):
    from failclosed import rerun_flags, rerun_while_stalled

    d = _faulty_dir(tmp_path, raise_at=40)
    rid = f"t{os.getpid()}xraise{secrets.token_hex(3)}"

    def attempt(n):
        return _live(d, d / "s.toml", rid + "r" * n, "--duration", "8", "--method", "faultymeth:Faulty", "--out",
                     d / "r.mcap", *(("--force",) if n else ()), *rerun_flags(n), cwd=d)

    rc, s, err = rerun_while_stalled(attempt, "method that raises")
    line = "method 'Faulty' raised at sample 40: ZeroDivisionError: boom"
    assert rc == 1, (s.get("faults"), err[-2000:])
    assert _lines(err) == [f"testbed run: {line}"], err
    assert s["outcome"] == "method fault at sample 40" and s["samples"] == 40 and not s["complete"]
    assert (s["method_fault"], s["method_fault_at"], s["diverged_at"]) == (line, 40, 40)
    assert [f["kind"] for f in s["faults"]] == ["method_fault"] and s["faults"][0]["at_sample"] == 40
    rc, out, err = tb("simulate", d / "s.toml", "--duration", "8", "--method", "faultymeth:Faulty", "--json", cwd=d)
    assert rc == 1
    sim = json.loads(out)
    for key in ("method_fault", "method_fault_at", "theta", "x", "x_final", "losses", "samples_lost", "escaped"):
        assert s[key] == sim[key], helpers.live.mismatch(s, sim, key)
    assert s["losses"]["channel"] == 0 and sum(s["losses"].values()) == s["samples_lost"]
    rc, out, err = tb("report", d / "r.mcap", "--json", cwd=d)
    assert rc == 0, err
    rep = json.loads(out)
    assert (rep["method_fault"], rep["method_fault_at"], rep["samples"]) == (line, 40, 40)
    assert rep["losses"] == s["losses"]
    assert rep["resimulation"]["reproduced"] is True
    assert "up to the method fault at sample 40" in rep["resimulation"]["verdict"]
    rc, out, err = tb("resimulate", d / "r.mcap", cwd=d)
    assert rc == 0 and "reproduced bit for bit up to the method fault at sample 40" in out, (out, err)
    rc, out, err = tb("report", d / "r.mcap", cwd=d)
    assert "METHOD FAULT at sample 40" in out and "-1" not in out.split("METHOD FAULT")[1].splitlines()[0]
