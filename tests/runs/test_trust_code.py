"""Code in a recording is data until the user says otherwise (``--trust-code``, docs/security.md).

A recording made with a method (or a plant) of the user's own stores the module's source.  Opened
from another folder with the module gone, no reader runs that source without ``--trust-code``
(``testbed.open(path, trust_code=True)``), and every reader runs it with it.  The modules here write a
file when they are imported: the file says whether the stored code ran.  The readers run from a folder
that is not the module's, with the module's folder not on the path.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import helpers.cli
import pytest

import testbed

ROOT = Path(testbed.__file__).resolve().parents[1]
EXAMPLES = ROOT / "docs" / "examples"

#: the first lines of each module: it writes the file $TB_MARK names when it is imported
MARKER = "import os as _os\nif _os.environ.get('TB_MARK'):\n    open(_os.environ['TB_MARK'], 'w').write('ran')\n"

#: a plant of the user's own: the bundled Lienard plant under another class (its compiled kernels are cached)
PLANT = MARKER + textwrap.dedent('''\
    from dataclasses import dataclass
    from typing import ClassVar

    from plants.lienard import Lienard


    @dataclass(frozen=True)
    class MyLienard(Lienard):
        name: ClassVar[str] = "mylienard"
    ''')

PLANT_SCENARIO = (ROOT / "testbed" / "scenario" / "bundled" / "paper.toml").read_text().replace(
    'name = "lienard"', 'name = "myplant:MyLienard"').replace(
    "K = [[-1.81, -1.90]]", "lqr = { Q = [[1.0, 0.0], [0.0, 1.0]], R = [[1.0]] }")

#: every reader of a recording: (name, argv after the recording's path or None for testbed.open)
READERS = [("report", ["report", "{rec}"]), ("report --json", ["report", "{rec}", "--json"]),
           ("export", ["export", "{rec}", "-o", "{tmp}/x.csv"]), ("compare", ["compare", "{rec}", "{rec}"]),
           ("replay", ["replay", "{rec}", "--rrd", "{tmp}/x.rrd", "--no-roa"]), ("resimulate", ["resimulate", "{rec}"]),
           ("testbed.open", None)]

#: runs every reader in this process, one after the other, and says whether the stored code ran in each;
#: with --trust-code each reader starts as a new process would (nothing pinned, the module not imported)
DRIVER = textwrap.dedent('''\
    import contextlib, io, json, os, sys
    import testbed
    from testbed.cli import COMMANDS
    from testbed.common.dispatch import run_command
    import plants.refs as refs
    import testbed.methods.registry as mreg

    readers, trust, mark = json.loads(sys.argv[1]), sys.argv[2] == "trust", os.environ["TB_MARK"]

    def fresh():
        for how, _sha, cls in list(refs._PINNED.values()):
            sys.modules.pop(cls.__module__, None)
        refs._PINNED.clear(); refs._RESOLVED.clear(); mreg._RESOLVED.clear()

    out = {}
    for name, argv in readers:
        if trust:
            fresh()
        if os.path.exists(mark):
            os.remove(mark)
        o, e = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(o), contextlib.redirect_stderr(e):
            if argv is None:
                try:
                    run = testbed.open(os.environ["TB_REC"], trust_code=trust)
                    rc, extra = 0, {"escaped": run.summary["escaped"], "x": run.arrays["x"].tolist(),
                                    "not_run": run.scenario.code_not_run()}
                except Exception as ex:
                    rc, extra = 1, {"error": repr(ex)}
            else:
                argv = argv + (["--trust-code"] if trust else [])
                rc, extra = run_command(COMMANDS[argv[0]][0], argv[0], argv[1:]), {}
        out[name] = {"rc": rc, "stdout": o.getvalue(), "stderr": e.getvalue(), "ran": os.path.exists(mark), **extra}
    print(json.dumps(out))
    ''')


def _env(tmp: Path, rec: Path) -> dict:
    return {"TB_MARK": str(tmp / "MARK"), "TB_REC": str(rec), "MPLBACKEND": "Agg"}


def _recording(tmp: Path, kind: str) -> tuple[Path, dict, Path]:
    """A recording of ``testbed simulate --out`` with a method (``kind`` "method") or a plant ("plant") of the
    user's own whose module writes $TB_MARK at import; then the module's folder moved away.  Returns the
    recording, ``simulate --json`` and an empty folder to read it from."""
    src = tmp / "src"
    src.mkdir()
    if kind == "method":
        (src / "mymethod.py").write_text(MARKER + (EXAMPLES / "mymethod.py").read_text())
        shutil.copy(EXAMPLES / "mymethod.toml", src / "s.toml")
    else:
        (src / "myplant.py").write_text(PLANT)
        (src / "s.toml").write_text(PLANT_SCENARIO)
    elsewhere = tmp / "elsewhere"
    elsewhere.mkdir()
    rec = tmp / "run.mcap"
    rc, out, err = helpers.cli.tb("simulate", src / "s.toml", "--duration", "3", "--json", "--out", rec, cwd=elsewhere,
                              env=_env(tmp, rec))
    assert rc == 0, err
    assert (tmp / "MARK").exists()  # simulate imported the user's own module from the scenario's folder: it ran
    (tmp / "MARK").unlink()
    shutil.move(src, tmp / "gone")
    return rec, json.loads(out), elsewhere


def _drive(tmp: Path, rec: Path, cwd: Path, trust: bool) -> dict:
    readers = [(n, None if a is None else [x.format(rec=rec, tmp=tmp) for x in a]) for n, a in READERS]
    env = {**os.environ, **_env(tmp, rec), "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-c", DRIVER, json.dumps(readers), "trust" if trust else "no"], cwd=cwd,
                       env=env, capture_output=True, text=True, timeout=helpers.cli.TIMEOUT)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # end to end: every reader in its own process
@pytest.mark.parametrize("kind", ["method", "plant"])
def test_no_reader_runs_stored_code_without_trust_code_and_every_reader_runs_it_with_it(tmp_path, kind):
    rec, sim, elsewhere = _recording(tmp_path, kind)
    ref = "mymethod:CenteredZoom" if kind == "method" else "myplant:MyLienard"

    got = _drive(tmp_path, rec, elsewhere, trust=False)
    assert not (tmp_path / "MARK").exists()
    for name, g in got.items():
        assert not g["ran"], f"{name} ran the code stored in the recording without --trust-code"
    for name in ("report", "report --json", "export", "compare", "replay"):
        assert got[name]["rc"] == 0, (name, got[name]["stderr"])
        note = [ln for ln in got[name]["stderr"].splitlines() if "--trust-code" in ln]
        assert note and ref in note[0] and "skipped (re-simulation" in note[0], (name, got[name]["stderr"])
    rep = json.loads(got["report --json"]["stdout"])
    assert rep["x"] == sim["x"] and rep["theta"] == sim["theta"] and rep["final_norm"] == sim["final_norm"]
    assert rep["escaped"] is None and rep["converged"] == sim["converged"]
    assert "--trust-code" in rep["resimulation"]["verdict"] and rep["resimulation"]["reproduced"] is None
    if kind == "plant":
        assert rep["plant_source"]["loaded_from"] == "not run"
    assert "IDENTICAL" in got["compare"]["stdout"]
    assert (tmp_path / "x.csv").stat().st_size > 0 and (tmp_path / "x.rrd").stat().st_size > 0
    assert got["resimulate"]["rc"] == 2 and got["resimulate"]["stdout"] == ""
    lines = got["resimulate"]["stderr"].strip().splitlines()
    assert len(lines) == 1 and "--trust-code" in lines[0] and ref in lines[0], lines
    op = got["testbed.open"]
    assert op["rc"] == 0 and op["x"] == sim["x"] and op["escaped"] is None and op["not_run"], op

    # the command itself, in its own process: exit 2 and one line naming the flag
    rc, out, err = helpers.cli.tb("resimulate", rec, cwd=elsewhere, env=_env(tmp_path, rec))
    assert rc == 2 and not (tmp_path / "MARK").exists()
    assert len(err.strip().splitlines()) == 1 and "--trust-code" in err, err

    got = _drive(tmp_path, rec, elsewhere, trust=True)
    for name, g in got.items():
        assert g["ran"], f"{name} --trust-code did not run the code stored in the recording"
        assert g["rc"] == 0, (name, g["stderr"])
    rep = json.loads(got["report --json"]["stdout"])
    assert rep["resimulation"]["reproduced"] is True and rep["escaped"] is sim["escaped"]  # the one verdict
    assert rep["x"] == sim["x"]
    assert "reproduced bit for bit" in got["resimulate"]["stdout"]
    assert got["testbed.open"]["escaped"] == rep["escaped"] and not got["testbed.open"]["not_run"]


@pytest.mark.slow  # end to end: readers in their own processes
def test_a_module_importable_from_the_users_own_path_runs_without_the_flag(tmp_path):
    """The user's own code: the module on the user's path (here PYTHONPATH) is imported as the run did."""
    rec, sim, elsewhere = _recording(tmp_path, "method")
    env = {**_env(tmp_path, rec), "PYTHONPATH": os.pathsep.join([str(ROOT), str(tmp_path / "gone")])}
    r = subprocess.run(helpers.cli.tb_cmd("report", str(rec), "--json"), cwd=elsewhere, env={**os.environ, **env},
                       capture_output=True, text=True, timeout=helpers.cli.TIMEOUT)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "MARK").exists() and "--trust-code" not in r.stderr
    rep = json.loads(r.stdout)
    assert rep["resimulation"]["reproduced"] is True and isinstance(rep["escaped"], bool)


def test_load_stored_refuses_without_trust_code_and_writes_nothing(tmp_path):
    """The one loader of stored plants and methods: without trust_code nothing is written, imported or run."""
    import hashlib

    from plants.refs import _TMP_DIRS, CodeNotTrusted, PlantRefError, check_plant_class, load_stored

    text = f"open({str(tmp_path / 'MARK')!r}, 'w').write('ran')\n"
    before = list(_TMP_DIRS)
    with pytest.raises(CodeNotTrusted, match="--trust-code") as e:
        load_stored("plant", "tb_trust_probe:X", "tb_trust_probe", "X", text, hashlib.sha256(text.encode()).hexdigest(),
                    check_plant_class, PlantRefError)
    assert "\n" not in str(e.value) and isinstance(e.value, ValueError)
    assert _TMP_DIRS == before and "tb_trust_probe" not in sys.modules and not (tmp_path / "MARK").exists()
    with pytest.raises(PlantRefError, match="not a subclass"):  # with it, the code runs (and has no plant X)
        load_stored("plant", "tb_trust_probe:X", "tb_trust_probe", "X", text, hashlib.sha256(text.encode()).hexdigest(),
                    check_plant_class, PlantRefError, trust_code=True)
    assert (tmp_path / "MARK").exists()


def test_a_stand_in_has_the_recorded_data_and_runs_nothing():
    import numpy as np

    from plants.refs import CodeNotTrusted, not_run, stand_in_plant
    from testbed.methods.registry import stand_in_method

    P = stand_in_plant("m:P", "P", 2, 1, ["mu"])
    p = P(mu=1.5)
    assert (p.n, p.m, p.params_dict(), p.name) == (2, 1, {"mu": 1.5}, "P") and "--trust-code" in not_run(P)
    for f in (lambda: p.f(np.zeros(2), np.zeros(1)), lambda: p.A, lambda: p.param_vector(), lambda: P.rhs.py):
        with pytest.raises(CodeNotTrusted):
            f()
    with pytest.raises(CodeNotTrusted, match="parameter"):
        stand_in_plant("m:P", "P", 2, 1, ["A"])  # a name the plant interface uses: no stand-in
    M = stand_in_method("m:Q", "Q", ["M", "E0"], 6)
    q = M(a=0.9)
    assert q.params == {"a": 0.9} and q.codebook(2, None).bits == 6 and not_run(q)
    for f in (lambda: q.make_encoder(None, None, None, None), lambda: q.kernel_code(None)):
        with pytest.raises(CodeNotTrusted):
            f()
