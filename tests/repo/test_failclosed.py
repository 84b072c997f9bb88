"""The suite fails closed (``tests/failclosed.py``): the capability helper, the one rerun policy, and a guard.

* ``require`` skips with the reason, or fails with it where ``TESTBED_REQUIRE`` names the capability;
* the guard: no test calls ``pytest.skip``, ``importorskip``, ``skipif`` or ``xfail`` outside the helper,
  and no test has a stall criterion or rerun loop of its own;
* the rerun policy: a stalled run is run again at most STALL_RERUNS times and the last run is returned (so a build
  that stalls every run is still compared); what an attacker can cause is no stall where an attacker is
  the subject;
* two deliberately broken builds, put in place of the live run by monkeypatching, that the suite's old
  tests passed or skipped: an outsider whose forged symbol reaches the controller (late symbols: the
  old security test read that as a stall twice and skipped), and a physical-timing loop whose u_k acts
  late in every run (the old test then compared nothing).  The real tests now fail on both.
"""

from __future__ import annotations

import ast
import json
from pathlib import Path

import pytest
from failclosed import (
    CAPABILITIES,
    REQUIRE_ENV,
    STALL_RERUNS,
    import_or_require,
    require,
    required,
    rerun_while_stalled,
    stalled,
)

HERE = Path(__file__).resolve().parents[1]  # tests/


# ---------------------------------------------------------------------------------------------- require
def test_require_skips_with_the_reason_unless_the_capability_is_required(monkeypatch):
    monkeypatch.delenv(REQUIRE_ENV, raising=False)
    with pytest.raises(pytest.skip.Exception, match="no SCHED_FIFO here"):
        require("fifo", "no SCHED_FIFO here")
    monkeypatch.setenv(REQUIRE_ENV, "npm,fifo")
    with pytest.raises(pytest.fail.Exception, match="required capability 'fifo'.*no SCHED_FIFO here"):
        require("fifo", "no SCHED_FIFO here")
    with pytest.raises(pytest.skip.Exception):
        require("netns", "not root")  # not named: still a skip
    monkeypatch.setenv(REQUIRE_ENV, "all")
    assert required() == set(CAPABILITIES)
    for cap in CAPABILITIES:
        with pytest.raises(pytest.fail.Exception, match=cap):
            require(cap, "missing")
    with pytest.raises(pytest.fail.Exception, match="cannot import no_such_module_here"):
        import_or_require("no_such_module_here", "dask")
    assert import_or_require("json", "dask") is json
    with pytest.raises(ValueError):
        require("gpu", "an unknown capability is a bug of the test")


def test_an_unknown_required_capability_is_a_usage_error(monkeypatch):
    monkeypatch.setenv(REQUIRE_ENV, "fifo,netnss")
    with pytest.raises(pytest.UsageError, match="netnss"):
        required()


# ---------------------------------------------------------------------------------------------- the guard
SKIPS = {"skip", "importorskip", "skipif", "xfail"}


def skip_calls(source: str) -> list[tuple[int, str]]:
    """(line, what) of every way a test file can skip other than ``failclosed.require``."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Attribute) and node.attr in SKIPS:
            base = ast.unparse(node.value)
            if base in ("pytest", "pytest.mark", "unittest") or base.startswith("pytest."):
                found.append((node.lineno, f"{base}.{node.attr}"))
        elif isinstance(node, ast.ImportFrom) and node.module in ("pytest", "_pytest.outcomes", "unittest"):
            found += [(node.lineno, f"from {node.module} import {a.name}") for a in node.names
                      if a.name in SKIPS | {"Skipped"}]
        elif isinstance(node, ast.Name) and node.id == "Skipped":
            found.append((node.lineno, "Skipped"))
    return found


def own_rerun_policies(source: str) -> list[tuple[int, str]]:
    """A stall criterion of a test's own (``def stalled``, ``def clock_fault``) or a count of reruns."""
    return [(n.lineno, n.name) for n in ast.walk(ast.parse(source))
            if isinstance(n, ast.FunctionDef) and n.name in ("stalled", "clock_fault")] + \
           [(n.lineno, t.id) for n in ast.walk(ast.parse(source)) if isinstance(n, ast.Assign)
            for t in n.targets if isinstance(t, ast.Name) and t.id == "STALL_RERUNS"]


