"""The Rerun view (``testbed.view.rerun``): simulate --rrd, replay of an MCAP, and a live run with --rerun save.

Every test writes a ``.rrd`` and reads it back with ``rerun.chunk.RrdReader``:
the entities are there and the logged E_k is the recording's (bit for bit);
``rerun rrd verify`` accepts every file the testbed writes (``simulate --rrd``, ``replay``,
``--rerun save`` and its merge after a kill; not the files a Rerun server saved).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess

import numpy as np
import pytest
import rerun as rr  # noqa: F401 - a dependency of the testbed (rerun-sdk)
from failclosed import require
from helpers.cli import tb_run_here
from rerun.chunk import RrdReader

from testbed.view import phase
from testbed.view import rerun as viewer

os.environ.setdefault("RERUN_ANALYTICS", "0")
TIMEOUT = float(os.environ.get("TESTBED_PROCESS_TIMEOUT", "300"))

ENTITIES = {"/plant/x", "/plant/u", "/encoder/E", "/encoder/log10_E", "/encoder/xi", "/controller/E",
            "/controller/log10_E", "/controller/xi", "/controller/theta", "/attacker/attack_on",
            "/phase/trajectory", "/phase/x", "/phase/xi", "/phase/box"}


def entity_paths(path) -> set[str]:
    return {c.entity_path for c in RrdReader(path).store().stream()}


def scalars(path, entity: str) -> dict[int, list[float]]:
    """k -> the logged Scalars of ``entity`` (temporal rows only)."""
    out: dict[int, list[float]] = {}
    for c in RrdReader(path).store().stream():
        if c.entity_path != entity or c.is_static:
            continue
        d = c.to_record_batch().to_pydict()
        if "Scalars:scalars" not in d:
            continue
        for k, v in zip(d["k"], d["Scalars:scalars"]):
            out[int(k)] = list(v)
    return out


def rrd_verify(path) -> subprocess.CompletedProcess:
    return subprocess.run([viewer.rerun_binary(), "rrd", "verify", str(path)], capture_output=True, text=True,
                          timeout=120, env=dict(os.environ, RERUN_ANALYTICS="0"))


@pytest.fixture(scope="module")
def sim(paper):
    from testbed.sim.batch import simulate_scenario

    return paper, simulate_scenario(paper)


# ---------------------------------------------------------------- pure parts
def test_attack_intervals_to_samples(paper):
    """One attack_on of a simulation (``simulate.attack_on_samples``), the Run's and the view's: the DoS
    schedule at t_k with the schedule's own convention, a_i <= k T <= a_i + tau_i (``Schedule.theta_samples``),
    so the sample at the end of an interval is on, as it is lost."""
    from testbed import scenario
    from testbed.runs.run import simulate
    from testbed.sim.batch import attack_on_samples, simulate_scenario

    sc = scenario.with_overrides(paper, {"duration": 6.0, "attack": {"intervals": [[1.0, 1.2], [4.0, 0.8]]}})
    res = simulate_scenario(sc)
    on = attack_on_samples(sc, res)
    assert len(on) == 60
    assert on[:10].sum() == 0 and on[10:23].all() and not on[23] and on[40:49].all() and on.sum() == 22
    assert np.array_equal(on, sc.attack.schedule(sc.T, 6.0).theta_samples(sc.T, 60).astype(bool))
    assert np.array_equal(on, res.theta.astype(bool))  # every sample of an interval is lost, no other
    assert np.array_equal(simulate(sc).arrays["attack_on"], on)


def test_roa_outline_paper_and_none_for_cartpole(paper):
    from testbed import scenario

    out = phase.roa_outline(paper, grid=31)
    assert out is not None and out.lines and 0.0 < out.fraction < 1.0
    assert all(ln.shape[1] == 2 for ln in out.lines)
    assert phase.roa_outline(scenario.load("cartpole")) is None


# ---------------------------------------------------------------- simulate --rrd
def test_simulation_rrd_entities_and_E(sim, tmp_path):
    sc, res = sim
    path = tmp_path / "sim.rrd"
    from testbed.runs.run import run_of_simulation
    from testbed.sim.batch import attack_on_samples

    viewer.run_to_rrd(path, run_of_simulation(sc, res), recording_id=f"sim-{sc.name}")
    r = RrdReader(path)
    assert len(r.recordings()) == 1 and len(r.blueprints()) == 1
    paths = entity_paths(path)
    assert ENTITIES | {"/phase/roa", "/scenario"} <= paths
    E = scalars(path, "/encoder/E")
    assert sorted(E) == list(range(len(res.E_enc)))
    assert np.array_equal(np.array([E[k][0] for k in sorted(E)]), res.E_enc)  # bit for bit
    Ed = scalars(path, "/controller/E")
    assert np.array_equal(np.array([Ed[k][0] for k in sorted(Ed)]), res.E_dec)
    x = scalars(path, "/plant/x")
    assert np.array_equal(np.array([x[k] for k in range(len(res.x))]), res.x)
    assert np.array_equal(np.array(x[len(res.x)]), res.x_final)
    lg = scalars(path, "/encoder/log10_E")
    np.testing.assert_allclose([lg[k][0] for k in sorted(lg)], np.log10(res.E_enc))
    theta = scalars(path, "/controller/theta")
    assert [int(theta[k][0]) for k in sorted(theta)] == res.theta.astype(int).tolist()
    on = scalars(path, "/attacker/attack_on")
    assert [int(on[k][0]) for k in sorted(on)] == attack_on_samples(sc, res).astype(int).tolist()
    v = rrd_verify(path)
    assert v.returncode == 0, v.stderr[-2000:]


@pytest.mark.slow  # seconds: the cart-pole drawn into Rerun
def test_simulate_cli_rrd_cartpole_without_roa(tmp_path):
    """n = 4: phase plane of (x1, x2), no ROA outline."""
    path = tmp_path / "cp.rrd"
    p = tb_run_here("simulate", "cartpole", "--duration", "2", "--rrd", path)
    assert p.returncode == 0, p.stderr[-2000:]
    paths = entity_paths(path)
    assert ENTITIES <= paths and "/phase/roa" not in paths
    assert len(scalars(path, "/plant/x")[0]) == 4
    v = rrd_verify(path)
    assert v.returncode == 0, v.stderr[-2000:]


# ---------------------------------------------------------------- replay of an MCAP recording
@pytest.mark.slow  # seconds: a simulation recorded and replayed into Rerun
def test_replay_of_simulated_recording_gives_the_same_E(sim, tmp_path):
    sc, res = sim
    mcap, rrd = tmp_path / "sim.mcap", tmp_path / "replay.rrd"
    p = tb_run_here("simulate", "paper", "--out", mcap)
    assert p.returncode == 0, p.stderr[-2000:]
    p = tb_run_here("replay", mcap, "--rrd", rrd)
    assert p.returncode == 0, p.stderr[-2000:]
    assert ENTITIES | {"/phase/roa", "/scenario"} <= entity_paths(rrd)
    E = scalars(rrd, "/encoder/E")
    assert np.array_equal(np.array([E[k][0] for k in sorted(E)]), res.E_enc)
    on = scalars(rrd, "/attacker/attack_on")
    # the attacker's recorded attack_on (the simulator's): [1.0, 2.2] and [4.0, 4.8] at T = 0.1, ends included
    from testbed.sim.batch import attack_on_samples

    assert [int(on[k][0]) for k in sorted(on)] == attack_on_samples(sc, res).astype(int).tolist()
    assert sum(v[0] for v in on.values()) == 22
    assert rrd_verify(rrd).returncode == 0


# ---------------------------------------------------------------- live: testbed run --rerun save
@pytest.mark.process
def test_live_run_rerun_save_one_recording_from_every_node(tmp_path, run_id):
    from helpers.cli import run_cli, tb_cmd

    from testbed.record import reader

    rrd, mcap = tmp_path / "live.rrd", tmp_path / "live.mcap"
    rc, out, err = run_cli(tb_cmd("run", "paper", "--duration", "3", "--run-id", run_id, "--json",
                                  "--out", str(mcap), "--rerun", "save", str(rrd)))
    assert rc == 0, err[-3000:]
    s = json.loads(out)
    assert s["rerun"]["mode"] == "save" and "error" not in s["rerun"], s["rerun"]
    for role in ("plant", "encoder", "controller", "attacker"):
        ns = s["node_summaries"][role]
        assert ns["rerun_errors"] == 0 and ns["rerun_logged"] >= 30, (role, ns)
    assert not list(tmp_path.glob(".live.rrd.parts-*")), "part files left behind"
    r = RrdReader(rrd)
    recs = r.recordings()
    assert len(recs) == 1 and recs[0].recording_id == run_id  # the launcher and four nodes: one recording
    assert len(r.blueprints()) == 1
    assert ENTITIES | {"/phase/roa", "/scenario"} <= entity_paths(rrd)
    rec = reader.read(mcap)
    enc = rec.telemetry["encoder"]
    want = {k: t.E for k, t in enc.items() if not t.silent}
    E = scalars(rrd, "/encoder/E")
    # exactly the recorded E_k (a sample is withheld only if a stall delayed its ack)
    assert len(want) == 30 - len(s["withheld_at"]) >= 25 and {k: v[0] for k, v in E.items()} == want
    Ed = scalars(rrd, "/controller/E")
    assert {k: v[0] for k, v in Ed.items()} == {k: t.E for k, t in rec.telemetry["controller"].items()
                                               if len(t.xi)}
    v = rrd_verify(rrd)
    assert v.returncode == 0, v.stderr[-2000:]


def _stream_entities(path) -> tuple[set[str], list]:
    """Entities and recordings of a file with or without a footer (a saving server writes none)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no footer: legacy format" from a --save server's file
        r = RrdReader(path)
        return {c.entity_path for c in r.stream()}, r.recordings()


