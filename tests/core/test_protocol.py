"""The protocol core (testbed/loop/protocol.py), actuation delays in both simulators, the delay-aware rule."""

import math
import tomllib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import plants
from testbed import scenario
from testbed.loop.flow import phi_T
from testbed.loop.protocol import (
    DEADLINE,
    INVALID,
    RECEIVED,
    SUPERSEDED,
    ControllerProtocol,
    EncoderProtocol,
    OdeProcess,
    PlantProtocol,
    Send,
    Withhold,
)
from testbed.loop.quantizer import delay_margin_gain
from testbed.methods.bundled import PaperMethod
from testbed.sim.batch import simulate_batch, simulate_scenario
from testbed.sim.loop import LinkEffects, OnlineAttacker, simulate_loop


def physical(name: str, **run) -> scenario.Scenario:
    """A bundled scenario under physical timing with extra [run] keys."""
    sc0 = scenario.load(name)
    d = tomllib.loads(sc0.source)
    d["run"]["timing"] = "physical"
    d["run"].update(run)
    return scenario.from_dict(d, name=sc0.name, source=sc0.source)


# ============================================================================ the state machines
def _ends(sc):
    model, paper = sc.make_model(), PaperMethod()
    return paper.make_encoder(model, sc.K, sc.quantizer, sc.flow), paper.make_decoder(model, sc.K, sc.quantizer, sc.flow)


def test_encoder_withholds_until_an_ack_resolves_and_recovers_theta_from_last_rx(paper):
    enc, dec = _ends(paper)
    ep, cp = EncoderProtocol(enc, 10), ControllerProtocol(dec, 10)
    x = paper.x0
    s0 = ep.sensor(0, x)
    assert isinstance(s0, Send)
    d0 = cp.symbol(0, cp.codebook.pack(s0.symbol))[0]
    assert d0.reason == RECEIVED and d0.theta == 0 and d0.last_rx == 0
    # the ack of sample 0 is lost: sample 1 is withheld (a new episode), sample 2 too
    w1 = ep.sensor(1, x)
    assert isinstance(w1, Withhold) and w1.first and w1.pending == 0
    d1 = cp.deadline(1)
    assert d1.reason == DEADLINE and d1.theta == 1 and d1.last_rx == 0
    w2 = ep.sensor(2, x)
    assert isinstance(w2, Withhold) and not w2.first
    # the ack of sample 1 (theta = 1, last_rx = 0) tells the encoder theta_0 = 0
    assert ep.ack(d1.k, d1.theta, d1.last_rx) == "resync"
    d2 = cp.deadline(2)
    assert ep.ack(d2.k, d2.theta, d2.last_rx) == "stale"
    assert ep.pending is None and enc.k == 3 == dec.k
    assert enc.xi.tolist() == dec.xi.tolist() and enc.E == dec.E
    assert ep.counters()["withheld"] == 2 and ep.counters()["desync_episodes"] == 1


def test_controller_decides_in_order_and_rejects_late_future_and_invalid(paper):
    enc, dec = _ends(paper)
    cp = ControllerProtocol(dec, 10)
    cb = cp.codebook
    # a symbol for sample 3 arrives first: 0, 1, 2 are superseded (lost)
    decs = cp.symbol(3, cb.pack(0), newest_k=3)
    assert [d.k for d in decs] == [0, 1, 2, 3]
    assert [d.reason for d in decs] == [SUPERSEDED] * 3 + [RECEIVED]
    assert cp.symbol(2, cb.pack(0)) == [] and cp.late == 1
    # a header naming a sample whose instant has not come: rejected, nothing decided
    assert cp.symbol(9, cb.pack(0), newest_k=4) == [] and cp.future == 1 and cp.next_k == 4
    # an invalid payload is a loss
    d = cp.symbol(4, b"\xff\xff", newest_k=4)[0]
    assert d.reason == INVALID and d.theta == 1 and cp.invalid == 1
    assert cp.deadline(7) is None and cp.deadline(5).reason == DEADLINE


