"""The committed figures and their data are what the commands draw now (docs/make_figures.py).

A figure is compared by the data it drew (the digest ``testbed.common.figstyle`` stores in every figure
file), not by pixels; the data files (``docs/analysis/paper.json``, ``docs/figures/*.json``) value
by value. The fast tier shows the check on copies: a current copy passes, a figure drawn from
other data, a figure without a digest and a data file with one changed value fail. The slow tier
recomputes every figure of the docs.
"""

from __future__ import annotations

import importlib.util
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.cli import PY

from testbed.common import figstyle

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"


def _make_figures():
    spec = importlib.util.spec_from_file_location("make_figures", DOCS / "make_figures.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def _check(docs: Path, *only: str) -> subprocess.CompletedProcess:
    args = [PY, str(DOCS / "make_figures.py"), "--check", "--docs", str(docs)]
    if only:
        args += ["--only", *only]
    return subprocess.run(args, capture_output=True, text=True, timeout=3600, cwd=ROOT)


@pytest.mark.slow  # seconds: figures drawn and compared (44 s on a busy 2-core machine)
def test_a_current_figure_passes_and_a_stale_one_fails(tmp_path):
    docs = tmp_path / "docs"
    (docs / "figures").mkdir(parents=True)
    fig, data = docs / "figures" / "simulate-paper.png", docs / "figures" / "simulate-paper.json"
    shutil.copyfile(DOCS / "figures" / "simulate-paper.png", fig)
    shutil.copyfile(DOCS / "figures" / "simulate-paper.json", data)
    r = _check(docs, "simulate-paper")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "every figure and its data is current" in r.stdout

    # a figure drawn from other data (another command's figure in its place)
    shutil.copyfile(DOCS / "figures" / "simulate-paper-escape.png", fig)
    r = _check(docs, "simulate-paper")
    assert r.returncode == 1 and "STALE figures/simulate-paper.png: drawn from other data" in r.stdout, r.stdout

    # a figure of an older version: the same picture without the digest
    from PIL import Image

    with Image.open(DOCS / "figures" / "simulate-paper.png") as im:
        im.save(fig)
    assert figstyle.read_digest(fig) is None
    r = _check(docs, "simulate-paper")
    assert r.returncode == 1 and "STALE figures/simulate-paper.png: carries no data digest" in r.stdout, r.stdout

    # the figure current again, its data with one value changed
    shutil.copyfile(DOCS / "figures" / "simulate-paper.png", fig)
    d = json.loads(data.read_text())
    d["final_norm"] *= 1.001
    data.write_text(json.dumps(d))
    r = _check(docs, "simulate-paper")
    assert r.returncode == 1 and "STALE figures/simulate-paper.json: other values" in r.stdout, r.stdout
    assert "final_norm" in r.stdout


@pytest.mark.slow  # half a second or more on a warm cache
def test_the_digest_follows_the_data_not_the_pixels(tmp_path):
    """The same data drawn at another size and format has the same digest; other data another."""
    import testbed

    run = testbed.simulate("paper", duration=5)
    a = figstyle.read_digest(run.plot(tmp_path / "a.png"))
    b = figstyle.read_digest(run.plot(tmp_path / "b.svg", size="column"))
    c = figstyle.read_digest(testbed.simulate("paper", duration=5, M=8).plot(tmp_path / "c.png"))
    assert a == b and a != c


@pytest.mark.slow  # half a second or more on a warm cache
def test_the_gallery_is_the_page_the_script_writes_and_shows_every_figure():
    mf = _make_figures()
    page = (DOCS / "figures.md").read_text()
    assert page == mf.gallery() + "\n"
    drawn = set()
    for job in mf.JOBS:
        for f in job.figures:
            assert (DOCS / f).is_file() and f"]({f})" in page, f
            assert figstyle.read_digest(DOCS / f), f"{f}: no data digest (drawn before testbed.common.figstyle)"
        if job.data:
            assert (DOCS / job.data).is_file(), job.data
        for c in job.commands:
            if "--plot" in c:
                drawn.add(c[0])
    from helpers.cli import SHARED

    assert drawn == set(SHARED["--plot"]), set(SHARED["--plot"]) - drawn
    # every figure a page of the docs shows is in the gallery
    shown = {f for p in DOCS.glob("*.md") for f in re.findall(r"\]\(((?:analysis|figures)/[^)]+\.png)\)", p.read_text())}
    assert shown <= {f for j in mf.JOBS for f in j.figures}, shown


@pytest.mark.slow
def test_every_committed_figure_and_its_data_is_current():
    """``python docs/make_figures.py --check``: every figure recomputed and compared by its data."""
    r = _check(DOCS)
    assert r.returncode == 0, r.stdout[-6000:] + r.stderr[-3000:]
