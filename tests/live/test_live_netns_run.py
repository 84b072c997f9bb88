"""``testbed run --netns`` (the feature; ``test_live_netns.py`` builds the namespaces by hand): every node
in its own network namespace; the namespaces gone after a clean run, a node crash, Ctrl-C and a
SIGKILLed launcher (after the next run); ``--cut`` sets a node's link down and up."""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import subprocess
import time

import numpy as np
import pytest
from failclosed import require
from helpers.cli import TIMEOUT, run_cli, tb_cmd
from helpers.live import BIT_EXACT_KEYS, LOGS, live, live_exact, mismatch, simulate
from helpers.procs import reap

from testbed.wire.transport import ROLES


def _require_netns():
    if os.geteuid() != 0:
        require("netns", "network namespaces need root (CAP_SYS_ADMIN, CAP_NET_ADMIN)")
    if shutil.which("ip") is None:
        require("netns", "network namespaces need iproute2 ('ip' not found)")


def _left(token: str) -> list[str]:
    """Namespaces (``ip netns list``) and host links (``ip link``) whose name carries ``token``."""
    ns = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, timeout=20).stdout
    links = subprocess.run(["ip", "-o", "link"], capture_output=True, text=True, timeout=20).stdout
    return [line for line in (*ns.splitlines(), *links.splitlines()) if token in line]