def test_the_guard_sees_every_way_to_skip():
    src = ("import pytest\nfrom pytest import skip\n"
           "@pytest.mark.skipif(True, reason='x')\ndef test_a():\n    pytest.skip('x')\n"
           "def test_b():\n    pytest.importorskip('numpy')\n    pytest.xfail('y')\n"
           "def stalled(s):\n    return None\n")
    assert sorted(w for _, w in skip_calls(src)) == sorted(["from pytest import skip", "pytest.mark.skipif",
                                                            "pytest.skip", "pytest.importorskip", "pytest.xfail"])
    assert own_rerun_policies(src) == [(9, "stalled")]


@pytest.mark.slow  # half a second or more on a warm cache
def test_no_test_skips_outside_the_capability_helper_or_reruns_on_its_own():
    """Every skip of the suite goes through ``failclosed.require`` (so CI's ``TESTBED_REQUIRE`` turns it into
    a failure), and every rerun of a stalled run through ``failclosed.rerun_while_stalled``."""
    files = sorted(p for p in HERE.rglob("*.py") if p.name not in ("failclosed.py", "test_failclosed.py"))
    assert len(files) > 25
    bad = {str(p.relative_to(HERE)): f for p in files if (f := skip_calls(p.read_text()))}
    assert not bad, f"skip outside failclosed.require: {bad}"
    own = {str(p.relative_to(HERE)): f for p in files if (f := own_rerun_policies(p.read_text()))}
    assert not own, f"a rerun policy outside failclosed.py: {own}"


# ---------------------------------------------------------------------------------------------- the policy
def _runs(*summaries):
    """A ``run(attempt)`` that returns the given summaries in turn, and the attempts it was called with."""
    calls = []

    def run(attempt):
        calls.append(attempt)
        return 0, summaries[attempt], ""

    return run, calls


def test_a_stalled_run_is_run_again_at_most_STALL_RERUNS_times_and_the_last_is_returned():
    stall = {"timing": {"deadline_misses": 1}}
    run, calls = _runs(*[stall] * STALL_RERUNS, dict(stall, last=True))
    with pytest.warns(UserWarning, match="machine stalled"):
        _, s, _ = rerun_while_stalled(run, "x")
    assert calls == list(range(STALL_RERUNS + 1)) and s["last"]  # the caller compares it, stalled or not
    run, calls = _runs(stall, {"clean": True}, stall)
    with pytest.warns(UserWarning):
        assert rerun_while_stalled(run, "x")[1] == {"clean": True} and calls == [0, 1]
    run, calls = _runs({}, stall)
    assert rerun_while_stalled(run, "x")[1] == {} and calls == [0]


@pytest.mark.parametrize("summary", [{"late_symbols": 2}, {"loss_reasons": {"superseded": 1}},
                                     {"events": {"future_symbol": 1}}, {"events": {"future_actuation": 3}},
                                     {"events": {"future_sensor": 1}}])
def test_what_an_attacker_can_cause_is_no_stall_where_an_attacker_is_the_subject(summary):
    assert stalled(summary) and stalled(summary, attacker=True) is None
    run, calls = _runs(summary, summary, summary)
    assert rerun_while_stalled(run, "x", attacker=True)[1] is summary and calls == [0]


def test_machine_stalls_count_for_every_test():
    for s in ({"timing": {"deadline_misses": 1}}, {"timing": {"overruns": 2}}, {"timing": {"late_for_schedule": 1}},
              {"node_summaries": {"encoder": {"stale_sensor": 1}}}, {"events": {"ack_missing": 1}}):
        assert stalled(s) and stalled(s, attacker=True), s
    assert stalled({"events": {"ack_missing": 1}, "ack_via_attacker": True}) is None  # the attacker drops acks


