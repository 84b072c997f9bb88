"""FMU plants (plants.fmu): a real Co-Simulation FMU of the Lienard plant built from tests/fmu with gcc.

The FMU is compiled against the FMI 2.0 headers fmpy ships and stepped through
``FMUPlant`` (the ``PlantProcess`` the simulator and the plant node hold); it must
follow the flow map phi_T of the built-in Lienard plant, and every broken FMU
must give one clear line.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

import numpy as np
import pytest

import plants
from plants.base import PlantFault, PlantProcess
from plants.fmu import FMUError, FMUPlant, describe

HERE = Path(__file__).resolve().parent
IO = dict(inputs=["u"], states=["x1", "x2"])


def _build():
    spec = importlib.util.spec_from_file_location("testbed_test_fmu_build", HERE / "fmu" / "build.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


XML = (HERE / "fmu" / "modelDescription.xml").read_text()


def test_fmu_follows_phi_T_over_the_paper_scenario(lienard_fmu, paper):
    """The paper scenario's inputs, stepped open loop through the FMU and through phi_T: within 1e-6."""
    from testbed.flow import phi_T
    from testbed.simulate import simulate_scenario

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
    from testbed.flow import phi_T

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
    from testbed.simulate import simulate_scenario

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
