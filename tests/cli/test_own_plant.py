"""Bring your own plant: a module next to a scenario, an installed plant package, testbed check-plant.

Every test here runs the real commands in their own processes, from a working
directory that is not the plant's folder: the plant must be found through the
scenario's folder (or the installed package), by every process of a run.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import secrets
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pytest
from helpers.cli import PY, tb

import plants

VDP = '''"""Van der Pol oscillator, written like plants/pendulum.py."""
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from plants.base import Plant, rhs_function


@rhs_function
def vdp_rhs(x, u, p, dx):
    mu = p[0]
    dx[0] = x[1]
    dx[1] = mu * (1.0 - x[0] * x[0]) * x[1] - x[0] + u[0]


@dataclass(frozen=True)
class VanDerPol(Plant):
    mu: float = 1.0

    name: ClassVar[str] = "vanderpol"
    rhs: ClassVar = vdp_rhs
    description: ClassVar[str] = "Van der Pol oscillator (n = 2, m = 1)"
    lipschitz_region: ClassVar[float] = 1.0

    @property
    def n(self):
        return 2

    @property
    def m(self):
        return 1

    def param_vector(self):
        return np.array([self.mu])

    def linearization(self):
        return np.array([[0.0, 1.0], [-1.0, self.mu]]), np.array([[0.0], [1.0]])
'''

#: the same plant with a wrong Jacobian: A[1][0] = +1 instead of -1
VDP_WRONG = VDP.replace("np.array([[0.0, 1.0], [-1.0, self.mu]])", "np.array([[0.0, 1.0], [1.0, self.mu]])")

SCENARIO = '''name = "vdp"
[plant]
name = "{ref}"
params = {{ mu = 1.0 }}
x0 = [0.1, 0.1]
[quantizer]
T = 0.1
M = 6
L = 5.0
E0 = 0.1
[controller]
lqr = {{ Q = [[10.0, 0.0], [0.0, 1.0]], R = [[0.1]] }}
[attack]
kind = "intervals"
intervals = [[1.0, 0.5]]
[run]
duration = {duration}
'''


@pytest.fixture
def plant_dir(tmp_path):
    """``<tmp>/plantdir/{myplants.py, vdp.toml}`` and an empty working directory ``<tmp>/elsewhere``."""
    d = tmp_path / "plantdir"
    d.mkdir()
    (d / "myplants.py").write_text(VDP)
    (d / "vdp.toml").write_text(SCENARIO.format(ref="myplants:VanDerPol", duration=5.0))
    (tmp_path / "elsewhere").mkdir()
    return d


# ====================================================================== a module next to the scenario
@pytest.mark.slow
def test_module_next_to_scenario_simulate_and_report(plant_dir):
    """simulate --out from another folder; report from a third: as imported, with the module gone, changed."""
    work = plant_dir.parent / "elsewhere"
    rec = plant_dir.parent / "run.mcap"
    rc, out, err = tb("simulate", "../plantdir/vdp.toml", "--json", "--out", rec, cwd=work)
    assert rc == 0, err
    sim = json.loads(out)
    assert sim["plant"] == "vanderpol" and sim["converged"] and sum(sim["theta"]) == 6

    # the same in-process, through the scenario loader (the folder is the scenario's, not the cwd)
    from testbed import scenario

    sc = scenario.load(plant_dir / "vdp.toml")
    assert sc.plant.ref == "myplants:VanDerPol" and sc.base_dir == str(plant_dir.resolve())
    assert type(sc.make_plant()).__module__ == "myplants"

    other = plant_dir.parent          # report runs from yet another folder
    rc, out, err = tb("report", rec, "--json", cwd=other)
    assert rc == 0, err
    rep = json.loads(out)
    sha = hashlib.sha256(VDP.encode()).hexdigest()
    assert rep["plant_source"] == {"ref": "myplants:VanDerPol", "sha256": sha, "loaded_from": "import",
                                   "differs": False, "importable_sha256": sha, "reason": None, "module": "myplants"}
    for key in ("x", "u", "E", "theta", "symbols"):
        assert rep[key] == sim[key], key

    # the module is gone: without --trust-code the stored source is not run (the recorded values are read)
    (plant_dir / "myplants.py").rename(plant_dir / "myplants.py.away")
    rc, out, err = tb("report", rec, "--json", cwd=other)
    assert rc == 0, err
    rep0 = json.loads(out)
    assert rep0["plant_source"]["loaded_from"] == "not run" and "--trust-code" in err
    assert rep0["x"] == sim["x"] and rep0["escaped"] is None and "--trust-code" in rep0["resimulation"]["verdict"]
    # with it, the report uses the source stored in the recording, and says so
    rc, out, err = tb("report", rec, "--trust-code", cwd=other)
    assert rc == 0, err
    assert "not importable; used the source stored in the recording" in out
    assert "runs code from the recording" in err
    rc, out, err = tb("report", rec, "--json", "--trust-code", cwd=other)
    rep2 = json.loads(out)
    assert rep2["plant_source"]["loaded_from"] == "recording" and rep2["plant_source"]["sha256"] == sha
    assert "no module 'myplants'" in rep2["plant_source"]["reason"]
    assert rep2["final_norm"] == rep["final_norm"] == sim["final_norm"]

    # the module is back but changed: the report says it differs
    (plant_dir / "myplants.py").write_text(VDP + "\n# tuned\n")
    rc, out, err = tb("report", rec, cwd=other)
    assert rc == 0, err
    assert "DIFFERS from the recorded one" in out and "differs from the one recorded" in err
    rc, out, _ = tb("report", rec, "--json", cwd=other)
    ps = json.loads(out)["plant_source"]
    assert ps["loaded_from"] == "import" and ps["differs"] is True and ps["importable_sha256"] != sha


@pytest.mark.slow  # its own processes (an interpreter start-up each)
def test_plant_reference_errors(tmp_path):
    """A reference that cannot be resolved is one line naming what was looked for, and exit 2."""
    from testbed import scenario

    (tmp_path / "vdp.toml").write_text(SCENARIO.format(ref="nosuchmod:VanDerPol", duration=1.0))
    with pytest.raises(scenario.ScenarioError, match=rf"no module 'nosuchmod' \(looked in {tmp_path}, then sys.path\)"):
        scenario.load(tmp_path / "vdp.toml")
    (tmp_path / "myplants.py").write_text(VDP)
    for ref, msg in [("myplants:Nope", "has no 'Nope'"), ("myplants:np", "is not a subclass of plants.Plant"),
                     ("my plants:X", "a module reference is 'module.path:ClassName'"),
                     ("vanderpol", "unknown plant 'vanderpol'")]:
        (tmp_path / "bad.toml").write_text(SCENARIO.format(ref=ref, duration=1.0))
        with pytest.raises(scenario.ScenarioError, match=msg):
            scenario.load(tmp_path / "bad.toml")
    (tmp_path / "broken.py").write_text("raise RuntimeError('boom')\n")
    (tmp_path / "bad.toml").write_text(SCENARIO.format(ref="broken:X", duration=1.0))
    with pytest.raises(scenario.ScenarioError, match="importing 'broken' failed: RuntimeError: boom"):
        scenario.load(tmp_path / "bad.toml")
    rc, _, err = tb("simulate", tmp_path / "bad.toml", cwd=tmp_path)
    assert rc == 2 and err.count("\n") == 1 and "RuntimeError: boom" in err


def test_two_folders_two_modules_of_one_name(tmp_path):
    """Each scenario gets the module of its own folder, even when both are called myplants."""
    from testbed import scenario

    for mu, d in ((1.0, "a"), (2.0, "b")):
        (tmp_path / d).mkdir()
        (tmp_path / d / "myplants.py").write_text(VDP.replace("mu: float = 1.0", f"mu: float = {mu}"))
        (tmp_path / d / "vdp.toml").write_text(SCENARIO.format(ref="myplants:VanDerPol", duration=1.0)
                                               .replace("params = { mu = 1.0 }\n", ""))
    pa = scenario.load(tmp_path / "a" / "vdp.toml").make_plant()
    pb = scenario.load(tmp_path / "b" / "vdp.toml").make_plant()
    assert (pa.mu, pb.mu) == (1.0, 2.0)


# ====================================================================== check-plant
@pytest.mark.slow
def test_check_plant_correct_and_wrong_jacobian(tmp_path):
    (tmp_path / "myplants.py").write_text(VDP)
    (tmp_path / "wrongplants.py").write_text(VDP_WRONG)
    rc, out, err = tb("check-plant", "myplants:VanDerPol", cwd=tmp_path)
    assert rc == 0, out + err
    lines = [ln.strip() for ln in out.splitlines()]
    verdicts = [ln.split()[:2] for ln in lines if ln.startswith(("PASS", "FAIL"))]
    assert verdicts == [["PASS", c] for c in ("shapes", "equilibrium", "jacobian", "remainder", "lipschitz",
                                               "assumption2", "stabilizable")]
    assert "settings from defaults (no --scenario): T = 0.1 s, M = 6" in out
    rc, out, err = tb("check-plant", "wrongplants:VanDerPol", "--json", cwd=tmp_path)
    assert rc == 1, out + err
    res = json.loads(out)
    bad = {c["name"] for c in res["checks"] if not c["ok"]}
    assert bad == {"jacobian", "remainder"} and res["ok"] is False
    jac = next(c for c in res["checks"] if c["name"] == "jacobian")
    assert "max |A - A_fd| = 2.00e+00" in jac["detail"]
    # with the scenario's L, T, M (and its parameters): L = 5 is above the estimate on ||x|| <= 1
    (tmp_path / "vdp.toml").write_text(SCENARIO.format(ref="myplants:VanDerPol", duration=1.0))
    rc, out, _ = tb("check-plant", "myplants:VanDerPol", "--scenario", "vdp.toml", "--L", "2.5", cwd=tmp_path)
    assert rc == 1 and "FAIL  lipschitz" in out and "EXCEEDS stated L = 2.5" in out
    rc, _, err = tb("check-plant", "myplants:Nope", cwd=tmp_path)
    assert rc == 2 and "has no 'Nope'" in err


# ====================================================================== an installed plant package
def _wheel(dest: Path) -> Path:
    """A wheel of the package ``my-plants``: module my_plants (the Van der Pol plant), entry point vdp-ep."""
    files = {
        "my_plants/__init__.py": VDP,
        "my_plants-0.1.dist-info/METADATA": "Metadata-Version: 2.1\nName: my-plants\nVersion: 0.1\n",
        "my_plants-0.1.dist-info/WHEEL": "Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n",
        "my_plants-0.1.dist-info/entry_points.txt": "[dos_testbed.plants]\nvdp-ep = my_plants:VanDerPol\n",
    }
    record = []
    for name, text in files.items():
        digest = base64.urlsafe_b64encode(hashlib.sha256(text.encode()).digest()).rstrip(b"=").decode()
        record.append(f"{name},sha256={digest},{len(text.encode())}")
    record.append("my_plants-0.1.dist-info/RECORD,,")
    files["my_plants-0.1.dist-info/RECORD"] = "\n".join(record) + "\n"
    whl = dest / "my_plants-0.1-py3-none-any.whl"
    with zipfile.ZipFile(whl, "w") as z:
        for name, text in files.items():
            z.writestr(name, text)
    return whl


@pytest.mark.slow
def test_installed_plant_package_entry_point(tmp_path, monkeypatch):
    """pip install of a tiny plant package (a wheel built here, installed with pip into a temporary folder).

    Then ``name = "vdp-ep"`` works in a scenario, ``testbed plants`` lists it, and
    in-process ``plants.resolve`` finds it through importlib.metadata.
    """
    site = tmp_path / "site"
    whl = _wheel(tmp_path)
    r = subprocess.run([PY, "-m", "pip", "install", "-q", "--no-deps", "--no-index", "--target", str(site), str(whl)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    env = {"PYTHONPATH": str(site)}
    rc, out, err = tb("plants", "--json", cwd=tmp_path, env=env)
    assert rc == 0, err
    rows = {row["name"]: row for row in json.loads(out)["plants"]}
    assert rows["vdp-ep"] == {"name": "vdp-ep", "source": "entry point", "ref": "my_plants:VanDerPol",
                              "dist": "my-plants", "n": 2, "m": 1, "shadowed": False, "error": None,
                              "description": "Van der Pol oscillator (n = 2, m = 1)"}
    assert rows["lienard"]["source"] == "built-in" and rows["lienard"]["n"] == 2
    (tmp_path / "ep.toml").write_text(SCENARIO.format(ref="vdp-ep", duration=2.0))
    rc, out, err = tb("simulate", "ep.toml", "--json", cwd=tmp_path, env=env)
    assert rc == 0, err
    assert json.loads(out)["plant"] == "vanderpol"
    rc, _, err = tb("simulate", "ep.toml", cwd=tmp_path)  # not installed: one line, exit 2
    assert rc == 2 and "unknown plant 'vdp-ep'" in err
    # in-process
    monkeypatch.syspath_prepend(str(site))
    assert "vdp-ep" in plants.entry_points()
    cls = plants.resolve("vdp-ep")
    assert cls.__module__ == "my_plants" and cls.name == "vanderpol"
    assert np.array_equal(plants.make("vdp-ep", mu=2.0).A, [[0.0, 1.0], [-1.0, 2.0]])


# ====================================================================== a live run of a user plant
@pytest.mark.process
def test_live_run_of_a_module_plant_equals_simulator(plant_dir):
    """testbed run from another folder: every node and the recorder import the module from the scenario's
    folder; the run equals testbed simulate bit for bit, and testbed report reads its recording."""
    from failclosed import rerun_flags, rerun_while_stalled
    from helpers.live import BIT_EXACT_KEYS, mismatch
    from helpers.procs import reap

    work = plant_dir.parent / "elsewhere"
    rec = plant_dir.parent / "live.mcap"

    def live(rid, *more):
        rc, out, err = tb("run", "../plantdir/vdp.toml", "--json", "--duration", "3", "--run-id", rid,
                          "--run-dir", plant_dir.parent / f"logs-{rid}", "--out", rec, *more, cwd=work)
        try:
            return rc, json.loads(out), err
        except json.JSONDecodeError:
            pytest.fail(f"no JSON summary (exit {rc})\nstdout: {out[-2000:]}\nstderr: {err[-3000:]}")

    rid = f"t{os.getpid()}xown{secrets.token_hex(3)}"
    def attempt(n):  # the one rerun policy: a stalled run again (its recording replaced), the last compared
        if n:
            assert not reap(rid + "r" * (n - 1))
        return live(rid + "r" * n, *(("--force",) if n else ()), *rerun_flags(n))

    try:
        rc, s, err = rerun_while_stalled(attempt, "module plant")
    finally:
        assert not reap(rid)  # every attempt's processes (their run ids begin with rid)
    assert rc == 0, (s.get("faults"), err[-2000:])
    assert s["complete"] and s["samples"] == 30 and s["outcome"] == "done"
    rc, out, err = tb("simulate", "../plantdir/vdp.toml", "--duration", "3", "--json", cwd=work)
    assert rc == 0, err
    sim = json.loads(out)
    for key in BIT_EXACT_KEYS:
        assert s[key] == sim[key], mismatch(s, sim, key)
    rc, out, err = tb("report", rec, "--json", cwd=plant_dir.parent)
    assert rc == 0, err
    rep = json.loads(out)
    assert rep["plant_source"]["loaded_from"] == "import" and not rep["plant_source"]["differs"]
    assert rep["x"] == sim["x"] and rep["source"] == "live"


def test_launcher_says_when_a_run_never_started(capsys):
    """A run whose nodes could not load the plant prints why, not a summary of a loop that never ran."""
    from testbed.commands.run import print_text

    why = "testbed node: vdp.toml: [plant] unknown plant 'vanderpol'"
    print_text({"samples": 0, "run_id": "r1", "scenario": "vdp", "outcome": "plant exited before the start",
                "faults": [{"node": "plant", "kind": "crashed", "why": "exit code 2", "last_log_line": why}],
                "run_dir": "/tmp/logs"})
    out = capsys.readouterr().out
    assert "the run NEVER STARTED (outcome: plant exited before the start)" in out
    assert why in out and "converged" not in out and "agree" not in out


def test_a_plant_file_may_not_shadow_an_imported_module(tmp_path):
    from testbed import scenario

    (tmp_path / "numpy.py").write_text(VDP)
    (tmp_path / "vdp.toml").write_text(SCENARIO.format(ref="numpy:VanDerPol", duration=1.0))
    with pytest.raises(scenario.ScenarioError, match="has the name of a module already imported from .*: rename it"):
        scenario.load(tmp_path / "vdp.toml")
    assert np.zeros(2).shape == (2,)   # numpy is still numpy


@pytest.mark.slow
def test_recorded_model_module_is_stored_too(tmp_path):
    """A [model] of a class of your own (model mismatch): its source is in the recording as well."""
    from testbed import scenario
    from testbed.record.recording import record_simulation
    from testbed.sim.batch import simulate_scenario

    (tmp_path / "mymodels.py").write_text(VDP)
    text = SCENARIO.format(ref="vanderpol-unused", duration=2.0).replace(
        '[plant]\nname = "vanderpol-unused"\nparams = { mu = 1.0 }\n',
        '[plant]\nname = "myplants:VanDerPol"\nparams = { mu = 1.1 }\n') + \
        '[model]\nname = "mymodels:VanDerPol"\nparams = { mu = 1.0 }\n'
    (tmp_path / "myplants.py").write_text(VDP)
    (tmp_path / "mm.toml").write_text(text)
    sc = scenario.load(tmp_path / "mm.toml")
    assert sc.make_model().mu == 1.0 and sc.make_plant().mu == 1.1
    rec = tmp_path / "mm.mcap"
    record_simulation(rec, sc, simulate_scenario(sc))
    (tmp_path / "mymodels.py").unlink()
    rc, out, err = tb("report", rec, "--json", "--trust-code", cwd=tmp_path.parent)
    assert rc == 0, err
    rep = json.loads(out)
    assert rep["model_source"]["loaded_from"] == "recording" and rep["model_source"]["module"] == "mymodels"
    assert rep["plant_source"]["loaded_from"] == "import" and not rep["plant_source"]["differs"]
    assert "model module 'mymodels' is not importable" in err


def test_stored_source_refusals_are_one_line_and_leave_sys_modules_as_they_were():
    """``plants.refs.load_stored``, under every plant and method a recording brings back: a corrupt text, a bad
    name, code that raises, a class of the wrong kind; each one line, and the module that held the name stays."""
    import hashlib
    import sys

    from plants.refs import PlantRefError, load_source
    from testbed.methods.base import MethodError
    from testbed.methods.registry import resolve_recorded

    def sha(text):
        return hashlib.sha256(text.encode()).hexdigest()

    raises = "raise RuntimeError('the stored code broke')\n"
    cases = [("", "", "no stored source"),
             (VDP, "0" * 64, "does not match its sha256 (corrupt recording)"),
             (raises, sha(raises), "failed to load: RuntimeError: the stored code broke")]
    for text, digest, why in cases:
        with pytest.raises(PlantRefError) as e:
            load_source("json:VanDerPol", None, "json", "VanDerPol", text, digest, trust_code=True)
        assert why in str(e.value) and "\n" not in str(e.value)
        assert sys.modules["json"] is json   # the real json module is still the one imported
    with pytest.raises(PlantRefError, match="bad stored module or class name"):
        load_source("x:VanDerPol", None, "os;rm", "VanDerPol", VDP, sha(VDP), trust_code=True)
    # a plant module named as a method: its class is no Method
    with pytest.raises(MethodError, match=r"is not a subclass of testbed\.methods\.Method") as e:
        resolve_recorded("testbed_no_such_module_xyz:VanDerPol", None, module="testbed_no_such_module_xyz",
                         class_name="VanDerPol", source=VDP, sha256=sha(VDP), trust_code=True)
    assert "\n" not in str(e.value) and "testbed_no_such_module_xyz" not in sys.modules
    with pytest.raises(MethodError, match="does not match its sha256"):
        resolve_recorded("testbed_no_such_module_xyz:M", None, module="testbed_no_such_module_xyz", class_name="M",
                         source=VDP, sha256="0" * 64, trust_code=True)
    # and a good one loads, pinned to its reference
    cls = load_source("testbed_stored_vdp:VanDerPol", None, "testbed_stored_vdp", "VanDerPol", VDP, sha(VDP),
                      trust_code=True)
    assert cls.name == "vanderpol" and sys.modules["testbed_stored_vdp"].VanDerPol is cls
    assert plants.refs.resolve("testbed_stored_vdp:VanDerPol", None) is cls