# ------------------------------------------------ live: testbed run --rerun connect URL
@pytest.mark.process
def test_live_run_rerun_connect_streams_to_a_grpc_server(tmp_path, run_id):
    """A real Rerun gRPC server (``rerun --port P --save F``, no viewer window) receives the run."""
    from helpers.cli import run_cli, tb_cmd

    got = tmp_path / "server.rrd"
    with viewer.saving_server(got) as url:
        rc, out, err = run_cli(tb_cmd("run", "paper", "--duration", "3", "--run-id", run_id, "--json",
                                      "--no-record", "--rerun", "connect", url))
    assert rc == 0, err[-3000:]
    s = json.loads(out)
    assert s["rerun"] == {"mode": "connect", "recording_id": run_id, "target": url}
    for role in ("plant", "encoder", "controller", "attacker"):
        ns = s["node_summaries"][role]
        assert ns["rerun_errors"] == 0 and ns["rerun_logged"] >= 30, (role, ns)
    ents, recs = _stream_entities(got)
    assert [r.recording_id for r in recs] == [run_id]  # every process into one recording
    assert ENTITIES | {"/phase/roa", "/scenario"} <= ents


# ------------------------------------------------ live: --rerun save when a node is killed
@pytest.mark.process
def test_live_rerun_save_merges_when_a_node_was_killed(tmp_path, run_id):
    """The killed node's part file has no footer; the merge keeps the others' data and the file verifies."""
    from helpers.cli import run_cli, tb_cmd

    rrd = tmp_path / "killed.rrd"
    rc, out, err = run_cli(tb_cmd("run", "paper", "--duration", "3", "--run-id", run_id, "--json",
                                  "--no-record", "--rerun", "save", str(rrd), "--kill", "encoder@1.5"))
    s = json.loads(out)
    assert rc == 1 and any(f["node"] == "encoder" for f in s["faults"]), (rc, s["faults"])
    assert "error" not in s["rerun"], s["rerun"]
    assert rrd.exists() and not list(tmp_path.glob(".killed.rrd.parts-*")), "no merge, or part files left"
    v = rrd_verify(rrd)
    assert v.returncode == 0, v.stderr[-2000:]
    ents = entity_paths(rrd)
    assert {"/plant/x", "/plant/u", "/controller/E", "/controller/theta", "/attacker/attack_on"} <= ents
    Ed = scalars(rrd, "/controller/E")
    assert len(Ed) >= 25, sorted(Ed)  # the controller decoded up to the end (E grows on losses after 1.5 s)
    # the killed encoder's part: what its tap had handed to Rerun before the kill (15 of 15 here)
    E = scalars(rrd, "/encoder/E")
    assert 5 <= len(E) <= 16 and sorted(E) == list(range(len(E))), sorted(E)


