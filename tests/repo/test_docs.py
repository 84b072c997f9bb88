"""The docs: numbers that cannot go stale, links that lead somewhere, the README's tour as written."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
from pathlib import Path

import pytest
from helpers.cli import PY

ROOT = Path(__file__).resolve().parents[2]


def _pages() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def test_the_readme_is_a_short_front_door():
    text = (ROOT / "README.md").read_text()
    lines = text.splitlines()
    assert len(lines) <= 300
    first60 = "\n".join(lines[:60])
    assert "pip install -e '.[test]'" in first60 and "python -m pytest" in first60


def test_every_relative_link_of_the_docs_leads_to_a_file():
    link = re.compile(r"\]\(([^)#\s]+)(#[^)]*)?\)")
    for page in _pages():
        for target, _anchor in link.findall(page.read_text()):
            if "://" in target:
                continue
            assert (page.parent / target).exists(), f"{page.name}: {target}"


def test_the_numbers_markers_are_well_formed():
    for page in _pages():
        text = page.read_text()
        assert text.count("<!--n:") == text.count("<!--/n-->"), page.name
        assert text.count("<!--numbers:") == text.count("<!--/numbers-->"), page.name


@pytest.mark.slow
def test_the_docs_numbers_are_current():
    """``python docs/make_numbers.py --check``: every generated number and table as the code computes it now."""
    r = subprocess.run([PY, str(ROOT / "docs" / "make_numbers.py"), "--check"], capture_output=True, text=True,
                       timeout=1800, cwd=ROOT)
    assert r.returncode == 0, r.stdout[-6000:] + r.stderr[-3000:]


def _tour() -> list[str]:
    text = (ROOT / "README.md").read_text()
    block = text[text.index("## A five-minute tour"):]
    code = block[block.index("```sh") + 5:block.index("```", block.index("```sh") + 5)]
    cmds = []
    for line in code.splitlines():
        line = line.split("#", 1)[0].strip()
        if line and not line.startswith("source "):
            cmds.append(line)
    return cmds


def test_the_tour_is_what_the_readme_says():
    cmds = _tour()
    assert [shlex.split(c)[1] for c in cmds] == ["simulate", "run", "report", "replay", "simulate", "report",
                                                 "analyze"]
    live = shlex.split(cmds[1])
    assert "--duration" not in live, "the tour's live run is the whole example"


def test_the_tours_budget_check_is_on_a_scenario_that_declares_a_budget():
    from testbed import scenario

    cmds = [shlex.split(c) for c in _tour()]
    rec = cmds[4][cmds[4].index("--out") + 1]
    assert cmds[5][1:3] == ["report", rec]
    assert scenario.load(cmds[4][2]).attack.budget is not None


@pytest.mark.process
def test_the_five_minute_tour_runs_as_written(tmp_path):
    """Each command of the README's tour, in a fresh folder, with the installed ``testbed``."""
    env = dict(os.environ, PATH=f"{Path(PY).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    env.pop("TESTBED_RECORDINGS_DIR", None)
    for cmd in _tour():
        r = subprocess.run(cmd, shell=True, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, (cmd, r.stdout[-2000:], r.stderr[-3000:])
    for f in ("paper.png", "recordings/paper.mcap", "recordings/paper.rrd", "recordings/greedy.mcap", "analysis.png"):
        assert (tmp_path / f).stat().st_size > 1000, f
