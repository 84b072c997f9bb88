"""The public API as docs/api.md says (fast tier), and no silent waits (docs/cli.md).

``Run.save`` writes a recording every reader and viewer opens, ``Run.plot`` draws the figure of
``testbed simulate --plot`` (the same data, compared by the digest each figure carries), the names
``testbed.compare`` and ``testbed.BadInput``, every bad override a ``BadInput`` that says what to
change, the overrides of the API and of the command line as the docs list them, ``Run.summary``
key by key, ``x_final``, ``testbed scenarios --show``; a numba compilation that says what it does,
``check-plant --scenario``, ``analyze``'s prose, and a refused ``testbed run`` that leaves nothing.
"""

from __future__ import annotations

import os
import re
import threading
import tomllib
from pathlib import Path

import numpy as np
import pytest
from helpers.cli import tb_run, tb_run_here

import testbed
from testbed import scenario
from testbed.common import errors, figstyle

ROOT = Path(__file__).resolve().parents[2]
API_MD = (ROOT / "docs" / "api.md").read_text()


# ============================================================================ Run.save, Run.plot
@pytest.mark.slow  # seconds: a report and a Rerun replay of the run
def test_run_save_writes_a_recording_that_every_reader_and_viewer_opens(tmp_path):
    sim = testbed.simulate("paper", x0=[0.05, -0.02], duration=6, attack={"intervals": [[0.5, 0.25]]})
    path = sim.save(tmp_path / "sim.mcap")
    run = testbed.open(path)
    assert run.source == "simulate" and run.N == sim.N == 60
    for name, a in sim.arrays.items():
        assert np.array_equal(run.arrays[name], a, equal_nan=a.dtype.kind == "f"), name
    assert list(run.scenario.x0) == [0.05, -0.02]          # the overrides went into the recording
    assert testbed.compare(run, sim)["identical"]
    r = tb_run_here("report", path, "--json")
    assert r.returncode == 0, r.stderr
    rrd = tmp_path / "sim.rrd"
    r = tb_run_here("replay", path, "--rrd", rrd, "--no-roa")
    assert r.returncode == 0, r.stderr
    assert rrd.stat().st_size > 1000


@pytest.mark.slow  # half a second or more on a warm cache
def test_run_save_never_overwrites_unless_asked_and_copies_a_recording(tmp_path):
    sim = testbed.simulate("paper", duration=2)
    path = sim.save(tmp_path / "a.mcap")
    with pytest.raises(testbed.BadInput, match="exists: pass overwrite=True"):
        sim.save(path)
    sim.save(path, overwrite=True)
    copy = testbed.open(path).save(tmp_path / "b.mcap")
    assert copy.read_bytes() == path.read_bytes()


@pytest.mark.slow  # seconds: the paper's figure drawn twice (41 s on a busy 2-core machine)
def test_run_plot_is_the_figure_of_simulate_plot(tmp_path):
    """Same data drawn (the digests every figure carries are equal), in each format and size."""
    png = tmp_path / "cli.png"
    r = tb_run_here("simulate", "paper", "--plot", png)
    assert r.returncode == 0, r.stderr
    sim = testbed.simulate("paper")
    want = figstyle.read_digest(png)
    assert want and len(want) == 64
    for ext in ("png", "pdf", "svg"):
        out = sim.plot(tmp_path / f"api.{ext}")
        assert figstyle.read_digest(out) == want, ext
    from PIL import Image

    with Image.open(sim.plot(tmp_path / "column.png", size="column")) as im:
        assert im.size[0] == round(figstyle.WIDTHS["column"] * 300)
    with Image.open(png) as im:
        assert im.size[0] == round(figstyle.WIDTHS["page"] * 300)
    other = testbed.simulate("paper", duration=20).plot(tmp_path / "other.png")
    assert figstyle.read_digest(other) != want
    with pytest.raises(testbed.BadInput, match=r"\.png, \.pdf, \.svg"):
        sim.plot(tmp_path / "x.jpg")
    with pytest.raises(testbed.BadInput, match="column, page"):
        sim.plot(tmp_path / "x.png", size="a4")


