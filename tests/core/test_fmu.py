"""FMU plants (plants.fmu): a real Co-Simulation FMU of the Lienard plant built from tests/data/fmu with gcc.

The FMU is compiled against the FMI 2.0 headers fmpy ships and stepped through
``FMUPlant`` (the ``PlantProcess`` the simulator and the plant node hold); it must
follow the flow map phi_T of the built-in Lienard plant, and every broken FMU
must give one clear line.
"""

from __future__ import annotations

import importlib.util
import json
import os
import secrets
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers.cli import tb
from helpers.live import live, live_exact

import plants
from plants.base import PlantFault, PlantProcess
from plants.fmu import FMUError, FMUPlant, describe

DATA = Path(__file__).resolve().parents[1] / "data"  # tests/data
IO = dict(inputs=["u"], states=["x1", "x2"])


def _build():
    spec = importlib.util.spec_from_file_location("testbed_test_fmu_build", DATA / "fmu" / "build.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


XML = (DATA / "fmu" / "modelDescription.xml").read_text()


def test_fmu_follows_phi_T_over_the_paper_scenario(lienard_fmu, paper):
    """The paper scenario's inputs, stepped open loop through the FMU and through phi_T: within 1e-6."""
    from testbed.loop.flow import phi_T
    from testbed.sim.batch import simulate_scenario

    res = simulate_scenario(paper)
    lin = paper.make_plant()
    with FMUPlant(lienard_fmu, **IO, params={"a": lin.a, "b": lin.b}) as p:
        assert isinstance(p, PlantProcess) and (p.n, p.m) == (2, 1)
        p.reset(paper.x0)
        assert np.array_equal(p.x, paper.x0)
        x = paper.x0.copy()
        err = 0.0
        traj = []
        for k in range(len(res.t)):
            assert p.advance(res.u[k], paper.T) == 0
            x = phi_T(lin, x, res.u[k], paper.T, paper.flow)[0]
            err = max(err, float(np.abs(p.x - x).max()))
            traj.append(p.x)
        assert err < 1e-6, err
        assert float(np.abs(p.x - res.x_final).max()) < 1e-6
        # the closed loop's own states too (the simulator's x_k)
        assert float(np.abs(np.array(traj[:-1]) - res.x[1:]).max()) < 1e-6
        # dt = 0 is a no-op; a second reset reproduces the run bit for bit
        before, t = p.x, p.t
        assert p.advance([5.0], 0.0) == 0
        assert np.array_equal(p.x, before) and p.t == t
        p.reset(paper.x0)
        again = []
        for k in range(len(res.t)):
            p.advance(res.u[k], paper.T)
            again.append(p.x)
        assert np.array_equal(np.array(again), np.array(traj))
        # the returned state is a copy
        p.x[0] = 99.0
        assert p.x[0] != 99.0


def test_fmu_parameters_are_set(lienard_fmu):
    """Real and Integer FMU parameters take effect at reset (a = b = 0: the linear part only)."""
    from testbed.loop.flow import phi_T

    lin0 = plants.make("lienard", a=0.0, b=0.0)
    x0 = np.array([1.5, -0.5])
    with FMUPlant(lienard_fmu, **IO, params={"a": 0.0, "b": 0.0}) as p:
        p.reset(x0)
        p.advance([0.3], 0.1)
        assert np.abs(p.x - phi_T(lin0, x0, [0.3], 0.1)[0]).max() < 1e-9
    with FMUPlant(lienard_fmu, **IO, params={"a": 0.0, "b": 0.0, "n_sub": 1}) as p:  # one RK4 step: less exact
        p.reset(x0)
        p.advance([0.3], 0.1)
        assert 1e-9 < np.abs(p.x - phi_T(lin0, x0, [0.3], 0.1)[0]).max() < 1e-4


def test_failed_step_is_a_plant_fault(lienard_fmu):
    with FMUPlant(lienard_fmu, **IO, params={"fail_at": 0.15}) as p:
        p.reset([0.1, 0.1])
        p.advance([0.0], 0.1)
        p.advance([0.0], 0.1)
        with pytest.raises(PlantFault) as e:
            p.advance([0.0], 0.1)
        line = str(e.value)
        assert "\n" not in line and "step from t = 0.2 s" in line and "the plant broke at t = 0.2" in line
        with pytest.raises(PlantFault, match="before reset"):  # the failed FMU is not stepped again
            p.advance([0.0], 0.1)
        p.reset([0.1, 0.1])    # but it can be reset
        p.advance([0.0], 0.1)
    with pytest.raises(PlantFault, match="closed"):
        p.reset([0.0, 0.0])


def test_broken_fmus_give_one_clear_line(lienard_fmu, tmp_path, monkeypatch):
    b = _build()

    def err(path, **kw) -> str:
        kw = {**IO, **kw}
        with pytest.raises(FMUError) as e:
            FMUPlant(path, **kw).close()
        line = str(e.value)
        assert "\n" not in line, line
        return line

    assert "no such FMU file" in err(tmp_path / "nope.fmu")
    junk = tmp_path / "junk.fmu"
    junk.write_bytes(b"PK\x03\x04 this is not a zip archive")
    assert "not a zip archive" in err(junk)
    assert "no binary for this platform (linux64)" in err(b.variant(lienard_fmu, tmp_path / "nobin.fmu",
                                                                    drop_binary=True))
    cwd = os.getcwd()
    assert "cannot load the FMU's binary" in err(b.variant(lienard_fmu, tmp_path / "badso.fmu",
                                                           binary=b"\x7fELF garbage"))
    assert os.getcwd() == cwd
    assert "no variable 'x3' (states); the FMU has: a, b, fail_at, n_sub, u, x1, x2" in \
        err(lienard_fmu, states=["x1", "x3"])
    assert "no variable 'w' (inputs)" in err(lienard_fmu, inputs=["w"])
    assert "'x1' is a Real output, not a Real input" in err(lienard_fmu, inputs=["x1"])
    assert "no variable 'c' (params)" in err(lienard_fmu, params={"c": 1.0})
    assert "'n_sub' is Integer, got 2.5" in err(lienard_fmu, params={"n_sub": 2.5})
    assert "'u' is a continuous input, not a parameter" in err(lienard_fmu, params={"u": 1.0})
    calc = XML.replace('name="x2" valueReference="1" causality="output" variability="continuous" initial="exact"',
                       'name="x2" valueReference="1" causality="output" variability="continuous" '
                       'initial="calculated"').replace('state x2">\n      <Real start="0"/>', 'state x2">\n      <Real/>')
    assert "initial = 'calculated'" in err(b.variant(lienard_fmu, tmp_path / "calc.fmu", model_description=calc))
    me = XML.replace('<CoSimulation modelIdentifier="lienard" canHandleVariableCommunicationStepSize="true"/>',
                     '<ModelExchange modelIdentifier="lienard"/>')
    assert "Model Exchange" in err(b.variant(lienard_fmu, tmp_path / "me.fmu", model_description=me))
    assert "cannot read modelDescription.xml: Opening and ending tag mismatch" in \
        err(b.variant(lienard_fmu, tmp_path / "bad.fmu", model_description=XML.replace("<ModelVariables>", "<M>")))
    assert "invalid modelDescription.xml" in \
        err(b.variant(lienard_fmu, tmp_path / "xsd.fmu", model_description=XML.replace("ModelVariables>", "Vars>")))
    # fmpy missing: one line naming the extra
    monkeypatch.setitem(sys.modules, "fmpy", None)
    assert "pip install 'dos-testbed[fmu]'" in err(lienard_fmu)


def test_scenario_fmu_keys(lienard_fmu, tmp_path):
    """[plant] fmu (relative to the scenario's folder): checked at load; needs a [model] section."""
    from testbed import scenario

    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "plant.fmu").write_bytes(Path(lienard_fmu).read_bytes())
    body = ('[plant]\nfmu = "plant.fmu"\ninputs = ["u"]\nstates = [{states}]\nparams = {{ a = 0.3333 }}\n'
            'x0 = [0.1, 0.1]\n[quantizer]\nT = 0.1\nM = 6\nL = 10.0\nE0 = 0.1\n[controller]\nK = [[-1.81, -1.90]]\n'
            '[run]\nduration = 1.0\n')
    f = tmp_path / "sub" / "fmu.toml"
    f.write_text(body.format(states='"x1", "x2"'))
    with pytest.raises(scenario.ScenarioError, match=r"an FMU plant needs a \[model\] section"):
        scenario.load(f)
    f.write_text(body.format(states='"x1", "y"'))
    with pytest.raises(scenario.ScenarioError, match=r"\[plant.fmu\] .*no variable 'y' \(states\)"):
        scenario.load(f)
    f.write_text(body.format(states='"x1", "x2"').replace('"plant.fmu"', '"missing.fmu"'))
    with pytest.raises(scenario.ScenarioError, match=f"{tmp_path}/sub/missing.fmu: no such FMU file"):
        scenario.load(f)
    f.write_text(body.format(states='"x1", "x2"').replace('[plant]\n', '[plant]\nname = "lienard"\n'))
    with pytest.raises(scenario.ScenarioError, match="either name"):
        scenario.load(f)
    info = describe(tmp_path / "sub" / "plant.fmu", **IO)
    assert (info.n, info.m, info.model_identifier) == (2, 1, "lienard")
    # with a [model]: the FMU is the true plant process, the model the predictions' plant
    f.write_text(body.format(states='"x1", "x2"') + '[model]\n')
    with pytest.raises(scenario.ScenarioError, match=r"\[model.name\] missing"):
        scenario.load(f)
    f.write_text(body.format(states='"x1", "x2"') + '[model]\nname = "lienard"\nparams = { a = 0.2 }\n')
    sc = scenario.load(f)
    assert sc.plant.name == "fmu:plant.fmu" and sc.make_model().a == 0.2
    with sc.make_process() as proc:
        assert isinstance(proc, FMUPlant) and (proc.n, proc.m) == (2, 1)
    f.write_text(body.format(states='"x1"').replace("x0 = [0.1, 0.1]", "x0 = [0.1]") + '[model]\nname = "lienard"\n')
    with pytest.raises(scenario.ScenarioError, match="lienard has n = 2, m = 1; the plant fmu:plant.fmu has n = 1"):
        scenario.load(f)