def test_deferred_decoder_update_changes_no_number(paper):
    """The live controller sends u_k before the decoder's prediction for k+1 (``defer_update``, settled
    after the send or by the next decision): every decision and state equals the undeferred one."""
    rng = np.random.default_rng(3)
    cps = [ControllerProtocol(_ends(paper)[1], 40, defer_update=d) for d in (False, True)]
    cb = cps[0].codebook
    out = [[], []]
    for k in range(40):
        r = rng.random()
        for i, cp in enumerate(cps):
            if r < 0.2:
                decs = [cp.deadline(k)]
            elif r < 0.3:
                decs = cp.symbol(k, b"\xff\xff")
            elif r < 0.4 and k + 1 < 40:
                continue  # superseded by the next sample's symbol
            else:
                decs = cp.symbol(k, cb.pack(int(rng.integers(0, cb.n_codes)) if i == 0 else out[0][-1][1]))
            out[i].extend((d.k, d.symbol, d.theta, d.u.tolist(), d.xi.tolist(), d.E, d.reason) for d in decs)
            if i == 1 and rng.random() < 0.5:
                cp.settle()  # sometimes settled after the send, sometimes by the next decision
    cps[1].settle()
    assert out[0] == out[1]
    assert cps[0].dec.xi.tolist() == cps[1].dec.xi.tolist() and cps[0].dec.E == cps[1].dec.E
    d = cps[1].dec
    d.decide(0)
    with pytest.raises(RuntimeError):
        d.decide(0)  # a decision before the last one's update: refused


def test_plant_checks_inputs_and_applies_the_actuation_policy(paper):
    proc = OdeProcess(paper.make_plant())
    pp = PlantProtocol(proc, 0.1, timing="physical", actuation="scheduled", sched_ns=20_000_000,
                       deadline_ns=50_000_000, loss_ns=40_000_000, u_max=5.0)
    assert pp.check_input([np.nan]) == (None, "nonfinite")
    u, fault = pp.check_input([1e12])
    assert fault == "clamped" and u.tolist() == [5.0]
    assert pp.check_input([0.5])[1] is None
    assert pp.delay_ns(3_000_000, 0) == 20_000_000      # early: at its scheduled instant
    assert pp.delay_ns(31_000_000, 0) == 31_000_000     # late: on arrival
    assert pp.delay_ns(41_000_000, 1) == 50_000_000     # a lost sample's u = 0 at the deadline
    pp.actuation = "arrival"
    assert pp.delay_ns(3_000_000, 0) == 3_000_000 and pp.delay_ns(-5, 0) == 0
    # hold u_{k-1} for delta, then u_k: the same flow map as the simulators
    proc.reset(paper.x0)
    pp.u_held = np.array([0.3])
    pp.step(np.array([-0.2]), 20_000_000)
    x_mid, _ = phi_T(paper.make_plant(), paper.x0, np.array([0.3]), 0.02)
    x1, _ = phi_T(paper.make_plant(), x_mid, np.array([-0.2]), 0.1 - 0.02)
    assert proc.x.tolist() == x1.tolist() and pp.u_held.tolist() == [-0.2]


