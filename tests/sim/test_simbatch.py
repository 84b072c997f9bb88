"""``testbed simulate`` on the batch kernel: every per-sample array and the JSON summary equal to the
per-sample loop's, bit for bit; the runs the kernel cannot take go to the loop, and say so."""

import dataclasses
import json

import numpy as np
import pytest
from helpers.sims import assert_simulators_identical, both_simulators

from testbed import cli, scenario
from testbed.sim.loop import LinkEffects
from testbed.sim.trajectory import kernel_refusal, simulate_scenario


def _sc(name, **over):
    return scenario.with_overrides(scenario.load(name), over) if over else scenario.load(name)


CASES = [
    ("paper", {}),
    ("paper", {"mode": "ideal"}),
    ("paper-escape", {}),
    ("paper-greedy", {}),
    ("pendulum", {}),
    ("cartpole", {}),
    ("paper", {"method": "zoom"}),
    ("paper", {"method": "static"}),
    ("paper", {"method": "unquantized"}),
    ("paper", {"method": "unquantized-hold"}),
    ("paper-escape", {"method": "zoom"}),
    ("paper", {"timing": "physical"}),
    ("paper", {"timing": "physical", "actuation": "arrival"}),
]


@pytest.mark.parametrize("name,over", CASES, ids=[f"{n}-{'-'.join(map(str, o.values())) or 'as-is'}" for n, o in CASES])
def test_kernel_equals_per_sample_loop_bit_for_bit(name, over):
    sc = _sc(name, **over)
    assert kernel_refusal(sc) is None
    per, bat = both_simulators(sc)
    assert len(per.t) > 0
    assert_simulators_identical(sc, per, bat)


RANDOM = {"kind": "random", "kappa_F": 0.5, "rho_F": 0.3, "kappa_D": 0.3, "rho_D": 0.25}


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("method", ["paper", "zoom", "unquantized-hold"])
def test_random_attacks(seed, method):
    sc = _sc("paper", attack={**RANDOM, "seed": seed}, method=method)
    per, bat = both_simulators(sc)
    assert per.theta.any()
    assert_simulators_identical(sc, per, bat)


@pytest.mark.slow  # half a second or more on a warm cache
def test_cartpole_random_attack_seeds():
    for seed in (4, 5):
        sc = _sc("cartpole", seed=seed)
        per, bat = both_simulators(sc)
        assert_simulators_identical(sc, per, bat)


def test_a_clamped_input():
    sc = scenario.load("paper")
    sc = dataclasses.replace(sc, controller=dataclasses.replace(sc.controller, u_max=0.05))
    per, bat = both_simulators(sc)
    assert per.counters["plant"]["clamped"] > 0
    assert_simulators_identical(sc, per, bat)


def test_a_diverging_run_stops_at_the_same_sample():
    import plants

    sc = scenario.load("paper")
    qp = dataclasses.replace(sc.quantizer, L=3.0)
    sc = dataclasses.replace(sc, quantizer=qp)
    per, bat = both_simulators(sc)
    assert_simulators_identical(sc, per, bat)
    assert plants  # the bundled registry is what the kernel accepts


def test_what_the_kernel_refuses_runs_per_sample():
    sc = scenario.load("paper")
    assert kernel_refusal(sc, LinkEffects(ack_via_attacker=True)) is not None
    assert kernel_refusal(sc, LinkEffects(corrupt=((5, "range"),))) is not None
    res = simulate_scenario(sc, effects=LinkEffects(corrupt=((5, "range"),)))
    assert res.simulator == "per-sample"
    with pytest.raises(ValueError, match="cannot run"):
        simulate_scenario(sc, effects=LinkEffects(ack_via_attacker=True), simulator="batch")
    assert simulate_scenario(sc).simulator == "batch"


def test_cli_says_which_simulator_ran(capsys):
    assert cli.main(["simulate", "paper", "--json", "--duration", "3"]) == 0
    assert json.loads(capsys.readouterr().out)["simulator"] == "batch"
    assert cli.main(["simulate", "paper", "--json", "--duration", "3", "--simulator", "per-sample"]) == 0
    assert json.loads(capsys.readouterr().out)["simulator"] == "per-sample"
    assert cli.main(["simulate", "paper", "--json", "--duration", "3", "--corrupt", "5"]) == 0
    assert json.loads(capsys.readouterr().out)["simulator"] == "per-sample"
    assert cli.main(["simulate", "paper", "--duration", "3", "--corrupt", "5", "--simulator", "batch"]) == 2
    assert "batch kernel cannot run" in capsys.readouterr().err


def test_physical_timing_with_a_drawn_latency():
    """u_k's latency drawn per sample (as --latency-from gives it), some past the deadline d T."""
    sc = _sc("paper", timing="physical", actuation="arrival")
    lat = np.random.default_rng(7).integers(0, 60_000_000, sc.n_steps)
    per, bat = both_simulators(sc, latency=lat)
    assert per.u_missing.any() and len(np.unique(per.delays)) > 10
    assert_simulators_identical(sc, per, bat)


def test_equal_where_reads_as_array_equal_of_the_selected_rows():
    """``equal_where`` (the ends' agreement of SimResult, the run tally and a recording's summary) is
    ``np.array_equal(a[mask], b[mask])``: NaN differs from NaN, -0.0 equals 0.0, 1-D and 2-D, C and F views."""
    from testbed.sim.loop import equal_where

    rng = np.random.default_rng(7)
    vals = np.array([0.0, -0.0, 1.5, np.nan, np.inf])
    for trial in range(400):
        rows, n = int(rng.integers(0, 6)), int(rng.integers(1, 3))
        shape = (rows,) if trial % 2 else (rows, n)
        a = rng.choice(vals, size=shape)
        b = a.copy() if trial % 3 else rng.choice(vals, size=shape)
        if rows and trial % 5 == 0:
            b[rng.integers(0, rows)] = np.nan
        mask = rng.random(rows) < 0.6
        if trial % 4 == 0:  # a column view of a column-major table, as a recording's columns are
            w = n if a.ndim == 2 else 1
            ta = np.asfortranarray(np.column_stack([a.reshape(rows, w), np.zeros(rows)]))
            tb = np.asfortranarray(np.column_stack([b.reshape(rows, w), np.zeros(rows)]))
            a, b = ta[:, :-1].reshape(shape), tb[:, :-1].reshape(shape)
        assert equal_where(a, b, mask) == bool(np.array_equal(a[mask], b[mask])), (a, b, mask)