def test_paper_scenario_with_the_fmu_as_true_plant(lienard_fmu, tmp_path):
    """The paper's loop with the FMU as [plant] and the built-in Lienard as [model]: the built-in run's states.

    E_min = 1e-9 in both: the paper's E_k falls to 1e-87, below any difference of two
    integrators (here 3e-13), and a box that small makes the quantizer saturate on it.
    """
    from testbed import scenario
    from testbed.sim.batch import simulate_scenario

    text = scenario.load("paper").source.replace('mode = "resilient"', 'mode = "resilient"\nE_min = 1e-9')
    (tmp_path / "lienard.fmu").write_bytes(Path(lienard_fmu).read_bytes())
    (tmp_path / "builtin.toml").write_text(text)
    fmu_text = text.replace('[plant]\nname = "lienard"\n', '[plant]\nfmu = "lienard.fmu"\ninputs = ["u"]\n'
                            'states = ["x1", "x2"]\n') + '\n[model]\nname = "lienard"\n' \
        'params = { a = 0.3333333333333333, b = 0.02 }\n'
    (tmp_path / "fmu.toml").write_text(fmu_text)
    ref = simulate_scenario(scenario.load(tmp_path / "builtin.toml"))
    res = simulate_scenario(scenario.load(tmp_path / "fmu.toml"))
    assert np.abs(res.x - ref.x).max() < 1e-6 and np.abs(res.x_final - ref.x_final).max() < 1e-6
    assert not res.saturated.any() and np.array_equal(res.theta, ref.theta)


