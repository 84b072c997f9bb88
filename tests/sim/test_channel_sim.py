"""The [network] channel in the simulator: the batch kernel equals the per-sample loop (the live nodes'
protocol objects) bit for bit with every link lossy and delayed; one seed gives one loss pattern; the
losses are told apart (attacker, channel, late, withheld) as a constructed case says they must be."""

import json
import tomllib

import numpy as np
import pytest
from helpers.sims import SIM_ARRAYS, assert_simulators_identical, both_simulators, same_bits

from testbed import scenario
from testbed.loop import channel
from testbed.loop.channel import ATTACKER, CHANNEL, LATE, WITHHELD, loss_counts
from testbed.scenario.write import to_toml
from testbed.sim.batch import summarize
from testbed.sim.trajectory import kernel_refusal, simulate_scenario


def _sc(name: str, network: dict, **over):
    sc = scenario.load(name)
    data = tomllib.loads(sc.source)
    data["network"] = network
    sc = scenario.loads(to_toml(data), name=name)
    return scenario.with_overrides(sc, over) if over else sc


ALL_LINKS = {"seed": 2, "sensor": {"loss": 0.05, "delay": 0.002}, "symbol": {"loss": 0.1, "loss_burst": 3.0},
             "ack": {"loss": 0.1}, "actuation": {"loss": 0.05, "delay": 0.005, "jitter": 0.002}}
LATE_LINKS = {"seed": 3, "symbol": {"delay": 0.03, "jitter": 0.02}, "ack": {"loss": 0.05},
              "actuation": {"delay": 0.005, "jitter": 0.002, "loss": 0.02}}
RANDOM = {"kind": "random", "kappa_F": 0.5, "rho_F": 0.3, "kappa_D": 0.3, "rho_D": 0.25, "seed": 4}
CASES = [
    ("paper", ALL_LINKS, {}),
    ("paper", ALL_LINKS, {"timing": "physical"}),
    ("paper", LATE_LINKS, {"timing": "physical"}),
    ("paper", LATE_LINKS, {"timing": "physical", "actuation": "arrival"}),
    ("paper", ALL_LINKS, {"attack": RANDOM}),
    ("paper", ALL_LINKS, {"method": "zoom"}),
    ("paper", ALL_LINKS, {"method": "unquantized-hold"}),
    ("paper-greedy", ALL_LINKS, {}),
    ("pendulum", ALL_LINKS, {}),
]


@pytest.mark.parametrize("name,net,over", CASES, ids=[f"{n}-{i}" for i, (n, _, _) in enumerate(CASES)])
def test_kernel_equals_per_sample_loop_with_a_channel(name, net, over):
    sc = _sc(name, net, **over)
    assert kernel_refusal(sc) is None
    per, bat = both_simulators(sc)
    assert_simulators_identical(sc, per, bat)
    assert same_bits(per.loss_cause, bat.loss_cause)
    # the channel did something, and every loss has exactly one cause
    assert (per.loss_cause == CHANNEL).any() or (per.loss_cause == LATE).any()
    assert np.array_equal(per.loss_cause != 0, per.theta != 0)
    if net["ack"]["loss"]:
        # the kernel's withholding (computed ahead, channel.withheld_pattern) is the protocol objects'
        assert per.withheld.any() and per.counters["encoder"]["desync_episodes"] > 0
    if over.get("timing") == "physical":
        assert per.u_missing.any()


def test_late_symbols_only_under_physical_timing():
    phys = simulate_scenario(_sc("paper", LATE_LINKS, timing="physical"))
    ideal = simulate_scenario(_sc("paper", LATE_LINKS))
    # symbol delay 30 ms +- 20 ms against the loss deadline 0.8 * 0.5 * T = 40 ms: a quarter are late
    assert 0.15 < np.mean(phys.loss_cause == LATE) < 0.35
    assert not (ideal.loss_cause == LATE).any() and ideal.delays is None


def test_one_seed_one_loss_pattern_and_another_seed_another():
    a = simulate_scenario(_sc("paper", ALL_LINKS))
    b = simulate_scenario(_sc("paper", ALL_LINKS))
    c = simulate_scenario(_sc("paper", {**ALL_LINKS, "seed": 5}))
    for name in SIM_ARRAYS:
        assert same_bits(getattr(a, name), getattr(b, name)), name
    assert not np.array_equal(a.loss_cause, c.loss_cause)


