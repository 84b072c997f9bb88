"""The rule-of-thumb warnings (``testbed.scenario.rulesofthumb``): E_min against the sensor's noise and E0 against
x0, as docs/plants-and-quantizer.md states them, and the one line ``testbed simulate`` prints before it runs
(``testbed run`` prints the same lines: ``tests/live/test_status_process.py``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from testbed import cli, scenario
from testbed.analysis import noise
from testbed.scenario import rulesofthumb

EXAMPLES = Path(__file__).resolve().parents[2] / "docs" / "examples"

NOISY = """
name = "noisy"
[plant]
name = "lienard"
params = { a = 0.3333333333333333, b = 0.02 }
x0 = [0.1, 0.1]
[plant.sensor]
distribution = "normal"
scale = 1e-5
seed = 1
[quantizer]
T = 0.1
M = 6
L = 10.0
E0 = 0.1
[controller]
K = [[-1.81, -1.90]]
[attack]
kind = "intervals"
intervals = [[1.0, 1.2], [4.0, 0.8]]
[run]
duration = 3.0
"""


def test_the_e_min_rule_is_the_documented_formula():
    """E_min >= ((1 + a) b + w) / (1 - a / M): warned just below, silent at and above; no noise, no rule."""
    b, w, a, M = 1e-5, 2e-6, 1.205, 6
    need = ((1 + a) * b + w) / (1 - a / M)
    assert rulesofthumb.e_min_guarantee(b, a, M, w) == pytest.approx(need)
    assert rulesofthumb.e_min_warning(need * (1 - 1e-9), b, w, a, M) is not None
    assert rulesofthumb.e_min_warning(need, b, w, a, M) is None
    assert rulesofthumb.e_min_warning(10 * need, b, w, a, M) is None
    assert rulesofthumb.e_min_warning(0.0, 0.0, 0.0, a, M) is None
    line = rulesofthumb.e_min_warning(0.0, b, 0.0, a, M)
    assert "\n" not in line and "E_min = 0" in line and f"{((1 + a) * b) / (1 - a / M):.3g}" in line
    # the paper's numbers of the docs: 6.8 b with Lambda = e, 2.76 b with the linearized growth
    sc = scenario.load("paper")
    assert rulesofthumb.e_min_guarantee(1.0, sc.quantizer.Lambda, 6) == pytest.approx(6.8, abs=0.05)
    assert rulesofthumb.e_min_guarantee(1.0, rulesofthumb.growth(sc.make_model(), sc.T), 6) == \
        pytest.approx(2.76, abs=0.01)
    assert noise.e_min_guarantee is rulesofthumb.e_min_guarantee  # one definition for the analysis too


def test_the_e0_rule_is_x0_plus_the_noise():
    assert rulesofthumb.e0_warning(0.1, 0.1, 4e-5) is not None       # x0 on the corner, a noisy sensor
    assert rulesofthumb.e0_warning(0.1, 0.1, 0.0) is None            # no noise: Assumption 5 with equality
    assert rulesofthumb.e0_warning(0.12, 0.1, 4e-5) is None
    assert rulesofthumb.e0_warning(0.1 + 4e-5, 0.1, 4e-5) is None
    assert "0.10004" in rulesofthumb.e0_warning(0.1, 0.1, 4e-5)


def test_which_scenarios_are_warned():
    """The issue's scenario (a noisy sensor, no E_min, x0 on the corner of the first box) gets both lines;
    the docs' noisy example (E_min = 3 b, E0 = 0.12) and every bundled scenario get none."""
    lines = rulesofthumb.warnings(scenario.loads(NOISY))
    assert len(lines) == 2 and lines[0].startswith("[quantizer] E_min") and lines[1].startswith("[quantizer] E0")
    assert rulesofthumb.warnings(scenario.load(EXAMPLES / "paper-noisy.toml")) == []
    for name in scenario.bundled_names():
        assert rulesofthumb.warnings(scenario.load(name)) == [], name
    fixed = NOISY.replace("E0 = 0.1\n", "E0 = 0.2\nE_min = 2e-4\n")
    assert rulesofthumb.warnings(scenario.loads(fixed)) == []
    # a disturbance alone needs a floor too (w in the numerator)
    dist = fixed.replace('[plant.sensor]\ndistribution = "normal"\nscale = 1e-5', '[plant.disturbance]\n'
                         'distribution = "uniform"\nscale = 1e-3')
    got = rulesofthumb.warnings(scenario.loads(dist))
    assert len(got) == 1 and "E_min" in got[0] and "w = 0.001" in got[0], got
    # a method that has no E_min or E0 is not warned about them
    swapped = scenario.with_overrides(scenario.loads(NOISY), {"method": "unquantized"})
    assert swapped.method.name == "unquantized" and rulesofthumb.warnings(swapped) == []


def test_simulate_prints_each_warning_as_one_line_before_it_runs(tmp_path, capsys):
    path = tmp_path / "noisy.toml"
    path.write_text(NOISY)
    assert cli.main(["simulate", str(path), "--json"]) == 0
    cap = capsys.readouterr()
    warned = [ln for ln in cap.err.splitlines() if ln.startswith("testbed simulate: warning: ")]
    assert len(warned) == 2 and "E_min" in warned[0] and "E0" in warned[1], cap.err
    assert "warning" not in cap.out
    (tmp_path / "ok.toml").write_text(NOISY.replace("E0 = 0.1\n", "E0 = 0.2\nE_min = 2e-4\n"))
    assert cli.main(["simulate", str(tmp_path / "ok.toml"), "--json"]) == 0
    assert "warning" not in capsys.readouterr().err
    assert np.isfinite(rulesofthumb.growth(scenario.load("paper").make_model(), 0.1))