# ------------------------------------------------ live: testbed run --rerun spawn
def _port_busy(port: int) -> bool:
    import socket

    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def _rerun_pids() -> set[int]:
    from helpers.procs import procs_with

    return set(procs_with(viewer.rerun_binary()))


@pytest.mark.process
def test_live_run_rerun_spawn_reuses_the_viewer_on_its_port(tmp_path, run_id):
    """``--rerun spawn`` with a viewer already on port 9876: no second viewer, the run goes to it.

    A headless saving server stands in for the viewer (there is no display here);
    what is not tested is the window a spawn opens when nothing listens there.
    """
    from helpers.cli import run_cli, tb_cmd

    if _port_busy(9876):
        require("port9876", "port 9876 is taken on this machine")
    got = tmp_path / "spawned.rrd"
    with viewer.saving_server(got, port=9876):
        before = _rerun_pids()
        rc, out, err = run_cli(tb_cmd("run", "paper", "--duration", "2", "--run-id", run_id, "--json",
                                      "--no-record", "--rerun", "spawn"))
        started = _rerun_pids() - before
    for pid in started:  # never leave a viewer behind, even when the test fails
        os.kill(pid, signal.SIGKILL)
    assert rc == 0, err[-3000:]
    assert not started, "spawn started a second viewer although one listened on 9876"
    s = json.loads(out)
    assert s["rerun"] == {"mode": "spawn", "recording_id": run_id, "target": viewer.DEFAULT_URL}
    for role in ("plant", "encoder", "controller", "attacker"):
        ns = s["node_summaries"][role]
        # every sample a node handled is logged (the attacker handles the symbols the encoder sent)
        handled = ns["dropped"] + ns["forwarded"] if role == "attacker" else 20
        assert ns["rerun_errors"] == 0 and ns["rerun_logged"] >= handled >= 15, (role, ns)
    ents, recs = _stream_entities(got)
    assert [r.recording_id for r in recs] == [run_id]
    assert ENTITIES | {"/phase/roa", "/scenario"} <= ents