# ====================================================================== plant faults, the analysis, live runs
def fmu_scenario(tmp_path, lienard_fmu, fmu_params: str = "", name: str = "fmu.toml") -> Path:
    """The paper scenario with the test FMU as [plant] (``fmu_params``: its params table) and the built-in
    Lienard as [model], E_min = 1e-9 (see test_paper_scenario_with_the_fmu_as_true_plant)."""
    from testbed import scenario

    text = scenario.load("paper").source.replace('mode = "resilient"', 'mode = "resilient"\nE_min = 1e-9')
    if not (tmp_path / "lienard.fmu").exists():
        (tmp_path / "lienard.fmu").write_bytes(Path(lienard_fmu).read_bytes())
    text = text.replace('[plant]\nname = "lienard"\nparams = { a = 0.3333333333333333, b = 0.02 }\n',
                        '[plant]\nfmu = "lienard.fmu"\ninputs = ["u"]\nstates = ["x1", "x2"]\n'
                        + (f"params = {{ {fmu_params} }}\n" if fmu_params else "")) \
        + '\n[model]\nname = "lienard"\nparams = { a = 0.3333333333333333, b = 0.02 }\n'
    (tmp_path / name).write_text(text)
    return tmp_path / name


def test_two_fmu_plants_in_one_process_keep_their_own_log(lienard_fmu):
    """Each FMUPlant's fault line carries its own FMU's message, after another FMUPlant came and went
    (fmpy's message formatter holds one process-wide logger: a freed one crashed the process)."""
    import gc

    a = FMUPlant(lienard_fmu, **IO, params={"fail_at": 0.15})
    b = FMUPlant(lienard_fmu, **IO, params={"fail_at": 0.05})
    a.reset([0.1, 0.1])
    b.reset([0.1, 0.1])
    b.advance([0.0], 0.1)
    with pytest.raises(PlantFault, match=r"fail_at = 0\.05"):
        b.advance([0.0], 0.1)
    b.close()
    del b
    gc.collect()
    a.advance([0.0], 0.1)
    a.advance([0.0], 0.1)
    with pytest.raises(PlantFault, match=r"the plant broke at t = 0\.2 s \(fail_at = 0\.15\)"):
        a.advance([0.0], 0.1)
    a.close()