def test_testbed_exports_compare_and_badinput():
    import testbed.runs.compare as compare_module
    import testbed.runs.run as run_module

    assert testbed.BadInput is errors.BadInput
    assert testbed.compare is compare_module.compare
    assert testbed.simulate is run_module.simulate and testbed.open is run_module.open and testbed.Run is run_module.Run
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        testbed.nothing  # noqa: B018 - the attribute access is the test
    c = testbed.compare("paper", "paper")
    assert c["identical"] and c["first_divergence"] is None
    assert {"open", "simulate", "compare", "Run", "BadInput"} <= set(dir(testbed))


# ============================================================================ overrides
@pytest.mark.parametrize("over, hint", [
    ({"foo": 1}, r"unknown override\(s\): foo; the overrides are duration, .*attack .*scenarios --show paper"),
    ({"x0": [0.5, 0.5]}, r"x0=\[0.5, 0.5\].*Assumption 5 \(pass E0=0.5 or larger with it"),
    ({"M": 2}, r"M=2.*Assumption 2 \(pass a larger M or a smaller T"),
    ({"attack": 3}, r"override attack must be a dict of \[attack\] keys \(e.g. attack="),
    ({"duration": -1.0}, r"duration=-1.0: .*\[run.duration\]"),
    ({"x0": [0.1]}, r"x0=\[0.1\]: .*\[plant.x0\] must have shape 1 x 2"),
    ({"mode": "fast"}, r"mode='fast': .*\[quantizer.mode\]"),
])
def test_every_bad_override_raises_badinput_with_what_to_change(over, hint):
    with pytest.raises(testbed.BadInput, match=hint) as e:
        testbed.simulate("paper", **over)
    assert type(e.value) is errors.BadInput     # the file is fine: not a ScenarioError
    assert "\n" not in str(e.value)


def test_the_overrides_of_the_api_and_the_command_line_are_the_documented_sets():
    from testbed.nodes.options import RunOptions

    section = API_MD[API_MD.index("## `testbed.simulate` overrides"):]
    section = section[:section.index("\n## ", 5)]
    rows = re.findall(r"^\| `([A-Za-z0-9_]+)` \| ([^|]+) \|", section, re.M)
    documented = {name: flag.strip() for name, flag in rows}
    assert set(documented) == set(scenario.OVERRIDES)
    flags = RunOptions.override_flags()
    for name, flag in documented.items():
        if name in flags:
            assert flag == f"`{flags[name]}`", name
        else:
            assert flag.startswith("none"), (name, flag)


def test_summary_keys_are_documented_one_by_one_and_live_ones_apart(tmp_path):
    from testbed.runs.run import LIVE_KEYS, RECORDING_KEYS, SUMMARY_KEYS

    sim = testbed.simulate("paper", duration=3)
    assert tuple(sim.summary) == SUMMARY_KEYS
    rec = testbed.open(sim.save(tmp_path / "s.mcap"))
    assert set(rec.summary) == set(SUMMARY_KEYS) | set(RECORDING_KEYS)
    assert not set(rec.summary) & set(LIVE_KEYS)
    section = API_MD[API_MD.index("## `Run.summary`"):]
    section = section[:section.index("\n## ", 5)]
    live = section[section.index("Live runs only"):]
    for key in SUMMARY_KEYS + RECORDING_KEYS:
        assert re.search(rf"^\|[^|]*`{key}`", section[:section.index("Live runs only")], re.M), key
    for key in LIVE_KEYS:
        assert re.search(rf"^\|[^|]*`{key}`", live, re.M), key


def test_open_passes_the_collector_less_often_and_puts_the_callers_threshold_back(tmp_path):
    """``testbed.open`` raises the collector's first threshold while it runs (``common.gcpasses``) and restores
    the caller's, also when it raises."""
    import contextlib
    import gc

    from testbed.common import gcpasses

    path = testbed.simulate("paper", duration=1).save(tmp_path / "s.mcap")
    old = gc.get_threshold()
    seen = []
    try:
        gc.set_threshold(123, 4, 5)
        real = gcpasses.fewer_passes

        @contextlib.contextmanager
        def spy():
            with real():
                seen.append(gc.get_threshold())
                yield
        gcpasses.fewer_passes = spy
        try:
            testbed.open(path)
        finally:
            gcpasses.fewer_passes = real
        assert seen == [(gcpasses.THRESHOLD, 4, 5)] and gc.get_threshold() == (123, 4, 5)
        with pytest.raises(testbed.BadInput):
            testbed.open(tmp_path / "missing.mcap")
        assert gc.get_threshold() == (123, 4, 5)
    finally:
        gc.set_threshold(*old)


