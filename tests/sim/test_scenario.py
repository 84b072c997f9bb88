"""Scenario files: bundled scenarios load; every bad value gets a clear error."""

import tomllib

import numpy as np
import pytest
from helpers.sims import paper_loop_toml

from testbed import scenario
from testbed.scenario.spec import ScenarioError

GOOD = paper_loop_toml() + """
[attack]
kind = "intervals"
intervals = [[1.0, 0.5], [3.0, 0.8]]

[run]
duration = 20.0
"""


def test_issue_example_loads():
    sc = scenario.loads(GOOD)
    assert sc.K.shape == (1, 2)
    assert sc.n_steps == 200
    assert sc.quantizer.Lambda == pytest.approx(np.e)
    th = sc.theta()
    assert th[10] == 1 and th[15] == 1 and th[16] == 0 and th[38] == 1 and th[39] == 0


@pytest.mark.parametrize("name", scenario.bundled_names())
def test_bundled_scenarios_load(name):
    sc = scenario.load(name)
    assert sc.x0.shape == (sc.make_plant().n,)
    assert sc.source


def test_bundled_names_include_the_paper():
    assert {"paper", "paper-escape"} <= set(scenario.bundled_names())


def test_lqr_controller():
    text = GOOD.replace('K = [[-1.81, -1.90]]', 'lqr = { Q = [[1e-4, 0.0], [0.0, 1e-4]], R = [[1.0]] }')
    sc = scenario.loads(text)
    np.testing.assert_allclose(sc.K, [[-1.81, -1.90]], atol=0.005)


def _bad(old, new):
    assert old in GOOD, old
    return GOOD.replace(old, new)


@pytest.mark.parametrize("text,match", [
    (_bad('name = "lienard"', 'name = "nope"'), r"unknown plant 'nope'"),
    (_bad("M = 6", "M = 2"), r"breaks Assumption 2"),
    (_bad("T = 0.1", "T = 0.0"), r"\[quantizer.T\] must be > 0"),
    (_bad("T = 0.1", "T = -1"), r"\[quantizer.T\] must be > 0"),
    (_bad("x0 = [0.1, 0.1]", "x0 = [0.1, 0.1, 0.1]"), r"\[plant.x0\] must have shape"),
    (_bad("K = [[-1.81, -1.90]]", "K = [[-1.81]]"), r"\[controller.K\] must have shape 1 x 2"),
    (_bad("K = [[-1.81, -1.90]]", "K = [[1.0, 1.0]]"), r"not Schur stable"),
    (_bad("E0 = 0.1", "E0 = 0.1\nfoo = 3"), r"unknown key\(s\) \['foo'\]"),
    (_bad("[run]", "[runn]\nx=1\n[run]"), r"unknown key\(s\) \['runn'\]"),
    (_bad("M = 6", "M = 6.5"), r"must be an integer"),
    (_bad("M = 6", 'M = "six"'), r"must be a number"),
    (_bad("E0 = 0.1", "E0 = 0.05"), r"breaks Assumption 5"),
    (_bad('kind = "intervals"\nintervals = [[1.0, 0.5], [3.0, 0.8]]', 'kind = "random"'), r"\[attack.kappa_F\] missing"),
    # a misspelled key is named as unknown whatever its value (a list, a number), as in every other section
    (_bad("intervals = [[1.0, 0.5], [3.0, 0.8]]", "intervals = [[1.0, 0.5]]\nintervalz = [[1.0, 0.5]]"),
     r"\[attack\] unknown key\(s\) \['intervalz'\]; allowed: \['intervals'\]"),
    (_bad("intervals = [[1.0, 0.5], [3.0, 0.8]]", "intervalz = [[1.0, 0.5]]"), r"\[attack\] unknown key\(s\) \['intervalz'\]"),
    (_bad('kind = "intervals"\nintervals = [[1.0, 0.5], [3.0, 0.8]]',
          'kind = "periodic"\nperiod = 2.0\nlength = 0.5\nofset = 1'), r"\[attack\] unknown key\(s\) \['ofset'\]"),
    (_bad('kind = "intervals"\nintervals = [[1.0, 0.5], [3.0, 0.8]]',
          'kind = "random"\nkappa_F = 1\nrho_F = 0.1\nkappa_D = 1\nrho_D = 1.0'), r"rho_D.*< 1"),
    (_bad('kind = "intervals"', 'kind = "laser"'), r"laser"),
    (_bad("intervals = [[1.0, 0.5], [3.0, 0.8]]", "intervals = [[1.0, -0.5]]"), r"tau"),
    (_bad("duration = 20.0", "duration = 0.01"), r"shorter than one sampling period"),
    (_bad('params = { a = 0.3333333333333333, b = 0.02 }', 'params = { c = 1 }'), r"unknown parameter"),
    (_bad("[run]\nduration = 20.0", ""), r"\[run\] section missing"),
    ("[plant\nname=", r"not valid TOML"),
])
def test_bad_values_are_clear_errors(text, match):
    with pytest.raises(ScenarioError, match=match):
        scenario.loads(text)


