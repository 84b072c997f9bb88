"""The channel model (testbed/loop/channel.py): seeded, prefix-stable draws; the loss chain's statistics
against its parameters; the [network] section parsed, rejected and round-tripped."""

import math
import tomllib

import numpy as np
import pytest

from testbed import scenario
from testbed.loop import channel
from testbed.loop.channel import LINKS, LinkModel, NetworkModel, draws, parse_network
from testbed.scenario.spec import ScenarioError
from testbed.scenario.write import to_toml


def _bursts(lost: np.ndarray) -> np.ndarray:
    """Lengths of the runs of consecutive losses."""
    d = np.diff(np.concatenate([[0], lost.astype(np.int8), [0]]))
    return np.flatnonzero(d == -1) - np.flatnonzero(d == 1)


def _model(**kw) -> NetworkModel:
    return NetworkModel(seed=7, links={"symbol": LinkModel(**kw)})


def test_draws_are_deterministic_and_prefix_stable():
    m = NetworkModel(seed=3, links={k: LinkModel(delay=0.004, jitter=0.002, loss=0.2, loss_burst=3.0, rate=1e5,
                                                 distribution="normal" if k == "ack" else "uniform")
                                    for k in LINKS})
    for link in LINKS:
        a, b = draws(m, link, 5000, bits=64), draws(m, link, 5000, bits=64)
        assert np.array_equal(a.lost, b.lost) and np.array_equal(a.delay, b.delay)
        for j in (0, 1, 17, 4999):
            c = draws(m, link, j, bits=64)
            assert np.array_equal(c.lost, a.lost[:j]) and np.array_equal(c.delay, a.delay[:j])
    # independent streams per link, and a different seed changes the draws
    assert not np.array_equal(draws(m, "symbol", 5000).lost, draws(m, "ack", 5000).lost)
    m2 = NetworkModel(seed=4, links=m.links)
    assert not np.array_equal(draws(m, "symbol", 5000).lost, draws(m2, "symbol", 5000).lost)


def test_delays_jitter_and_rate():
    d = draws(_model(delay=0.005, jitter=0.002), "symbol", 20000).delay
    assert d.min() >= 0.003 and d.max() <= 0.007
    assert abs(d.mean() - 0.005) < 1e-4 and abs(d.std() - 0.002 / math.sqrt(3)) < 1e-4   # U(-j, j): std j / sqrt 3
    # clipped at zero: delay 1 ms, jitter 3 ms
    d = draws(_model(delay=0.001, jitter=0.003), "symbol", 20000).delay
    assert d.min() == 0.0 and abs(np.mean(d == 0) - 1 / 3) < 0.02
    dn = draws(_model(delay=0.01, jitter=0.001, distribution="normal"), "symbol", 20000).delay
    assert abs(dn.std() - 0.001) < 5e-5
    # rate: 1000 bits at 1e5 bits/s take 10 ms more; an absent link is ideal
    assert np.allclose(draws(_model(delay=0.002, rate=1e5), "symbol", 10, bits=1000).delay, 0.012)
    e = draws(_model(loss=0.5), "actuation", 100, bits=1000)
    assert not e.lost.any() and not e.delay.any()
    assert not draws(None, "symbol", 10).lost.any()


@pytest.mark.parametrize("loss, burst", [(0.05, 1.0), (0.2, 1.0), (0.05, 4.0), (0.2, 6.0), (0.5, 2.0)])
def test_loss_rate_and_burst_length(loss, burst):
    """Over 400 000 samples (fixed seed), the realized loss rate is the model's loss and the mean burst
    length the model's loss_burst (Gilbert-Elliott) or 1 / (1 - loss) (Bernoulli: a run of independent
    losses is geometric).  Bounds are several standard deviations wide."""
    lost = draws(_model(loss=loss, loss_burst=burst), "symbol", 400_000).lost
    b = _bursts(lost)
    assert abs(lost.mean() - loss) < 0.006
    want = 1 / (1 - loss) if burst == 1 else burst
    assert abs(b.mean() - want) / want < 0.04
    if burst == 1:   # independent: the loss after a loss is as likely as any
        assert abs(lost[1:][lost[:-1]].mean() - loss) < 0.01
    else:            # Gilbert-Elliott: P(loss | loss before) = 1 - r
        assert abs(lost[1:][lost[:-1]].mean() - (1 - 1 / burst)) < 0.01


def test_parse_network_and_errors():
    m = parse_network({"seed": 5, "symbol": {"loss": 0.1, "loss_burst": 3}, "actuation": {"delay": 0.005,
                                                                                         "jitter": 0.002}})
    assert m.seed == 5 and m.link("symbol").loss_burst == 3.0 and m.link("ack").ideal
    assert parse_network(m.to_dict()) == m
    bad = [({"seed": -1}, "network.seed"), ({"seed": 1.5}, "network.seed"), ({"foo": {}}, "unknown key"),
           ({"symbol": {"loss": 1.0}}, "network.symbol.loss"), ({"symbol": {"los": 0.1}}, "unknown key"),
           ({"ack": {"loss_burst": 0.5}}, "network.ack.loss_burst"), ({"sensor": {"delay": -1}}, "network.sensor.delay"),
           ({"sensor": {"rate": 0}}, "network.sensor.rate"), ({"sensor": {"distribution": "pareto"}}, "distribution"),
           ({"symbol": {"loss": 0.9, "loss_burst": 2}}, "loss_burst"), ({"symbol": 3}, "must be a table")]
    for table, needle in bad:
        with pytest.raises(channel.ChannelError, match=needle.replace(".", r"\.")):
            parse_network(table)


def test_scenario_network_section_round_trips():
    sc = scenario.load("paper")
    assert sc.network is None
    data = tomllib.loads(sc.source)
    data["network"] = {"seed": 11, "symbol": {"loss": 0.05, "loss_burst": 2.0}, "actuation": {"delay": 0.005}}
    text = to_toml(data)
    sc2 = scenario.loads(text)
    assert sc2.network == parse_network(data["network"]) and sc2.network.seed == 11
    assert scenario.loads(to_toml(tomllib.loads(sc2.source))).network == sc2.network
    data["network"]["symbol"]["loss"] = 2
    with pytest.raises(ScenarioError, match=r"\[network\.symbol\.loss\]"):
        scenario.loads(to_toml(data))