# ============================================================================ delays in the simulators
@pytest.mark.parametrize("name,run", [
    ("paper", {}),                                                          # scheduled, latency 0
    ("paper", {"sim_delay": {"kind": "uniform", "min": 0.0, "max": 0.03, "seed": 4}}),  # some late
    ("paper-greedy", {"actuation": "arrival", "sim_delay": {"kind": "uniform", "min": 0.001, "max": 0.01,
                                                            "seed": 1}}),
    ("pendulum", {"actuation": "arrival", "sim_delay": {"kind": "trace", "values": [0.004, 0.002, 0.009]}}),
])
def test_batch_kernel_equals_per_sample_loop_with_delays(name, run):
    sc = physical(name, **run)
    res = simulate_scenario(sc)
    kw = dict(greedy_params=sc.attack.greedy_params(), score=sc.attack.score) if sc.attack.online else \
        dict(theta=sc.theta()[None, :])
    b = simulate_batch(sc.make_plant(), sc.K, sc.quantizer, sc.x0, sc.n_steps, timing=sc.timing_params,
                       latency=sc.sim_latency()[None, :], u_max=sc.controller.u_max, record=True, flow=sc.flow,
                       **kw)
    assert np.array_equal(b.x[0], res.x) and np.array_equal(b.E[0], res.E_enc)
    assert np.array_equal(b.theta[0], res.theta) and np.array_equal(b.x_final[0], res.x_final)
    assert b.saturations[0] == res.saturations and b.mismatch[0] == 0


def test_zero_delay_physical_timing_is_ideal_timing(paper):
    """Holding u_{k-1} for 0 s is no hold: arrival actuation at zero latency equals the paper's loop."""
    d = tomllib.loads(paper.source)
    d["run"].update(timing="physical", actuation="arrival")
    d["quantizer"]["rule"] = "paper"
    sc = scenario.from_dict(d, source=paper.source)
    a = simulate_scenario(sc, latency=np.zeros(sc.n_steps, dtype=np.int64))
    # a lost sample's u = 0 leaves the controller at its loss deadline: zero latency only for received ones
    ideal = simulate_scenario(paper)
    ksat = np.nonzero(paper.theta())[0]
    assert np.array_equal(a.x[:ksat[0] + 1], ideal.x[:ksat[0] + 1])


def _margin_case(rng, plant, K, E, nominal, lo, hi, L_u, Lam):
    """One random check of the delay-aware bound: ||x_{k+1} - xi_{k+1}|| <= Lambda E/M + margin."""
    M = 6
    q = rng.uniform(-1.0, 1.0, 2)
    x = q + rng.uniform(-E / M, E / M, 2)
    u_prev = rng.uniform(-2, 2, 1)
    u = (K @ q).ravel()
    delta = rng.uniform(lo, hi)
    true, _ = phi_T(plant, x, u_prev, delta)
    true, _ = phi_T(plant, true, u, 0.1 - delta)
    pred, _ = phi_T(plant, q, u_prev, nominal)
    pred, _ = phi_T(plant, pred, u, 0.1 - nominal)
    bound = Lam * E / M + delay_margin_gain(Lam, L_u, nominal, lo, hi) * np.max(np.abs(u - u_prev))
    return float(np.max(np.abs(true - pred))), float(bound)


def test_the_delay_margin_covers_every_delay_in_the_bound_numerically():
    """Random states, inputs and delays in [min, max] (Lienard, L = 10 on |x1| <= 4): never outside the box."""
    plant = plants.make("lienard")
    K = np.array([[-1.81, -1.90]])
    Lam = math.exp(10 * 0.1)
    rng = np.random.default_rng(7)
    worst = 0.0
    for _ in range(400):
        E = 10 ** rng.uniform(-6, -1)
        lo, hi = sorted(rng.uniform(0.0, 0.05, 2))
        nominal = rng.uniform(lo, hi)
        err, bound = _margin_case(rng, plant, K, E, nominal, lo, hi, plant.input_gain(4.0), Lam)
        assert err <= bound * (1 + 1e-9) + 1e-15
        worst = max(worst, err / bound)
    assert worst > 0.05  # the bound is not vacuous: it is approached within a factor 20