def test_allow_flags():
    sc = scenario.loads(_bad("M = 6", "M = 2\nallow_M_le_Lambda = true"))
    assert sc.quantizer.M == 2


def test_missing_file_and_unknown_name():
    with pytest.raises(ScenarioError, match="no such scenario file"):
        scenario.load("does/not/exist.toml")
    with pytest.raises(ScenarioError, match="neither a scenario file nor a bundled scenario"):
        scenario.load("not-a-scenario")


@pytest.mark.slow  # its own processes (an interpreter start-up each)
def test_reading_a_scenario_imports_no_numba():
    """The launcher until the run starts and the attacker node never import numba (about 0.3 s of
    CPU per process at a live run's start-up): reading and checking a scenario needs none."""
    import subprocess
    import sys

    code = ("import sys, testbed.cli, testbed.live.launcher, testbed.nodes.main, testbed.nodes.attacker\n"
            "from testbed import scenario\n"
            "for name in ('paper', 'pendulum', 'paper-greedy'):\n"
            "    sc = scenario.load(name)\n"
            "    sc.make_model()\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('numba', 'llvmlite'))[:3])\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[]", out.stdout


def test_the_one_method_swap_rule():
    """--method with the scenario's own method keeps its params (given params go over them); another
    method gets its defaults and the note names the params it drops and the [quantizer] keys it ignores;
    an unknown [quantizer] key stays an error whatever the swap."""
    text = GOOD.replace("[attack]", '[method]\nname = "static"\nparams = { range = 0.7 }\n\n[attack]')
    text = "\n".join(ln for ln in text.splitlines() if not ln.startswith(("L = ", "E0 = ", "mode = "))) + "\n"
    sc = scenario.loads(text)
    assert dict(sc.method.params) == {"range": 0.7} and not sc.method_note
    same = scenario.with_overrides(sc, {"method": "static"})
    assert dict(same.method.params) == {"range": 0.7} and same.method_note == ""
    assert dict(scenario.with_overrides(sc, {"method": {"name": "static", "params": {"range": 0.5}}}).method.params) \
        == {"range": 0.5}
    other = scenario.with_overrides(sc, {"method": "unquantized"})
    assert other.method.name == "unquantized" and dict(other.method.params) == {}
    assert other.method_note == ("note: method 'unquantized' ignores [quantizer] M of this scenario and drops the "
                                 "[method] params range of 'static'")
    back = scenario.with_overrides(other, {"method": "static"})  # from the file again: its own params
    assert dict(back.method.params) == {"range": 0.7}
    data = tomllib.loads(text)
    data["quantizer"]["foo"] = 1
    swapped, note, _ = scenario.swap_method(data, "unquantized", None)
    assert swapped["quantizer"] == {"T": 0.1, "foo": 1} and "ignores [quantizer] M of" in note
    with pytest.raises(ScenarioError, match=r"unknown key\(s\) \['foo'\]"):
        scenario.from_dict(swapped)


def test_a_run_parses_its_scenario_once(monkeypatch, tmp_path):
    """A process of a live run reads its scenario text once: the run options are applied to the parsed
    document (not by parsing ``source`` again), and a drawn seed, the start digest, the rules of thumb,
    a rewrite of the scenario and a later override all work from that one parse."""
    from testbed.nodes.options import RunOptions, load_scenario, run_digest
    from testbed.scenario import rulesofthumb
    from testbed.scenario import write as scenariowrite

    path = tmp_path / "s.toml"
    random = 'kind = "random"\nkappa_F = 2.0\nrho_F = 0.1\nkappa_D = 1.0\nrho_D = 0.1'  # no seed: one is drawn
    path.write_text(scenario.load("paper").source.replace('kind = "intervals"', random)
                    .replace("intervals = [[", "# intervals = [["), encoding="utf-8")
    parses = []
    real = tomllib.loads
    monkeypatch.setattr(tomllib, "loads", lambda text, **kw: parses.append(len(text)) or real(text, **kw))
    sc = load_scenario(str(path), RunOptions(duration=3.0, method="zoom", deadline=0.6))
    assert len(parses) == 1
    assert (sc.run.duration, sc.method.name, sc.run.deadline, sc.source) == (3.0, "zoom", 0.6, path.read_text())
    sc2, over = scenario.with_seed(sc, RunOptions(duration=3.0, method="zoom", deadline=0.6).overrides())
    run_digest(sc2, RunOptions())
    rulesofthumb.warnings(sc2)
    scenariowrite.with_attack(sc2, x0=sc2.x0, E0=sc2.quantizer.E0, intervals=[], duration=1.0, name="copy",
                              description="", out_dir=tmp_path)
    assert sc2.run.duration == 3.0 and sc2.attack.params_dict["seed"] == over["seed"], "a drawn seed kept the rest"
    sc3 = scenario.with_overrides(sc2, dict(over, T=0.05))
    assert len(parses) == 1, "the scenario text was parsed again"
    assert sc3.T == 0.05 and sc3.attack.params_dict["seed"] == over["seed"] and sc3.run.duration == 3.0
    assert sc3.document() == real(path.read_text()), "the document is the file's, overrides apart"


def test_a_process_builds_its_method_once(monkeypatch):
    """The method object the scenario's check built is the one every later ``make_method`` returns (an
    encoder node asks three times); a copy through pickle (a campaign's worker) builds its own, and a
    spec changed by ``dataclasses.replace`` never keeps another's object."""
    import dataclasses
    import pickle

    from testbed import methods

    built = []
    real = methods.make
    monkeypatch.setattr(methods, "make", lambda *a, **kw: built.append(a[0]) or real(*a, **kw))
    sc = scenario.load("paper")
    assert built == ["paper"]
    m = sc.make_method()
    assert sc.make_method() is m and sc.make_method().make_encoder is not None and built == ["paper"]
    sc2 = pickle.loads(pickle.dumps(sc))
    assert sc2 == sc and sc2.make_method() is not m and built == ["paper", "paper"]
    other = dataclasses.replace(sc.method, name="zoom")
    assert other.make().display_name() != m.display_name() and built[-1] == "zoom"
    built.clear()
    swapped = scenario.load("paper", overrides={"method": "zoom"})
    assert built == ["zoom"], "a --method swap builds its method once (the swap's check hands it to the build)"
    assert swapped.make_method() is swapped.make_method() and built == ["zoom"]
    built.clear()
    assert scenario.with_overrides(sc, {"method": "static"}).method.name == "static" and built == ["static"]


def test_a_process_parses_the_scenario_once_and_builds_each_object_once(monkeypatch, capsys):
    """A command reads the scenario's TOML once and builds the plant, the model and the method once (the
    per-sample simulator, the kernel's check and the summary all ask for them again); a node's scenario from a
    join file, with the run's overrides, likewise.  Counted at the three builders."""
    import plants
    from testbed import cli, methods
    from testbed.nodes import joined

    counts: dict = {}

    def counting(mod, name):
        real = getattr(mod, name)
        monkeypatch.setattr(mod, name, lambda *a, **kw: counts.__setitem__(name, counts.get(name, 0) + 1)
                            or real(*a, **kw))

    counting(tomllib, "loads")
    counting(plants, "instantiate")
    counting(methods, "make")
    for ref, per_sample, objects in (("paper", [], 1), ("paper-mismatch", ["--simulator", "per-sample"], 2)):
        counts.clear()
        assert cli.main(["simulate", ref, "--duration", "1", *per_sample]) == 0
        assert counts == {"loads": 1, "instantiate": objects, "make": 1}, (ref, counts)
    capsys.readouterr()
    sc = scenario.load("paper")
    jf = type("JoinFile", (), {"path": "join.json", "scenario": {"toml": sc.source, "name": "paper", "base_dir": ""}})
    counts.clear()
    node_sc = joined.scenario(jf, {"duration": 2.0, "E0": 3.0})
    assert counts == {"loads": 1, "instantiate": 1, "make": 1}
    import dataclasses

    assert dataclasses.replace(node_sc, path=sc.path) == scenario.with_overrides(sc, {"duration": 2.0, "E0": 3.0})
    assert node_sc.make_plant() is node_sc.make_model() is node_sc.make_plant()


def test_overrides_in_one_parse_equal_load_then_override():
    """``load(ref, overrides=...)`` builds what ``with_overrides(load(ref), ...)`` builds, and blames the same input."""
    for over in ({"duration": 2.5, "method": "zoom"}, {"T": 0.05, "E0": 3.0}, {"attack": {"kind": "none"}}):
        a, b = scenario.load("paper", overrides=over), scenario.with_overrides(scenario.load("paper"), over)
        assert a == b and a.path == b.path and a.method_note == b.method_note
    for bad in ({"M": 2}, {"T": -1.0}, {"bogus": 1}):
        with pytest.raises(scenario.BadInput) as one:
            scenario.load("paper", overrides=bad)
        with pytest.raises(scenario.BadInput) as two:
            scenario.with_overrides(scenario.load("paper"), bad)
        assert str(one.value) == str(two.value) and not isinstance(one.value, ScenarioError)