def test_x_final_is_the_state_one_period_after_the_last_sample():
    from testbed.loop.flow import phi_T

    sim = testbed.simulate("paper", duration=3)
    x, u = sim.arrays["x"], sim.arrays["u"]
    sc = sim.scenario
    want, status = phi_T(sc.make_plant(), x[-1], u[-1], sc.T, sc.flow)
    assert status == 0
    assert np.allclose(sim.summary["x_final"], want, rtol=1e-10, atol=1e-14)
    assert not np.allclose(sim.summary["x_final"], x[-1])    # x_N, not x_{N-1}
    assert "x_final" in API_MD and "x_N" in API_MD


def test_scenarios_show_prints_the_bundled_toml(tmp_path):
    for name in scenario.bundled_names():
        r = tb_run_here("scenarios", "--show", name)
        assert r.returncode == 0, r.stderr
        assert r.stdout == scenario.load(name).source
        tomllib.loads(r.stdout)
    f = tmp_path / "mine.toml"
    f.write_text(tb_run_here("scenarios", "--show", "paper").stdout)
    a, b = testbed.simulate(str(f)), testbed.simulate("paper")
    assert np.array_equal(a.arrays["x"], b.arrays["x"])
    r = tb_run_here("scenarios", "--show", "nope")
    assert r.returncode == 2 and "bundled ones are" in r.stderr and len(r.stderr.splitlines()) == 1


# ============================================================================ no silent waits
@pytest.mark.slow  # half a second or more on a warm cache
def test_a_long_compilation_names_the_kernel_and_says_it_happens_once():
    """The numba listener of ``testbed.common.compilenotice`` (delay 0 here: every real compilation says so)."""
    import io

    import numba as nb
    from numba.core import event

    from testbed.common.compilenotice import _Notice

    out = io.StringIO()
    notice = _Notice(out, delay=0.0)
    threads = threading.active_count()

    class L(event.Listener):
        def on_start(self, ev):
            notice.start(ev.data["dispatcher"])

        def on_end(self, ev):
            notice.end()

    def fresh_kernel_for_the_notice(x):
        return x * 2.5 + 1

    listener = L()
    event.register("numba:compile", listener)
    try:
        k = nb.njit(fresh_kernel_for_the_notice)
        assert k(2.0) == 6.0
        k(3.0)                                   # compiled already: no second notice
    finally:
        event.unregister("numba:compile", listener)
    text = out.getvalue()
    assert notice.timer is None and threading.active_count() == threads   # no thread left behind
    assert "compiling" in text and "fresh_kernel_for_the_notice" in text, text
    assert "happens once" in text and text.count("compiling") == 1
    assert re.search(r"compiled in \d+\.\d s", text)

    # a compilation shorter than the delay: nothing said, and its timer thread is gone afterwards
    quiet = io.StringIO()
    notice2 = _Notice(quiet, delay=60.0)

    class L2(event.Listener):
        def on_start(self, ev):
            notice2.start(ev.data["dispatcher"])

        def on_end(self, ev):
            notice2.end()

    def another_fresh_kernel(x):
        return x - 1.5

    listener2 = L2()
    event.register("numba:compile", listener2)
    try:
        assert nb.njit(another_fresh_kernel)(2.0) == 0.5
    finally:
        event.unregister("numba:compile", listener2)
    assert quiet.getvalue() == "" and threading.active_count() == threads


@pytest.mark.slow  # its own processes (an interpreter start-up each)
def test_the_cli_installs_the_notice_where_it_computes():
    from testbed import cli

    assert {"simulate", "analyze", "sweep", "check-plant", "compare", "report"}.isdisjoint(cli.QUIET_START)
    r = tb_run("simulate", "paper", "--duration", "1")         # cached kernels: nothing said
    assert r.returncode == 0 and "compiling" not in r.stderr


def _own_plant(folder: Path) -> Path:
    """docs/own-plant.md's Van der Pol plant (myplants.py) and a scenario naming it (vdp.toml), in ``folder``."""
    doc = (ROOT / "docs" / "own-plant.md").read_text()
    i = doc.index('"""myplants.py: a Van der Pol oscillator."""')
    (folder / "myplants.py").write_text(doc[i:doc.index("```", i)])
    toml = scenario.load("paper").source.replace('name = "lienard"', 'name = "myplants:VanDerPol"')
    toml = re.sub(r"(?m)^params = \{ a = .*\}$", "params = { mu = 0.5 }", toml)
    (folder / "vdp.toml").write_text(toml)
    return folder / "vdp.toml"


