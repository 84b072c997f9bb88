"""One wording for an input's numbers, ranges and choices (``testbed/common/validate.py``): the checks' phrases,
and the same phrase behind each parser's field name (the scenario, its [network] and device tables, a
method's parameters, a campaign file, ``testbed run``'s ROLE@VALUE flags)."""

import math
from importlib import resources
from pathlib import Path

import pytest

from testbed import scenario
from testbed.campaign import spec
from testbed.common import validate
from testbed.common.errors import BadInput
from testbed.scenario.spec import ScenarioError

PAPER = resources.files("testbed").joinpath("scenario/bundled/paper.toml").read_text()


@pytest.mark.parametrize("value,kw,phrase", [
    ("x", {}, "must be a number, got 'x'"),
    (True, {}, "must be a number, got True"),
    (math.nan, {}, "must be finite, got nan"),
    (math.inf, {}, "must be finite, got inf"),
    (-math.inf, {"allow_inf": True}, "must be finite, got -inf"),
    (2.5, {"integer": True}, "must be an integer, got 2.5"),
    (0, {"lo": 0, "lo_open": True}, "must be > 0, got 0"),
    (-1, {"lo": 0}, "must be >= 0, got -1"),
    (1.0, {"hi": 1, "hi_open": True}, "must be < 1, got 1.0"),
    (2, {"hi": 1.5}, "must be <= 1.5, got 2"),
])
def test_number_phrases(value, kw, phrase):
    with pytest.raises(validate.Invalid) as e:
        validate.number(value, **kw)
    assert str(e.value) == phrase


def test_what_passes_comes_back_typed():
    assert validate.number(3.0, integer=True) == 3 and type(validate.number(3.0, integer=True)) is int
    assert validate.number(math.inf, lo=0, lo_open=True, allow_inf=True) == math.inf
    assert validate.count(0) == 0 and validate.choice("b", ("a", "b")) == "b"
    assert validate.text_number("2", int) == 2 and validate.positive(1) == 1.0
    for bad, check, phrase in [(1.0, lambda v: validate.count(v, 0), "must be an integer >= 0, got 1.0"),
                               (0, validate.positive, "must be a positive number, got 0"),
                               ("c", lambda v: validate.choice(v, ("a", "b")), "must be one of 'a', 'b', got 'c'"),
                               ("x", validate.text_number, "'x' is not a number"),
                               ("-1", validate.text_number, "'-1' is not a finite number >= 0")]:
        with pytest.raises(validate.Invalid, match="^" + phrase.replace(".", r"\.") + "$"):
            check(bad)


def _error(text: str) -> str:
    with pytest.raises(ScenarioError) as e:
        scenario.loads(text, where="s.toml")
    return str(e.value)


def test_every_scenario_parser_gives_the_phrase_behind_its_field():
    assert _error(PAPER.replace("T = 0.1", "T = -1")) == "s.toml: [quantizer.T] must be > 0, got -1"
    assert _error(PAPER + '\n[network]\nsensor = {delay = -1}\n').endswith("[network.sensor.delay] must be >= 0, got -1")
    assert _error(PAPER + '\n[network]\nsensor = {distribution = "pareto"}\n').endswith(
        "[network.sensor.distribution] must be one of 'uniform', 'normal', got 'pareto'")  # the jitter's default first
    assert _error(PAPER + '\n[plant.sensor]\nscale = nan\n') == "s.toml: [plant.sensor.scale] must be finite, got nan"
    assert _error(PAPER + '\n[plant.sensor]\nscale = 1e-3\nseed = -2\n') == \
        "s.toml: [plant.sensor.seed] must be an integer >= 0, got -2"
    assert _error(PAPER + '\n[plant.disturbance]\nscale = 1e-3\ndistribution = "x"\n') == \
        "s.toml: [plant.disturbance.distribution] must be one of 'normal', 'uniform', got 'x'"  # the noise's first


def test_campaign_method_and_flag_parsers_give_the_phrase():
    with pytest.raises(BadInput, match=r"c\.toml: seed must be an integer >= 0, got -1$"):
        spec.loads('scenario = "paper"\nseed = -1\n', Path("c.toml"))
    from testbed.nodes.options import _number
    with pytest.raises(BadInput, match=r"^--kill: 'x' is not a number$"):
        _number(float, "x", "--kill")
    from testbed.methods import MethodError, make
    with pytest.raises(MethodError, match=r"^method 'static': parameter range must be a positive number, got -1$"):
        make("static", params={"range": -1})


def test_command_flags_give_the_phrase(capsys):
    """A command's flag checked by ``validate.flag``: one line naming the flag, exit 2."""
    from testbed import cli

    for argv, line in [(["check-plant", "pendulum", "--M", "1"], "--M must be an integer >= 2, got 1"),
                       (["check-plant", "pendulum", "--T", "-0.5"], "--T must be a positive number, got -0.5"),
                       (["worst-attack", "paper", "--beam", "0"], "--beam must be >= 1, got 0")]:
        assert cli.main(argv) == 2
        err = capsys.readouterr().err
        assert line in err and len(err.strip().splitlines()) == 1, err