@pytest.mark.slow  # its own processes (an interpreter start-up each)
def test_netns_refused_without_ip(tmp_path):
    """Without what it needs (here: no ``ip`` on PATH), one clear line and exit 2; --cut without --netns too."""
    env = dict(os.environ, PATH=str(tmp_path))
    p = subprocess.run(tb_cmd("run", "paper", "--netns", "--duration", "1"), capture_output=True, text=True,
                       timeout=120, env=env)
    assert p.returncode == 2, p.stderr
    assert p.stderr.strip().count("\n") == 0 and "--netns" in p.stderr and "'ip' not found" in p.stderr, p.stderr
    p = subprocess.run(tb_cmd("run", "paper", "--cut", "plant@1:1"), capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and p.stderr.strip().count("\n") == 0 and "--cut needs --netns" in p.stderr, p.stderr
    p = subprocess.run(tb_cmd("run", "paper", "--netns", "--cut", "plant@1"), capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 2 and "ROLE@SECONDS:DURATION" in p.stderr, p.stderr


@pytest.mark.process
def test_netns_paper_equals_simulator():
    """A --netns run of the paper's example equals the simulator bit for bit; every node process ran in a
    namespace of its own (not the test's), and none is left."""
    _require_netns()
    run_id = f"t{os.getpid()}nsrun{secrets.token_hex(3)}"
    rc, s, err = live_exact(run_id, "paper", "--netns", "--duration", "5")
    assert rc == 0, (s["faults"], err[-3000:])
    ids = {r: s["node_summaries"][r]["netns"] for r in ROLES}
    assert len(set(ids.values())) == 4, ids
    assert os.readlink("/proc/self/ns/net") not in ids.values()
    assert s["security"]["topology"] == "router"
    sim = simulate("paper", 5)
    for key in BIT_EXACT_KEYS:
        assert s[key] == sim[key], mismatch(s, sim, key)
    assert not _left(run_id)


@pytest.mark.process
def test_netns_link_cut_rides_through():
    """--cut controller@1.5:1: the controller's link is down for 1 s; the run completes on time (exit 0),
    the samples of the outage are deadline losses, the loop takes symbols again once the link is back,
    and the recording has the fault event ``controller_link_cut`` with the interval."""
    _require_netns()
    run_id = f"t{os.getpid()}nscut{secrets.token_hex(3)}"
    rc, s, err = live(run_id, "paper", "--netns", "--duration", "5", "--cut", "controller@1.5:1")
    assert rc == 0, (s["faults"], err[-3000:])
    assert s["complete"] and s["samples"] == s["n_steps"]
    cut = [f for f in s["faults"] if f["kind"] == "link_cut"]
    assert len(cut) == 1 and cut[0]["node"] == "controller", s["faults"]
    down, up = cut[0]["down_s"], cut[0]["up_s"]
    assert 1.5 <= down < 2.5 and 0.99 <= up - down < 1.5, cut
    assert cut[0]["liveliness_lost"] is False, cut  # a cut shorter than the lease does not end a session
    T = s["T"]
    during = set(range(int(down / T) + 1, int(up / T)))   # samples wholly inside the outage
    lost = set(s["deadline_missed_at"]) | set(s["attacker_dropped_at"]) | set(s["withheld_at"])
    assert during <= lost, (sorted(during - lost), s["loss_reasons"])
    after = [k for k, th in enumerate(s["theta"]) if k * T > up + 1.0 and th == 0]  # theta_k = 0: received
    assert after, ("no symbol arrived after the link came back", s["theta"])
    from testbed.record import reader

    rec = reader.read(s["recording"]["path"])
    ev = [e for e in rec.events if e.kind == "controller_link_cut"]
    assert len(ev) == 1 and json.loads(ev[0].detail)["up_s"] == up, rec.events
    assert not _left(run_id)


def _start(run_id: str, *more: str) -> tuple[subprocess.Popen, str]:
    err = os.path.join(LOGS, f"{run_id}.err")
    os.makedirs(LOGS, exist_ok=True)
    p = subprocess.Popen(tb_cmd("run", "paper", "--netns", "--duration", "30", "--json", "--no-record", "-v",
                                "--run-id", run_id, "--run-dir", os.path.join(LOGS, run_id), *more),
                         stdout=subprocess.DEVNULL, stderr=open(err, "w"), start_new_session=True)
    end = time.monotonic() + TIMEOUT
    while time.monotonic() < end and p.poll() is None:
        with open(err) as f:
            if "phase start" in f.read():
                return p, err
        time.sleep(0.2)
    os.killpg(p.pid, signal.SIGKILL)
    pytest.fail(f"run {run_id} did not start: {open(err).read()[-3000:]}")


@pytest.mark.process
def test_netns_nothing_left_after_crash_ctrl_c_and_sigkill():
    _require_netns()
    tag = f"t{os.getpid()}nsleft{secrets.token_hex(3)}"
    # a SIGKILLed launcher cannot clean up: its namespaces stay, until the next --netns run
    killed = tag + "k"
    p, _ = _start(killed)
    assert _left(killed)
    os.kill(p.pid, signal.SIGKILL)
    p.wait(10)
    reap(killed)
    assert _left(killed), "the namespaces of a SIGKILLed launcher were there to clean"
    # the next run (one whose controller crashes) removes them, and its own at its end
    crashed = tag + "c"
    rc, s, err = live(crashed, "paper", "--netns", "--duration", "4", "--crash", "controller@10", "--no-record")
    assert rc == 1 and any(f["kind"] == "crashed" and f["node"] == "controller" for f in s["faults"]), s["faults"]
    assert not _left(killed) and not _left(crashed), _left(tag)
    # Ctrl-C (SIGINT to the launcher) mid-run
    interrupted = tag + "i"
    p, err = _start(interrupted)
    p.send_signal(signal.SIGINT)
    assert p.wait(60) == 128 + signal.SIGINT, open(err).read()[-2000:]
    assert not reap(interrupted)
    assert not _left(interrupted), _left(interrupted)
    # SIGKILL again, and testbed run --netns-clean removes them (and does nothing else)
    killed2 = tag + "K"
    p, _ = _start(killed2)
    os.kill(p.pid, signal.SIGKILL)
    p.wait(10)
    reap(killed2)
    rc, out, err = run_cli(tb_cmd("run", "--netns-clean"), 60)
    assert rc == 0 and killed2 in out, (out, err)
    assert not _left(tag), _left(tag)


@pytest.mark.process
def test_netns_physical_timing_over_a_delayed_actuation_link(tmp_path):
    """Physical timing (scheduled actuation, the delay-aware rule) with ``[network.actuation] delay = 5 ms,
    jitter = 2 ms`` across network namespaces: every u_k is held for its drawn delay and still comes
    before its instant (0.4 d T = 36 ms at deadline 0.9), so the run converges, equals the simulator
    bit for bit, and its recording re-simulates within 1e-9."""
    from testbed import scenario
    from testbed.loop import channel
    from testbed.nodes.process import fifo_permitted

    _require_netns()
    path = tmp_path / "paper-delay.toml"
    path.write_text(scenario.load("paper").source + "\n[network]\nseed = 3\n[network.actuation]\ndelay = 0.005\n"
                                                    "jitter = 0.002\n")
    sc = scenario.load(str(path))
    run_id = f"t{os.getpid()}nsphys{secrets.token_hex(3)}"
    rt = ("--realtime",) if fifo_permitted() else ()
    dl = ("--deadline", "0.9")
    rc, s, err = live_exact(run_id, str(path), "--netns", "--duration", "30", "--timing", "physical", *dl, *rt)
    assert rc == 0, (s["faults"], err[-2000:])
    assert s["timing_mode"] == "physical" and s["complete"] and s["rule"] == "delay-aware"
    assert s["samples"] == 300 and s["converged"] and s["final_norm"] < 1e-4, s["final_norm"]
    rows = s["node_summaries"]["plant"]["channel"]["actuation"]["delay_s"]
    delay = channel.draws(sc.network, "actuation", 300).delay
    assert len(rows) >= 250 and all(model == delay[k] and realized >= model - 1e-4 for k, model, realized in rows)
    rc, out, err = run_cli(tb_cmd("resimulate", s["recording"]["path"], "--json"))
    r = json.loads(out)
    assert r["reproduced"] and r["max_state_error"] <= 1e-9 and r["symbols_identical"], r
    rc, out, err = run_cli(tb_cmd("simulate", "paper", "--timing", "physical", *dl, "--json"))
    sim = json.loads(out)
    for key in ("symbols", "theta", "E", "x"):
        assert s[key] == sim[key], mismatch(s, sim, key)
    assert not _left(run_id)


@pytest.mark.process
def test_netns_bursty_symbol_channel_equals_the_simulator(tmp_path):
    """A Gilbert-Elliott symbol link (loss 0.15, mean burst 3) across network namespaces: the run equals
    ``testbed simulate`` of the same scenario and seed bit for bit; ``testbed report --json`` of its
    recording tells the losses apart as the simulator does (the channel's positive, the attacker's those
    its schedule covers), and the recording shows the channel's losses in bursts."""
    from testbed import scenario

    _require_netns()
    path = tmp_path / "paper-burst.toml"
    path.write_text(scenario.load("paper").source + "\n[network]\nseed = 5\n[network.symbol]\nloss = 0.15\n"
                                                    "loss_burst = 3.0\n")
    run_id = f"t{os.getpid()}nsburst{secrets.token_hex(3)}"
    rc, s, err = live_exact(run_id, str(path), "--netns", "--duration", "10")
    assert rc == 0, (s["faults"], err[-2000:])
    sim = simulate(str(path), 10)
    for key in BIT_EXACT_KEYS:
        assert s[key] == sim[key], mismatch(s, sim, key)
    rc, out, err = run_cli(tb_cmd("report", s["recording"]["path"], "--json"))
    assert rc == 0, err
    rep = json.loads(out)
    assert rep["losses"] == sim["losses"] and rep["losses"]["channel"] > 0, (rep["losses"], sim["losses"])
    assert rep["losses"]["attacker"] == len(s["attacker_dropped_at"]) > 0
    assert "attacker's losses only" in rep["dos"]["counts"]
    from testbed.record import reader

    lost = reader.read(s["recording"]["path"]).summaries["controller"]["channel"]["symbol"]["lost_at"]
    runs = [j - i for i, j in zip(lost, lost[1:]) if j - i == 1]
    assert len(runs) >= 3, lost  # consecutive samples lost by the channel: bursts
    assert not _left(run_id)


@pytest.mark.process
def test_netns_a_cut_next_to_a_channel_model_tells_the_causes_apart(tmp_path):
    """A lossy symbol link (the [network] model) and a 1 s --cut of the controller's link in one run: the
    samples the model dropped are the channel's, those the cut took the real network's (never the
    channel's), and the five causes add up to the samples lost in the JSON and in the report's text."""
    from testbed import scenario
    from testbed.record import reader

    _require_netns()
    path = tmp_path / "paper-lossy.toml"
    path.write_text(scenario.load("paper").source + "\n[network]\nseed = 5\n[network.symbol]\nloss = 0.1\n")
    run_id = f"t{os.getpid()}nscause{secrets.token_hex(3)}"
    # the cut between the paper's two attacks ([1.0, 2.2] s and [4.0, 4.8] s), half a period away from any
    # sample: a cut at a sample's own time (2.6 s) can fall between its symbol's arrival and its actuation,
    # losing only the ack, and then the outage's samples are all withheld, none the network's
    rc, s, err = live(run_id, str(path), "--netns", "--duration", "5", "--cut", "controller@2.65:1")
    assert rc == 0, (s["faults"], err[-3000:])
    ls = s["losses"]
    assert sum(ls.values()) == s["packets_dropped"], ls
    cut = [f for f in s["faults"] if f["kind"] == "link_cut"][0]
    T = s["T"]
    during = set(range(int(cut["down_s"] / T) + 1, int(cut["up_s"] / T)))   # samples wholly inside the outage
    rec = reader.read(s["recording"]["path"])
    from testbed.loop.channel import model_lost

    recorded = set(rec.summaries["controller"]["channel"]["symbol"]["lost_at"])   # the stage's own record
    model = {int(k) for k in np.flatnonzero(model_lost(scenario.load(str(path)).network, s["n_steps"]))}
    assert recorded <= model   # the stage dropped what the model's draws say, nothing else
    other = set(s["attacker_dropped_at"]) | set(s["withheld_at"])
    # what the cut took and the model did not decide: the real network's (or late, when it came after all)
    taken = during - model - other
    assert taken and ls["network"] + ls["late"] >= len(taken), (sorted(taken), ls)
    # the channel's: only samples the model's draws lose
    assert 0 < ls["channel"] <= len(model), (ls, sorted(model))
    rc, out, err2 = run_cli(tb_cmd("report", s["recording"]["path"]))
    assert rc in (0, 1), err2
    assert (f"losses by cause: attacker {ls['attacker']}, channel {ls['channel']}, network {ls['network']}, "
            f"late {ls['late']}, withheld {ls['withheld']}") in out, out
    assert not _left(run_id)