def test_losses_told_apart_on_a_constructed_case():
    """The paper's attack (two intervals) with a symbol link that loses 10% (seed 9) and nothing
    else: the attacker's losses are the attack's samples, the channel's the link's draws outside them
    (``channel.draws``, computed here on their own), and nothing is late or withheld."""
    sc = _sc("paper", {"seed": 9, "symbol": {"loss": 0.1}})
    res = simulate_scenario(sc)
    N = sc.n_steps
    attack = sc.theta(N).astype(bool)
    link = channel.draws(sc.network, "symbol", N).lost
    assert loss_counts(res.loss_cause) == {"attacker": int(attack.sum()), "channel": int((link & ~attack).sum()),
                                           "network": 0, "late": 0, "withheld": 0}
    assert np.array_equal(np.flatnonzero(res.loss_cause == ATTACKER), np.flatnonzero(attack))
    assert np.array_equal(res.theta.astype(bool), attack | link)
    s = summarize(sc, res)
    assert s["losses"] == loss_counts(res.loss_cause) and sum(s["losses"].values()) == s["samples_lost"]
    # the ack link alone: every loss is a withheld sample (no attack, no symbol loss)
    res = simulate_scenario(_sc("paper", {"seed": 9, "ack": {"loss": 0.2}}, attack={"kind": "none"}))
    assert res.theta.any() and np.array_equal(res.loss_cause != 0, res.withheld)
    assert (res.loss_cause[res.theta != 0] == WITHHELD).all()


@pytest.mark.slow  # half a second or more on a warm cache
def test_gilbert_elliott_bursts_in_the_simulated_run():
    """Losses on a bursty symbol link (mean burst 5) come in runs of about 5 samples; Bernoulli at the same
    loss rate in runs of about 1 / (1 - loss)."""
    def mean_run(burst):
        res = simulate_scenario(_sc("paper", {"seed": 1, "symbol": {"loss": 0.2, "loss_burst": burst}},
                                    attack={"kind": "none"}, duration=2000.0), simulator="batch")
        lost = res.theta.astype(np.int8)
        d = np.diff(np.concatenate([[0], lost, [0]]))
        runs = np.flatnonzero(d == -1) - np.flatnonzero(d == 1)
        return lost.mean(), runs.mean()

    rate, run = mean_run(5.0)
    assert abs(rate - 0.2) < 0.02 and 4.5 < run < 5.5
    rate, run = mean_run(1.0)
    assert abs(rate - 0.2) < 0.02 and abs(run - 1.25) < 0.05