@pytest.mark.slow  # half a second or more on a warm cache
def test_plant_fault_stops_the_simulation_and_is_reported(lienard_fmu, tmp_path, capsys):
    """A failing FMU step ends testbed simulate at that sample: the samples before it are the good FMU's,
    the fault is in the JSON and in one line on stderr, exit 1; a failing reset is a run of no samples."""
    from testbed import cli, scenario
    from testbed.sim.batch import simulate_scenario, summarize

    good = simulate_scenario(scenario.load(fmu_scenario(tmp_path, lienard_fmu, name="good.toml")))
    bad_sc = scenario.load(fmu_scenario(tmp_path, lienard_fmu, "fail_at = 1.0", name="bad.toml"))
    res = simulate_scenario(bad_sc)
    k = res.plant_fault_at
    assert k == 11 and len(res.t) == k + 1   # the FMU's t = 1.1 s >= fail_at (0.1 summed ten times < 1.0)
    assert "the plant broke at t = 1.1 s (fail_at = 1)" in res.plant_fault and "\n" not in res.plant_fault
    assert np.array_equal(res.x, good.x[:k + 1]) and np.array_equal(res.u, good.u[:k + 1])
    assert np.array_equal(res.x_final, good.x[k])   # the state at the fault: the failed step moved nothing
    out = summarize(bad_sc, res)
    assert out["plant_fault"] == res.plant_fault and out["plant_fault_at"] == 11
    assert out["diverged"] and not out["converged"] and out["diverged_at"] == 11
    assert summarize(bad_sc, good)["plant_fault"] is None
    assert cli.main(["simulate", str(tmp_path / "bad.toml"), "--json"]) == 1
    cap = capsys.readouterr()
    assert json.loads(cap.out)["plant_fault_at"] == 11
    assert cap.err.count("\n") == 1 and "testbed simulate: plant fault at sample 11 (t = 1.1 s): FMU lienard.fmu: " \
        "step from t = 1.1 s by 0.1 s failed" in cap.err
    res0 = simulate_scenario(scenario.load(fmu_scenario(tmp_path, lienard_fmu, "n_sub = 0", name="bad0.toml")))
    assert len(res0.t) == 0 and res0.plant_fault_at == 0 and "initialization failed" in res0.plant_fault
    assert "n_sub must be >= 1" in res0.plant_fault