@pytest.mark.parametrize("name", ["paper", "paper-greedy", "pendulum"])
def test_delays_within_the_bound_cause_no_saturation(name):
    """Arrival actuation, delays drawn inside the declared bound: the quantizer never saturates."""
    sc0 = scenario.load(name)
    dT = sc0.run.deadline * sc0.T
    lo, hi = 0.002 * sc0.T / 0.1, 0.006 * sc0.T / 0.1
    sc = physical(name, actuation="arrival", delay={"nominal": 0.5 * (lo + hi), "min": lo, "max": hi},
                  delay_lost={"nominal": 0.8 * dT + 0.004 * sc0.T / 0.1, "min": 0.8 * dT + lo,
                              "max": 0.8 * dT + hi},
                  sim_delay={"kind": "uniform", "min": lo, "max": hi, "seed": 11})
    res = simulate_scenario(sc)
    assert res.saturations == 0, np.nonzero(res.saturated)[0]
    assert res.agree


def test_delays_beyond_the_bound_saturate_and_recover():
    """The paper's rule under 3-9 ms of latency: saturations, OVERFLOW, zoom-out, and the loop converges."""
    sc0 = scenario.load("paper")
    d = tomllib.loads(sc0.source)
    d["attack"] = {"kind": "none"}
    d["run"].update(timing="physical", actuation="arrival",
                    sim_delay={"kind": "uniform", "min": 0.003, "max": 0.009, "seed": 2})
    d["quantizer"]["rule"] = "paper"
    sc = scenario.from_dict(d, source=sc0.source)
    res = simulate_scenario(sc)
    assert res.saturations > 0
    assert all(res.symbols[k] == 36 for k in np.nonzero(res.saturated)[0])  # OVERFLOW each time
    assert res.agree and res.final_norm < 1e-3


def test_scheduled_physical_timing_converges_on_the_paper_and_the_paper_rule_does_not():
    sc = physical("paper")
    res = simulate_scenario(sc)
    assert res.saturations == 0 and res.final_norm < 1e-4
    d = tomllib.loads(sc.source)
    d["run"].update(timing="physical", actuation="arrival",
                    sim_delay={"kind": "uniform", "min": 0.002, "max": 0.008, "seed": 1})
    d["quantizer"]["rule"] = "paper"
    bad = simulate_scenario(scenario.from_dict(d, source=sc.source))
    assert bad.saturations > 10 and bad.final_norm > 1.0  # the failure physical timing had


# ============================================================================ lockstep, whatever happens
@pytest.mark.slow  # half a second or more on a warm cache
@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), via=st.booleans(), arrival=st.booleans())
def test_encoder_and_decoder_stay_in_lockstep_under_random_delays_losses_and_ack_losses(seed, via, arrival):
    rng = np.random.default_rng(seed)
    sc0 = scenario.load("paper")
    d = tomllib.loads(sc0.source)
    d["run"].update(timing="physical", actuation="arrival" if arrival else "scheduled", duration=4.0,
                    sim_delay={"kind": "uniform", "min": 0.0, "max": float(rng.uniform(0.0, 0.06)),
                               "seed": int(seed % 1000)})
    sc = scenario.from_dict(d, source=sc0.source)
    N = sc.n_steps
    theta = (rng.random(N) < rng.uniform(0, 0.5)).astype(np.uint8)
    corrupt = tuple((int(k), "length") for k in rng.choice(N, 3, replace=False))
    res = simulate_loop(None, sc.K, sc.quantizer, sc.x0, N, OnlineAttacker(theta=theta, T=sc.T), sc.flow,
                        model=sc.make_model(), process=sc.make_process(), timing=sc.timing_params,
                        latency=sc.sim_latency(), effects=LinkEffects(ack_via_attacker=via, corrupt=corrupt))
    known = np.isfinite(res.E_enc)
    assert np.array_equal(res.E_enc[known], res.E_dec[known])
    assert np.array_equal(res.xi_enc[known], res.xi_dec[known])
    if not via:
        assert not res.withheld.any()
    # the decoder lost every withheld sample and every corrupted one
    assert all(res.theta[k] == 1 for k in np.nonzero(res.withheld)[0])
    assert all(res.theta[k] == 1 for k, _ in corrupt if k < len(res.theta))