# ---------------------------------------------------------------------------------------------- broken builds
def _simulated(*args) -> dict:
    from helpers.cli import tb_here

    rc, out, err = tb_here("simulate", "paper", *args, "--json")
    assert rc == 0, err
    return json.loads(out)


@pytest.mark.slow  # half a second or more on a warm cache
def test_a_broken_build_whose_outsider_gets_in_fails_the_security_test():
    """Broken build: the outsider's forged symbol for sample 30 is taken, and its later copies arrive late.
    The old test read the late symbols as a stall, ran it again, and skipped; now the run is compared.
    (The security test's verdict is ``helpers.verdicts.assert_outsider_changed_nothing``; the broken build stands
    in for its run.)"""
    from helpers.verdicts import OUTSIDER_S, assert_outsider_changed_nothing

    sim = _simulated("--duration", str(OUTSIDER_S))
    broken = dict(sim, complete=True, outcome="done", faults=[], events={}, late_symbols=4,
                  security={"authenticated": True, "topology": "router", "transport": "user/password"},
                  recording={"complete": True}, timing={"deadline_misses": 0, "overruns": 0})
    broken["symbols"] = list(sim["symbols"])
    broken["symbols"][30] = 7
    calls = []

    def outsider_run(rid, peer, foreign, more=()):
        calls.append(rid)
        return 0, broken, ""

    with pytest.raises(AssertionError, match="symbols first differs at sample 30"):
        assert_outsider_changed_nothing("tbroken", "router", outsider_run)
    assert calls == ["tbroken"]  # late symbols are the attacker's doing here: no rerun
    # a build that makes every run stall (a deadline miss in each) is run three times and still compared
    calls.clear()
    broken["timing"] = {"deadline_misses": 1, "overruns": 0}
    with pytest.warns(UserWarning, match="machine stalled"), \
            pytest.raises(AssertionError, match="symbols first differs at sample 30"):
        assert_outsider_changed_nothing("tbroken", "router", outsider_run)
    assert calls == ["tbroken" + "r" * i for i in range(STALL_RERUNS + 1)]


@pytest.mark.slow  # half a second or more on a warm cache
def test_a_broken_build_whose_u_acts_late_in_every_run_fails_the_physical_timing_test(monkeypatch):
    """Broken build: under physical timing u_k acts a little after its instant in every run (late for its
    schedule), so the loop leaves the simulator's path though it still converges and re-simulates.  The
    old test compared nothing when the last run was late; now the last run is compared.  (The test is
    ``helpers.verdicts.assert_physical_timing_on_the_paper``; the broken build stands in for its live runs.)"""
    import helpers.live
    import helpers.verdicts

    sim = _simulated("--timing", "physical", "--deadline", "0.9")  # as the test runs it
    broken = dict(sim, complete=True, outcome="done", faults=[], events={}, samples=len(sim["t"]),
                  encoder_decoder_agree_where_known=True, recording={"path": "unused.mcap", "complete": True},
                  timing={"deadline_misses": 0, "overruns": 0, "late_for_schedule": 3})
    broken["x"] = [list(x) for x in sim["x"]]
    broken["x"][100][0] += 1e-12
    calls = []
    monkeypatch.setattr(helpers.live, "live", lambda rid, *a, **k: calls.append(rid) or (0, broken, ""))
    monkeypatch.setattr(helpers.live, "reap", lambda token, wait=5.0: [])  # live_exact reaps a stalled run
    monkeypatch.setattr(helpers.verdicts, "resimulated", lambda s: {"reproduced": True, "max_state_error": 0.0,
                                                          "symbols_identical": True})
    with pytest.warns(UserWarning, match="late_for_schedule"), \
            pytest.raises(AssertionError, match="x first differs at sample 100"):
        helpers.verdicts.assert_physical_timing_on_the_paper("tbroken", ())
    assert calls == ["tbroken" + "r" * i for i in range(STALL_RERUNS + 1)]
