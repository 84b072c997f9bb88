"""Contract test over every registered plant, and the Lienard plant of the paper."""

import numpy as np
import pytest
from numpy.testing import assert_allclose

import plants
from testbed.loop.plantcheck import check_plant

ALL = plants.names()


@pytest.mark.parametrize("name", ALL)
def test_contract(name):
    """The contract of testbed.loop.plantcheck (the checks testbed check-plant runs) on every registered plant.

    Assumption 2 depends on the scenario's L, T, M: it is checked with each plant's bundled scenario.
    """
    p = plants.make(name)
    checks = {c.name: c for c in check_plant(p, grid=21)}
    assert list(checks) == ["shapes", "equilibrium", "jacobian", "remainder", "lipschitz", "assumption2",
                            "stabilizable"]
    for c in checks.values():
        if c.name != "assumption2":
            assert c.ok, f"{name}: {c.name}: {c.detail}"
    # the analytic linearization within 1e-6 of central finite differences (absolute)
    A, B = p.linearization()
    Jx, Ju = p.jacobian_fd()
    assert_allclose(A, Jx, atol=1e-6)
    assert_allclose(B, Ju, atol=1e-6)
    # the origin of the linearization is unstable for the bundled nonlinear plants
    if name != "linear":
        assert np.max(np.linalg.eigvals(A).real) > 0
    # Lipschitz estimate is positive and finite on a small box
    L = p.lipschitz(0.2, u_bound=1.0, grid=9)
    assert 0 < L < np.inf


@pytest.mark.parametrize("scenario", ["paper", "pendulum", "cartpole"])
def test_contract_with_bundled_scenario(scenario):
    from testbed import scenario as scn

    sc = scn.load(scenario)
    q = sc.quantizer
    checks = check_plant(sc.make_plant(), L=q.L, T=q.T, M=q.M, grid=21)
    assert all(c.ok for c in checks), [c for c in checks if not c.ok]


def test_check_plant_finds_faults():
    """Each check fails on a plant broken in its way (the verdict names it)."""
    lin = plants.make("linear", A=[[0.0, 1.0], [2.0, -1.0]], B=[[0.0], [1.0]])

    class WrongA(type(lin)):
        def linearization(self):
            A, B = super().linearization()
            return A + np.array([[0.0, 0.0], [0.5, 0.0]]), B

    bad = {c.name: c for c in check_plant(WrongA(lin.A_, lin.B_))}
    assert not bad["jacobian"].ok and "A_fd" in bad["jacobian"].detail
    assert all(c.ok for n, c in bad.items() if n not in ("jacobian", "remainder"))
    # uncontrollable unstable mode: x2' = x2, u enters x1 only
    unstab = plants.make("linear", A=[[-1.0, 0.0], [0.0, 1.0]], B=[[1.0], [0.0]])
    c = {c.name: c for c in check_plant(unstab)}
    assert not c["stabilizable"].ok and "uncontrollable" in c["stabilizable"].detail
    # Lipschitz above the stated L, and Assumption 2 broken by that L
    c = {c.name: c for c in check_plant(plants.make("lienard"), L=5.0, T=0.5, M=6)}
    assert not c["lipschitz"].ok and not c["assumption2"].ok


def test_registry_errors():
    with pytest.raises(ValueError, match="unknown plant 'nope'.*lienard"):
        plants.make("nope")
    with pytest.raises(ValueError, match="unknown parameter.*'c'"):
        plants.make("lienard", c=1.0)
    with pytest.raises(ValueError, match="must be > 0"):
        plants.make("pendulum", l=0.0)
    with pytest.raises(ValueError, match="square"):
        plants.make("linear", A=[[1.0, 2.0]], B=[[1.0]])


def test_lienard_is_the_paper_plant():
    p = plants.make("lienard", a=1 / 3, b=1 / 50)
    x = np.array([0.7, -0.2])
    a, b = 1 / 3, 1 / 50
    assert_allclose(p.f(x, [0.3]), [x[1] + x[0] + a * x[0] ** 3 - b * x[0] ** 5, -x[0] + 0.3], rtol=1e-15)
    # the paper's L = 10 holds on a region larger than the nominal region of attraction
    assert p.lipschitz(p.lipschitz_region, grid=81) <= 10.0
    assert p.lipschitz(5.0, grid=81) > 10.0


def test_cartpole_has_n4():
    p = plants.make("cartpole")
    assert (p.n, p.m) == (4, 1)
