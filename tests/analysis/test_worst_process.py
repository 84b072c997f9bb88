"""Process tier: the scenario ``testbed worst-attack --scenario-out`` writes escapes in a live ``testbed run``."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import pytest
from helpers.cli import tb_run

from testbed import scenario

pytestmark = pytest.mark.process


def test_the_worst_attack_scenario_escapes_live(tmp_path):
    from helpers.live import live_exact
    from helpers.procs import reap

    # the paper's loop over a 3 s horizon (a live run of 3 s); two attacks at most
    base = (Path(scenario.__file__).parent / "bundled" / "paper.toml").read_text()
    short = tmp_path / "paper3.toml"
    short.write_text(re.sub(r"^duration = .*$", "duration = 3.0", base, flags=re.M))
    out = tmp_path / "worst.toml"
    p = tb_run("worst-attack", short, "--attacks", "2", "--json", "--no-progress", "--no-greedy", "--scenario-out", out,
            timeout=900)
    assert p.returncode == 0, p.stderr
    d = json.loads(p.stdout)
    assert d["escaped"] and d["n_steps"] == 30 and out.exists()
    p = tb_run("simulate", out, "--json", timeout=300)
    assert p.returncode == 0, p.stderr
    sim = json.loads(p.stdout)
    assert sim["escaped"] is True
    rid = f"t{os.getpid()}xworst"
    try:
        rc, s, err = live_exact(rid, str(out))
    finally:
        assert not reap(rid)
    assert s["escaped"] is True, (rc, s.get("faults"), err[-2000:])
    assert s["escape_criterion"] == sim["escape_criterion"]
    assert s["theta"] == sim["theta"] and s["x_final"] == sim["x_final"]
