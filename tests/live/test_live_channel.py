"""The live channel stage: a run with ``[network]`` loses the samples the channel model's seeded draws
say (``testbed.loop.channel.draws``, the simulator's draws), holds each message for its drawn delay, and
equals the simulator with the same ``[network]`` bit for bit."""

from __future__ import annotations

import json
import os
import secrets

import numpy as np
import pytest
from helpers.cli import run_cli, tb_cmd
from helpers.live import BIT_EXACT_KEYS, TOPOLOGIES, live_exact, mismatch, simulate

from testbed import scenario
from testbed.loop import channel

pytestmark = pytest.mark.process

NETWORK = """
[network]
seed = 7
[network.symbol]
loss = 0.1
[network.actuation]
delay = 0.003
jitter = 0.002
[network.sensor]
delay = 0.002
[network.ack]
loss = 0.1
loss_burst = 2.0
"""


def test_live_channel_losses_are_the_models_draws_and_the_simulators(tmp_path):
    path = tmp_path / "chan.toml"
    path.write_text(scenario.load("paper").source + NETWORK)
    sc = scenario.load(str(path))
    run_id = f"t{os.getpid()}chan{secrets.token_hex(3)}"
    rc, s, err = live_exact(run_id, str(path), "--duration", "5")
    assert rc == 0, (s["faults"], err[-3000:])
    # the same [network] and seed, simulated: the same lost samples, and the same run bit for bit
    sim = simulate(str(path), 5)
    for key in BIT_EXACT_KEYS:
        assert s[key] == sim[key], mismatch(s, sim, key)
    # and the losses told apart alike: the channel's are the symbol link's drops
    assert s["losses"] == sim["losses"] and s["losses"]["channel"] > 0, (s["losses"], sim["losses"])
    N = s["n_steps"]
    drawn = set(np.flatnonzero(channel.draws(sc.network, "symbol", N).lost).tolist())
    sent = set(range(N)) - set(s["attacker_dropped_at"]) - set(s["withheld_at"])
    ch = s["node_summaries"]["controller"]["channel"]["symbol"]
    # the channel lost exactly the drawn samples whose symbol was on the link (the attacker's and the
    # encoder's losses come first), and each of them is a loss (theta_k = 1) at the controller's deadline
    assert ch["lost_at"] == sorted(drawn & sent) and ch["lost_at"], (ch["lost_at"], sorted(drawn), sorted(sent))
    assert all(s["theta"][k] == 1 for k in ch["lost_at"]), s["theta"]
    every = [k for node in s["node_summaries"].values() for link in (node.get("channel") or {}).values()
             for k in link["lost_at"]]
    assert s["events"].get("channel_lost") == len(every)  # one event per drop, on every link
    assert s["losses"]["channel"] == len(ch["lost_at"])
    from testbed.record import reader

    rec = reader.read(s["recording"]["path"])  # the recording keeps it, for resimulate and report
    assert rec.summaries["controller"]["channel"]["symbol"] == ch
    # every u_k that reached the plant was held for at least its drawn delay (one host: the nodes'
    # run clocks agree within microseconds), and not much longer
    delay = channel.draws(sc.network, "actuation", N).delay
    rows = s["node_summaries"]["plant"]["channel"]["actuation"]["delay_s"]
    assert len(rows) >= N // 2, rows
    for k, model, realized in rows:
        assert model == delay[k]
        assert model - 1e-4 <= realized < model + 0.05, (k, model, realized)
    # the sensor link's x_k held 2 ms; the ack link's losses are its draws (every sample's ack is sent;
    # the last one or two may still be on their way when the encoder stops)
    enc = s["node_summaries"]["encoder"]["channel"]
    assert enc["sensor"]["delay_s"] and all(m == 0.002 and r >= m - 1e-4 for _, m, r in enc["sensor"]["delay_s"])
    ack = set(np.flatnonzero(channel.draws(sc.network, "ack", N).lost).tolist())
    assert set(range(N - 2)) & ack <= set(enc["ack"]["lost_at"]) <= ack and enc["ack"]["lost_at"], enc["ack"]
    # the run re-simulates exactly from its recording
    rc, out, err = run_cli(tb_cmd("resimulate", s["recording"]["path"], "--json"))
    r = json.loads(out)
    assert r["reproduced"] and r["max_state_error"] == 0 and r["symbols_identical"], r


@pytest.mark.parametrize("topology", TOPOLOGIES)
def test_live_sensor_and_ack_losses_equal_the_simulator(tmp_path, topology):
    """Sensor and ack links that lose messages (x_k never reaches the encoder; theta_k never comes back,
    so the encoder withholds): the live run equals the simulator bit for bit, withheld samples included,
    in four processes and with the encoder in the plant's process (where the two links are applied to
    what the plant hands over in memory)."""
    path = tmp_path / "sa.toml"
    path.write_text(scenario.load("paper").source + "\n[network]\nseed = 9\n[network.sensor]\nloss = 0.1\n"
                                                    "[network.ack]\nloss = 0.1\n")
    sc = scenario.load(str(path))
    run_id = f"t{os.getpid()}chsa{secrets.token_hex(3)}"
    rc, s, err = live_exact(run_id, str(path), "--duration", "5", *topology)
    assert rc == 0, (s["faults"], err[-3000:])
    sim = simulate(str(path), 5)
    for key in (*BIT_EXACT_KEYS, "withheld_at", "losses"):
        assert s[key] == sim[key], mismatch(s, sim, key)
    assert s["withheld_at"] and s["losses"]["channel"] > 0
    N = s["n_steps"]
    enc = s["node_summaries"]["encoder"]["channel"]
    drawn = set(np.flatnonzero(channel.draws(sc.network, "sensor", N).lost).tolist())
    assert enc["sensor"]["lost_at"] == sorted(drawn), enc["sensor"]