def test_analysis_that_needs_the_true_plant_refuses_an_fmu(lienard_fmu, tmp_path, capsys):
    """The batch simulator integrates equation (1) plants only: one line, exit 2; the model's theorems run."""
    from testbed import cli

    f = str(fmu_scenario(tmp_path, lienard_fmu))
    for cmd in (["sweep", f], ["worst-attack", f], ["vulnerability", f], ["roa", f, "--vulnerable"],
                ["analyze", f, "--full"]):
        assert cli.main(cmd) == 2, cmd
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "the true plant is the FMU lienard.fmu, which the batch simulator" in err
        assert 'whose [plant] is its [model] (name = "lienard")' in err
    assert cli.main(["roa", f, "--grid", "5", "--horizon", "1", "--workers", "1", "--no-progress", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert (d["plant"], d["model"]) == ("fmu:lienard.fmu", "lienard")


def _where(tmp_path) -> dict:
    """Where an FMU run runs: in ``tmp_path``, the processes' temporary files (the extracted FMUs) in
    ``tmp_path/tmp``, the node logs in ``tmp_path/logs/RUN_ID``."""
    (tmp_path / "tmp").mkdir(exist_ok=True)
    return {"cwd": tmp_path, "env": {"TMPDIR": str(tmp_path / "tmp")}, "logs": tmp_path / "logs"}


def _live_exact(tmp_path, scenario_file, rid: str, *args):
    """``helpers.live.live_exact`` of an FMU run (the one rerun policy: a stalled run is run again, run id ``rid`` +
    "r" per rerun, the last run is returned to be compared); no attempt may leave a process behind."""
    return live_exact(rid, scenario_file, *args, no_leftovers=True, what=f"FMU run {scenario_file}", **_where(tmp_path))


@pytest.mark.process
def test_live_run_with_the_fmu_as_true_plant_equals_its_simulation(lienard_fmu, tmp_path):
    """testbed run with the FMU in the plant node, ideal timing: testbed simulate of it, bit for bit."""
    from helpers.live import BIT_EXACT_KEYS, mismatch

    f = fmu_scenario(tmp_path, lienard_fmu)
    rid = f"t{os.getpid()}xfmu{secrets.token_hex(3)}"
    rc, s, err = _live_exact(tmp_path, f, rid, "--duration", "3", "--no-record")
    assert rc == 0, (s.get("faults"), err[-2000:])
    assert s["complete"] and s["samples"] == 30 and s["plant"] == "fmu:lienard.fmu" and s["model"] == "lienard"
    rc, out, err = tb("simulate", f, "--duration", "3", "--json", cwd=tmp_path)
    assert rc == 0, err
    sim = json.loads(out)
    for key in BIT_EXACT_KEYS:
        assert s[key] == sim[key], mismatch(s, sim, key)
    assert s["plant_fault"] is None
    assert not list((tmp_path / "tmp").glob("testbed-fmu-*")), "the plant node left an extracted FMU behind"


@pytest.mark.process
def test_fmu_failing_mid_run_ends_the_live_run_as_a_plant_fault(lienard_fmu, tmp_path):
    """doStep fails from t = 1.1 s: exit 1, a fault entry naming it, the recording readable up to the fault
    (testbed report: the samples testbed simulate has up to its fault); a failing reset: a startup failure."""
    from helpers.live import BIT_EXACT_KEYS
    from helpers.procs import reap

    f = fmu_scenario(tmp_path, lienard_fmu, "fail_at = 1.0")
    rec = tmp_path / "fault.mcap"
    rid = f"t{os.getpid()}xfmuf{secrets.token_hex(3)}"
    rc, s, err = _live_exact(tmp_path, f, rid, "--duration", "3", "--out", rec)
    assert rc == 1, err[-2000:]
    assert s["plant_fault_at"] == 11 and "the plant broke at t = 1.1 s" in s["plant_fault"]
    (fault,) = s["faults"]
    assert fault["node"] == "plant" and fault["kind"] == "plant_fault" and fault["exit_code"] == 1
    assert fault["at_sample"] == 11 and s["outcome"] == "plant fault at sample 11"
    assert "plant_fault k=11 FMU lienard.fmu: step from t = 1.1 s by 0.1 s failed" in fault["last_log_line"]
    assert "Traceback" not in Path(s["nodes"]["plant"]["log"]).read_text()   # the last attempt's log (a rerun has its own id)
    assert s["node_summaries"]["plant"]["plant_fault_at"] == 11
    assert s["node_summaries"]["encoder"]["stop_reason"].startswith("stop from plant: plant fault at sample 11: ")
    rc, out, err = tb("report", rec, "--json", cwd=tmp_path)
    assert rc == 0, err
    rep = json.loads(out)
    rc, out, _ = tb("simulate", f, "--duration", "3", "--json", cwd=tmp_path)
    assert rc == 1
    sim = json.loads(out)
    assert rep["samples"] == 12 and rep["plant_fault"] == sim["plant_fault"] and rep["plant_fault_at"] == 11
    for key in BIT_EXACT_KEYS:
        assert rep[key] == sim[key], key
    assert rep["resimulation"]["reproduced"] is True
    # the FMU cannot even initialize: the plant node fails at start-up, with the FMU's line in its log
    f0 = fmu_scenario(tmp_path, lienard_fmu, "n_sub = 0", name="bad0.toml")
    rid0 = rid + "s"
    try:
        rc, s, err = live(rid0, f0, "--duration", "3", "--no-record", **_where(tmp_path))
    finally:
        assert not reap(rid0)
    assert rc == 1 and s["samples"] == 0 and s["outcome"] == "plant exited before the start"
    line = "testbed node plant: startup failed: plant fault: FMU lienard.fmu: initialization failed"
    assert any(line in (x.get("last_log_line") or "") and "n_sub must be >= 1" in x["last_log_line"]
               for x in s["faults"]), s["faults"]
    assert (tmp_path / "logs" / rid0 / "plant.log").read_text().strip().startswith(line)