def test_simulate_json_says_losses(capsys, tmp_path):
    from testbed import cli

    sc = _sc("paper", {"seed": 9, "symbol": {"loss": 0.1}})
    path = tmp_path / "paper.toml"
    path.write_text(sc.source)
    assert cli.main(["simulate", str(path), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["losses"]["channel"] > 0 and s["losses"]["attacker"] == int(sc.theta(sc.n_steps).sum())


def test_recorded_losses_on_a_constructed_record():
    """The rule a recording is read by (channel.recorded_losses), on ten samples whose fate is known:
    0 received; 1 withheld; 2 dropped by the attacker; 3 corrupted (invalid); 4 superseded; 5, 6, 7 forwarded
    and never received, of which the controller counted one as arriving late; 8, 9 received."""
    theta = np.array([0, 1, 1, 1, 1, 1, 1, 1, 0, 0])
    z = np.zeros(10, dtype=bool)

    def at(*ks):
        m = z.copy()
        m[list(ks)] = True
        return m

    got = channel.recorded_losses(theta, withheld=at(1), attacker=at(2), invalid=at(3), superseded=at(4),
                                  late_symbols=1, channel_lost=at(5))
    # 5 the channel model lost (its own record); of 6 and 7, one arrived late, the other the real network lost
    assert got == {"attacker": 2, "channel": 1, "network": 1, "late": 2, "withheld": 1}
    assert sum(got.values()) == theta.sum() and tuple(got) == channel.LOSS_KINDS
    # no channel model: a sent sample that never arrived is the real network's, never the channel's
    got = channel.recorded_losses(theta, withheld=at(1), attacker=at(2), invalid=at(3), superseded=at(4),
                                  late_symbols=1)
    assert got == {"attacker": 2, "channel": 0, "network": 2, "late": 2, "withheld": 1}
    # the model's record of a sample another cause lost first does not count twice
    got = channel.recorded_losses(theta, withheld=at(1), attacker=at(2), invalid=at(3), superseded=at(4),
                                  late_symbols=0, channel_lost=at(1, 2, 8))
    assert got["channel"] == 0 and sum(got.values()) == theta.sum()
    # a late count larger than the candidates cannot make the network's negative
    got = channel.recorded_losses(theta, withheld=z, attacker=z, invalid=z, superseded=z, late_symbols=99)
    assert got["network"] == 0 and got["late"] == int(theta.sum())


@pytest.mark.slow  # seconds: simulations recorded and reported
def test_report_of_a_simulated_recording_tells_losses_apart(tmp_path):
    """A simulated run with a lossy, late symbol link and a lossy ack link, written as a recording: the
    report reads back the simulator's losses (the attacker's from its log, the late ones from the
    controller's count), the budget section says it prices the attacker's only, and all losses as DoS
    are judged against Theorem 1's region (computed here on its own)."""
    from testbed.analysis import Loop, allowable_region
    from testbed.record.recording import record_simulation
    from testbed.runs.report import report

    sc = _sc("paper", {"seed": 3, "symbol": {"loss": 0.05, "delay": 0.03, "jitter": 0.02}, "ack": {"loss": 0.05},
                       "sensor": {"loss": 0.05}, "actuation": {"loss": 0.05, "delay": 0.004}}, timing="physical")
    res = simulate_scenario(sc)
    want = loss_counts(res.loss_cause)
    assert all(want[k] > 0 for k in want if k != "network") and want["network"] == 0  # a simulation has no real network
    path = tmp_path / "net.mcap"
    record_simulation(str(path), sc, res)
    s = report(path, resimulate=None)   # every sample
    assert s["losses"] == want
    # the recording says what happened (x_k that never reached the encoder: no encoder record), so it
    # re-simulates bit for bit, and its summary is the simulation's
    assert s["resimulation"]["reproduced"] is True, s["resimulation"]["verdict"]
    sim = json.loads(json.dumps(summarize(sc, res)))
    for key in ("samples_lost", "withheld_at", "symbols", "E", "theta", "x_final", "losses"):
        assert json.loads(json.dumps(s[key], default=lambda a: a.tolist())) == sim[key], key
    attack = sc.theta(sc.n_steps).astype(bool)   # the attack's samples the encoder sent (symbol >= 0)
    assert s["dropped_by_attacker"] == want["attacker"] == int((attack & (res.symbols >= 0)).sum())
    assert "attacker's losses only" in s["dos"]["counts"]
    ld = s["losses_as_dos"]
    H = sc.n_steps * sc.T
    from attackers.schedule import Schedule

    every = Schedule.from_theta(res.theta, sc.T)   # all losses, each run of them one attack
    assert len(res.intervals()) < len(every)       # the attacker's own intervals are fewer
    assert ld["frequency"] == pytest.approx(len(every) / H)
    assert ld["duration_fraction"] == pytest.approx(every.total_duration / H)   # a run of j + 1: j T
    reg = allowable_region(Loop.from_scenario(sc), "paper")
    assert ld["theorem1"]["in_allowable_region"] == bool(reg.holds(ld["frequency"], ld["duration_fraction"]))


@pytest.mark.slow  # seconds of numerics: Theorem 1's region twice
def test_losses_as_dos_inside_and_outside_theorem1_region():
    from testbed.runs.report import losses_as_dos

    sc = scenario.load("paper")
    theta = np.zeros(300, dtype=np.uint8)
    theta[100:102] = 1                   # two lost samples in 30 s: one attack of T (Schedule.from_theta)
    ld = losses_as_dos(sc, theta)
    assert (ld["count"], ld["frequency"], ld["duration_fraction"]) == (1, pytest.approx(1 / 30), pytest.approx(0.1 / 30))
    assert ld["theorem1"]["in_allowable_region"] is True
    theta = np.zeros(300, dtype=np.uint8)
    theta[::3] = 1                       # every third sample: 100 attacks of one sample (3.3 per s)
    ld = losses_as_dos(sc, theta)
    assert ld["count"] == 100 and ld["theorem1"]["in_allowable_region"] is False


@pytest.mark.slow  # half a second or more on a warm cache
def test_a_campaign_sweeps_network_keys(tmp_path):
    """``[axes]`` with dotted ``network.*`` keys: every row is its scenario's ``testbed simulate`` run (the
    channel applied: more samples lost on the lossy link), and the batch-kernel grouping leaves the channel
    runs to the simulator that applies it."""
    from testbed.campaign import rows as cmp_rows
    from testbed.campaign import spec as cmp
    from testbed.campaign.engine import outcome

    (tmp_path / "paper.toml").write_text(scenario.load("paper").source)
    c = tmp_path / "c.toml"
    c.write_text('scenario = "paper.toml"\nseed = 1\n[axes]\n"network.symbol.loss" = [0.0, 0.2]\n'
                 '"network.symbol.loss_burst" = [1.0, 4.0]\n"network.seed" = [1, 2]\n')
    runs, _ = cmp.plan(cmp.parse(c))
    assert len(runs) == 8
    rows = cmp_rows.simulate_runs([(r.id, r.text, r.name, r.base_dir) for r in runs])
    lost = {}
    for r, row in zip(runs, rows, strict=True):
        sc = scenario.loads(r.text, base_dir=r.base_dir)
        assert sc.network.link("symbol").loss == r.axes["network.symbol.loss"]
        want = outcome(summarize(sc, simulate_scenario(sc)))
        assert {k: row[k] for k in want} == want
        lost.setdefault(r.axes["network.symbol.loss"], []).append(row["samples_lost"])
    assert min(lost[0.2]) > max(lost[0.0])


def test_the_kernel_refuses_only_greedy_scoring_E_with_a_lossy_ack_link():
    sc = _sc("paper-greedy", ALL_LINKS, attack={"score": "E"})
    assert "ack link" in kernel_refusal(sc)
    assert simulate_scenario(sc).simulator == "per-sample"
    assert kernel_refusal(_sc("paper-greedy", {**ALL_LINKS, "ack": {}}, attack={"score": "E"})) is None