@pytest.mark.slow
def test_the_first_analysis_of_an_own_plant_says_it_compiles_once(tmp_path):
    """A real first compilation: the batch kernel specialized for a new plant, in a fresh kernel cache."""
    toml = _own_plant(tmp_path)
    env = dict(os.environ, TESTBED_CACHE_DIR=str(tmp_path / "cache"))
    r = tb_run("roa", toml, "--grid", "5", "--no-progress", "--workers", "1", env=env, timeout=900)
    assert r.returncode == 0, r.stderr
    assert re.search(r"testbed: compiling the batch simulator for this plant .* \(this happens once", r.stderr), r.stderr
    assert re.search(r"testbed: compiled in \d+\.\d s", r.stderr)
    r = tb_run("roa", toml, "--grid", "5", "--no-progress", "--workers", "1", env=env, timeout=900)
    assert r.returncode == 0 and "compiling" not in r.stderr, r.stderr


@pytest.mark.slow  # its own processes (an interpreter start-up each)
def test_check_plant_takes_the_plant_from_the_scenario(tmp_path):
    toml = _own_plant(tmp_path)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    r = tb_run("check-plant", "--scenario", toml, "--json", cwd=elsewhere)
    assert r.returncode in (0, 1), r.stderr                 # a verdict, not bad input
    import json

    d = json.loads(r.stdout)
    assert d["ref"] == "myplants:VanDerPol" and d["params"] == {"mu": 0.5} and d["class"] == "myplants:VanDerPol"
    assert d["settings"]["from"].startswith("scenario")
    r = tb_run("check-plant")
    assert r.returncode == 2 and "name a plant (REF) or a scenario" in r.stderr


@pytest.mark.slow  # seconds of numerics: two analyses
def test_analyze_prints_prose_and_the_papers_delta_only_for_the_papers_example():
    r = tb_run_here("analyze", "paper")
    assert r.returncode == 0, r.stderr
    assert "{" not in r.stdout and "'paper'" not in r.stdout, r.stdout
    assert "Theorem 1's condition at this budget holds" in r.stdout
    assert "the paper's delta" in r.stdout
    r = tb_run_here("analyze", "pendulum")
    assert r.returncode == 0, r.stderr
    assert "{" not in r.stdout and "paper's delta" not in r.stdout, r.stdout


@pytest.mark.slow  # its own processes (an interpreter start-up each)
def test_a_refused_run_leaves_no_run_folder(tmp_path):
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    out = tmp_path / "exists.mcap"
    out.write_bytes(b"x")
    r = tb_run("run", "paper", "--out", out, env=dict(os.environ, TMPDIR=str(tmp)), timeout=60)
    assert r.returncode == 2 and "exists" in r.stderr
    assert list(tmp.iterdir()) == []


@pytest.mark.process
def test_a_live_runs_summary_has_the_documented_keys_and_no_process_details(tmp_path):
    """A real live run (four processes over Zenoh): Run.summary is SUMMARY_KEYS, RECORDING_KEYS and
    LIVE_KEYS, without node PIDs or log paths; the run folder of a finished run is gone."""
    from testbed.runs.run import LIVE_KEYS, RECORDING_KEYS, SUMMARY_KEYS

    tmp = tmp_path / "tmp"
    tmp.mkdir()
    path = tmp_path / "live.mcap"
    r = tb_run("run", "paper", "--duration", "2", "--out", path, env=dict(os.environ, TMPDIR=str(tmp)), timeout=180)
    assert r.returncode == 0, r.stderr[-3000:]
    run = testbed.open(path)
    assert run.source == "live"
    assert set(run.summary) <= set(SUMMARY_KEYS) | set(RECORDING_KEYS) | set(LIVE_KEYS)
    assert set(SUMMARY_KEYS) | set(RECORDING_KEYS) <= set(run.summary)
    assert set(run.summary) & set(LIVE_KEYS)
    text = repr(run.summary)
    assert "pid" not in text and ".log" not in text, text
    assert not list(tmp.glob("testbed-run-*"))
