"""Process tier: real ``testbed run`` / ``testbed node`` processes over Zenoh on loopback.

Run with ``pytest -m process``.  Every test uses its own run id (key prefix) and
port, runs under a timeout, and checks that no process of its run survives.
"""

from __future__ import annotations

import json
import math
import os
import secrets
import signal
import subprocess
import time

import pytest
from failclosed import require
from helpers.cli import TIMEOUT, run_cli, tb_cmd
from helpers.live import (
    BIT_EXACT_KEYS,
    LOGS,
    TOPOLOGIES,
    WITH_ROUTER,
    live,
    live_exact,
    mismatch,
    resimulated,
    simulate,
    transport_of,
)
from helpers.procs import procs_with, reap
from helpers.verdicts import assert_physical_timing_on_the_paper

from testbed.nodes.process import fifo_permitted

pytestmark = pytest.mark.process

# ====================================================================== ideal timing: bit for bit
@pytest.fixture(scope="module", params=TOPOLOGIES)
def paper_run(request):
    rid = f"t{os.getpid()}xpaper{secrets.token_hex(3)}"
    try:
        yield live_exact(rid, "paper", "--duration", "5", *request.param)
    finally:
        left = reap(rid)
        assert not left


def test_paper_live_equals_simulator_bit_for_bit(paper_run):
    rc, s, err = paper_run
    assert rc == 0, (s["faults"], err[-2000:])
    assert s["complete"] and s["samples"] == 50 and s["outcome"] == "done"
    # the default on one host: the peer topology (direct links, mutual TLS), chosen by --topology auto
    sec = s["security"]
    assert (sec["topology"], sec["transport"], sec["topology_auto"]) == ("peer", "mutual tls", True), sec
    assert sec["topology_why"] == "every node runs on the launcher's host" and sec["authenticated"]
    sim5 = simulate("paper", 5)
    for key in BIT_EXACT_KEYS:
        assert s[key] == sim5[key], mismatch(s, sim5, key)
    # ... and the same samples of the full 30 s `testbed simulate paper`
    sim30 = simulate("paper", 30)
    for key in ("symbols", "theta", "E", "E_dec", "xi", "x", "u"):
        assert s[key] == sim30[key][:50], mismatch(s, {c: v[:50] if isinstance(v, list) else v
                                                       for c, v in sim30.items()}, key)
    assert s["encoder_decoder_agree"] is True
    # the paper's bursts [1.0, 2.2] and [4.0, 4.8]: samples 10..22 and 40..48
    assert sum(s["theta"]) == 22 and s["attacker"]["dropped"] == 22


def test_paper_live_reports_sizes_and_timing(paper_run):
    _, s, _ = paper_run
    assert s["sizes"]["symbol_payload_bytes"] == 1 and s["sizes"]["header_bytes"] == 12
    tm = s["timing"]
    # a stalled machine may make the controller's u_k = 0 for a *dropped* sample late (40 ms loss
    # deadline vs the plant's 50 ms; the plant then applies u_k = 0 itself, so the run stays exact);
    # a received sample never missed, and most dropped ones did not either
    assert tm["deadline_misses"] == len(s["deadline_missed_at"]) <= sum(s["theta"]) // 2, s["deadline_missed_at"]
    assert all(s["theta"][k] == 1 for k in s["deadline_missed_at"]), (s["deadline_missed_at"], s["theta"])
    assert tm["sampling_jitter_us"]["n"] == 50
    assert tm["sensor_to_actuator_us"]["n"] == 28  # the 28 samples that reached the controller
    for stage in ("encoder", "proxy", "controller", "plant"):
        assert tm["stages_us"][stage]["n"] > 0
    assert tm["sensor_to_actuator_us"]["p50"] < 0.5 * 100_000  # the median inside the 50 ms deadline
    # the attacker published its status on both edges of the first burst (on at sample 10, off after 22)
    st = s["attacker_status"]
    assert [x["attack_on"] for x in st][:2] == [True, False] and st[0]["k"] == 10 and st[1]["k"] > 22, st
    for r in ("plant", "encoder", "attacker", "controller"):
        assert s["nodes"][r]["exit_code"] == 0
        assert r in s["node_summaries"]
    colocated = s["node_summaries"]["plant"]["colocated"] == ["encoder"]
    assert (s["nodes"]["encoder"].get("colocated_in") == "plant") == colocated
    assert (s["node_summaries"]["encoder"]["pid"] == s["node_summaries"]["plant"]["pid"]) == colocated
    assert s["node_summaries"]["controller"]["ack"] == "on the actuation"
    # nodes leaving at the end of a clean run are not reported as lost peers
    assert "peer_lost" not in s["events"] and "controller_lost" not in s["events"], s["events"]


@pytest.mark.parametrize("topology", WITH_ROUTER)
def test_greedy_attacker_live_equals_simulator(run_id, topology):
    rc, s, err = live_exact(run_id, "paper-greedy", "--duration", "4", *topology)
    assert rc == 0, (s["faults"], err[-2000:])
    assert s["security"]["authenticated"]
    assert s["security"]["transport"] == transport_of(topology)
    sim = simulate("paper-greedy", 4)
    for key in BIT_EXACT_KEYS:
        assert s[key] == sim[key], mismatch(s, sim, key)
    assert s["node_summaries"]["attacker"]["missing_scores"] == 0


def test_realtime_runs_the_nodes_and_the_router_under_sched_fifo(run_id):
    """--realtime: every node's loop and the launcher's router threads under SCHED_FIFO; the run is the
    simulator's bit for bit.  With the default (auto), a run at T = 0.1 s asks for none, one at 5 ms for all."""
    if not fifo_permitted():
        require("fifo", "SCHED_FIFO is not permitted here (needs root or CAP_SYS_NICE)")
    rc, s, err = live_exact(run_id, "paper", "--duration", "3", "--realtime", "--no-record", "--topology", "router")
    assert rc == 0, (s["faults"], err[-2000:])
    assert s["launcher"]["sched_fifo"] is True and s["launcher"]["spawn"] == "fork"
    assert all(s["node_summaries"][r]["sched_fifo"] is True for r in ("plant", "encoder", "attacker", "controller"))
    sim = simulate("paper", 3)
    for key in BIT_EXACT_KEYS:
        assert s[key] == sim[key], mismatch(s, sim, key)
    rc, s, err = live(run_id + "n", "paper", "--duration", "1", "--no-record")  # auto, T = 0.1 s: not asked for
    assert rc == 0 and s["launcher"]["sched_fifo"] is False and s["launcher"]["realtime"] == "auto"
    assert not any(s["node_summaries"][r]["sched_fifo"] for r in ("plant", "encoder", "attacker", "controller"))
    rc, s, err = live(run_id + "f", "paper", "--T", "0.005", "--duration", "1", "--no-record")  # auto, T < 10 ms
    assert rc == 0, (s["faults"], err[-2000:])
    assert s["launcher"]["sched_fifo"] is True
    assert all(s["node_summaries"][r]["sched_fifo"] is True for r in ("plant", "encoder", "attacker", "controller"))


# ====================================================================== faults
@pytest.mark.parametrize("topology", TOPOLOGIES)
def test_malformed_and_out_of_range_payloads_are_losses(run_id, topology):
    """The attacker corrupts samples 4 (out-of-range code) and 6 (wrong length)."""
    rc, s, err = live_exact(run_id, "paper", "--duration", "3", "--corrupt", "4:range,6:length", *topology)
    assert rc == 0, (s["faults"], err[-2000:])
    assert s["invalid_payloads"] == 2
    assert s["theta"][4] == 1 and s["theta"][6] == 1 and s["symbols"][4] != -1
    assert s["loss_reasons"]["invalid"] == 2
    assert [e["k"] for e in s["event_log"] if e["kind"] == "invalid_payload"] == [4, 6]
    # the loop is exactly the simulator's with the same corruption
    rc, out, err = run_cli(tb_cmd("simulate", "paper", "--duration", "3", "--corrupt", "4:range,6:length", "--json"))
    sim = json.loads(out)
    for key in BIT_EXACT_KEYS:
        assert s[key] == sim[key], mismatch(s, sim, key)
    r = resimulated(s)
    assert r["reproduced"] and r["max_state_error"] == 0 and r["symbols_identical"] and r["E_identical"]


def _after(s, k0):
    return range(k0 + 2, s["samples"])


@pytest.mark.parametrize("topology", WITH_ROUTER)
def test_controller_killed_plant_runs_on_with_zero_input(run_id, topology):
    rc, s, err = live(run_id, "paper", "--duration", "3", "--kill", "controller@1.05", *topology)
    assert rc == 1
    (f,) = [f for f in s["faults"] if f["node"] == "controller"]
    assert f["kind"] == "killed" and f["signal"] == "SIGKILL" and f["injected"]
    assert f["liveliness_lost"] and f["liveliness_detect_ms"] < 1000
    assert "controller died" in err
    k0 = s["controller_lost_at"]
    assert 9 <= k0 <= 14  # killed at 1.05 s; a loaded machine may kill or notice a sample or two late
    assert s["complete"] and s["samples"] == 30  # the plant ran to the end
    assert all(s["u"][k] == [0.0] for k in _after(s, k0))
    assert s["timing"]["u_missing"] >= 30 - k0 - 1
    assert s["events"].get("controller_lost") == 1
    assert_recording_kept_the_run(s, "controller", k0)


def assert_recording_kept_the_run(s: dict, killed: str, k_kill: int) -> None:
    """Crash safety: the run's MCAP (the default one) holds the whole run, the killed node's
    samples up to its death, and the launcher's fault event."""
    from testbed.record import reader

    rec = reader.read(s["recording"]["path"])
    assert not rec.truncated and s["recording"]["complete"], rec.read_error
    assert sorted(rec.telemetry["plant"]) == list(range(s["samples"]))
    ks = sorted(rec.telemetry[killed])
    assert ks == list(range(len(ks))) and k_kill - 2 <= len(ks) <= k_kill + 2, (killed, k_kill, ks[-3:])
    assert any(e.node == "launcher" and e.kind == f"{killed}_killed" for e in rec.events)


@pytest.mark.parametrize("topology", TOPOLOGIES)
@pytest.mark.parametrize("node", ["encoder", "attacker"])
def test_uplink_node_killed_controller_counts_losses(run_id, node, topology):
    """Killing the encoder when it is colocated kills it alone (the launcher's SIGUSR2 to the plant's
    process): the plant runs on, and the run looks as if the encoder's own process had been killed."""
    rc, s, err = live(run_id, "paper", "--duration", "3", "--kill", f"{node}@0.55", *topology)
    assert rc == 1
    (f,) = [f for f in s["faults"] if f["node"] == node]
    assert f["kind"] == "killed" and f["liveliness_lost"]
    assert s["complete"]
    k0 = f["at_sample"]
    assert 4 <= k0 <= 9  # killed at 0.55 s; a loaded machine may kill or notice a sample or two late
    assert all(s["theta"][k] == 1 for k in _after(s, k0))
    assert s["loss_reasons"]["deadline"] >= 30 - k0 - 2
    # the controller still answers the lost samples (u = 0) before the plant's deadline: only
    # 10 ms of margin, so a loaded 2-core machine may push a few late; a controller that did not
    # answer would miss every one of the ~24
    assert s["timing"]["deadline_misses"] <= 3
    assert any(e["kind"] == "peer_lost" and node in e["detail"] for e in s["event_log"])
    assert_recording_kept_the_run(s, node, k0)


def test_exec_spawn_equals_simulator(run_id):
    """``--spawn exec``: each node a fresh ``python -m testbed.cli node`` (the path ``--node-prefix``
    takes) instead of a fork of the launcher; the same run, bit for bit."""
    rc, s, err = live_exact(run_id, "paper", "--duration", "3", "--spawn", "exec", "--no-record")
    assert rc == 0, (s["faults"], err[-2000:])
    sim = simulate("paper", 3)
    for key in BIT_EXACT_KEYS:
        assert s[key] == sim[key], mismatch(s, sim, key)
    assert len({s["node_summaries"][r]["pid"] for r in ("plant", "encoder", "attacker", "controller")}) == 4


@pytest.mark.parametrize("rx", ["thread", "direct", "spin"])
def test_receive_modes_equal_simulator(run_id, rx):
    """``--rx thread`` (the default: a handler on a thread of its own per subscriber), ``--rx direct``
    (handlers on Zenoh's receive thread) and ``--rx spin`` (the primary input through an ``Inlet``, its own
    thread spinning before the input is due): the same run, bit for bit."""
    rc, s, err = live_exact(run_id, "paper", "--duration", "3", "--rx", rx, "--no-record")
    assert rc == 0, (s["faults"], err[-2000:])
    sim = simulate("paper", 3)
    for key in BIT_EXACT_KEYS:
        assert s[key] == sim[key], mismatch(s, sim, key)
    for role in ("plant", "encoder", "attacker", "controller"):
        assert s["node_summaries"][role]["rx"] == rx, (role, s["node_summaries"][role])
    inlets = {r: v["rx_inlet"] for r, v in s["node_summaries"].items() if "rx_inlet" in v}
    if rx == "spin":  # every node's primary input went through its Inlet, which saw the messages
        assert inlets and all(v["spun"] + v["woken"] > 0 for v in inlets.values()), inlets
    else:
        assert not inlets, inlets


def test_colocated_encoder_killed_just_before_the_end_is_reported(run_id):
    """Its host closes a colocated encoder at the end too: the launcher tells that apart from a
    death near the end (no summary from the encoder, though the plant's came), and a clean run's
    closing is never reported as a death (``test_greedy_attacker_live_equals_simulator[colocated]``)."""
    rc, s, err = live(run_id, "paper", "--duration", "3", "--kill", "encoder@2.85",
                      "--colocate", "encoder", "--no-record")
    assert rc == 1, err[-2000:]
    (f,) = [f for f in s["faults"] if f["node"] == "encoder"]
    assert f["kind"] == "killed" and f["injected"] and f["colocated_in"] == "plant"
    assert 26 <= f["at_sample"] <= 29
    assert s["complete"]


def test_node_crash_is_reported_with_its_reason(run_id):
    rc, s, err = live(run_id, "paper", "--duration", "3", "--crash", "controller@8")
    assert rc == 1
    (f,) = [f for f in s["faults"] if f["node"] == "controller"]
    assert f["kind"] == "crashed" and f["exit_code"] == 1
    assert "injected crash of the controller at sample 8" in f["last_log_line"]
    assert 8 <= s["controller_lost_at"] <= 13
    assert s["complete"]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_launcher_signal_stops_everything(run_id, sig):
    p = subprocess.Popen(tb_cmd("run", "paper", "--json", "--run-id", run_id, "--duration", "30",
                                "--run-dir", os.path.join(LOGS, run_id)),
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        end = time.monotonic() + TIMEOUT
        while len(procs_with(run_id)) < 5 and time.monotonic() < end:  # launcher + 4 nodes
            time.sleep(0.1)
        time.sleep(1.0)
        t = time.monotonic()
        p.send_signal(sig)
        out, err = p.communicate(timeout=30)
        assert time.monotonic() - t < 15
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.communicate()
    assert p.returncode == 128 + sig
    s = json.loads(out)
    assert s["outcome"].startswith("interrupted")
    assert reap(run_id, wait=3.0) == []


# ====================================================================== ack channel, timing modes
@pytest.mark.parametrize("topology", TOPOLOGIES)
def test_ack_through_the_attacker_keeps_lockstep(run_id, topology):
    rc, s, err = live_exact(run_id, "paper", "--duration", "6", "--ack-via-attacker", *topology)
    assert rc == 0, (s["faults"], err[-2000:])
    assert s["attacker"]["acks_dropped"] >= 13
    ns = s["node_summaries"]["encoder"]
    assert ns["desync_episodes"] >= 1 and ns["inconsistent_acks"] == 0
    # wherever both ends recorded xi_k, E_k they are identical: no desync, ever
    known = [k for k in range(s["samples"]) if s["E"][k] is not None and s["E_dec"][k] is not None]
    assert len(known) == s["samples"] - len(s["withheld_at"]) > 30
    assert all(s["E"][k] == s["E_dec"][k] and s["xi"][k] == s["xi_dec"][k] for k in known)
    assert s["encoder_decoder_agree_where_known"] is True
    # withholding happens only while the jammer is on (or right after), exactly as the simulator says
    assert set(s["withheld_at"]) <= set(range(10, 24)) | set(range(40, 50))
    assert s["saturations"] == 0
    rc, out, err = run_cli(tb_cmd("simulate", "paper", "--duration", "6", "--ack-via-attacker", "--json"))
    sim = json.loads(out)
    for key in ("withheld_at", "symbols", "theta", "E", "E_dec", "x", "u"):
        assert s[key] == sim[key], mismatch(s, sim, key)
    r = resimulated(s)
    assert r["reproduced"] and r["max_state_error"] == 0 and r["symbols_identical"] and r["E_identical"]


@pytest.mark.parametrize("topology", TOPOLOGIES)
def test_physical_timing_converges_on_the_paper_and_resimulates(run_id, topology):
    """The paper's scenario and attacks with u_k acting at a real instant (``helpers.verdicts.assert_physical_timing_
    on_the_paper``): it converges, equals the simulator bit for bit, and the recording re-simulates exactly."""
    assert_physical_timing_on_the_paper(run_id, topology)


def test_physical_timing_on_arrival_survives_latency(run_id, tmp_path):
    """u_k acts when it arrives, the paper's rule: the latency is model mismatch, answered by the
    saturation protocol.  Without DoS, x_k leaves Q(xi_k, E_k) whenever E_k has zoomed in below the
    mismatch; the encoder sends OVERFLOW, both ends zoom out in lockstep and the state keeps decaying.
    """
    from testbed import scenario

    text = scenario.load("paper").source.replace('kind = "intervals"', 'kind = "none"')
    text = "\n".join(line for line in text.splitlines() if not line.startswith("intervals"))
    f = tmp_path / "paper-no-dos.toml"
    f.write_text(text)
    rc, s, err = live_exact(run_id, str(f), "--duration", "6", "--timing", "physical", "--actuation", "arrival",
                            "--rule", "paper")
    assert rc == 0, (s["faults"], err[-2000:])
    assert s["timing_mode"] == "physical" and s["complete"]
    assert s["encoder_decoder_agree"] is True
    assert sum(s["theta"]) == 0
    assert s["timing"]["sensor_to_actuator_us"]["n"] == 60
    # every saturation was answered with the OVERFLOW codeword (M^n = 36), u_k = 0 there
    assert all(s["symbols"][k] == 36 and s["u"][k] == [0.0] for k in s["saturated_at"])
    assert not s["diverged"] and s["final_norm"] < 0.1
    r = resimulated(s)
    assert r["reproduced"] and r["max_state_error"] <= 1e-9 and r["symbols_identical"], r


@pytest.mark.parametrize("topology", ["router", "peer", "router-tls"])
def test_standalone_nodes(run_id, tmp_path, topology):
    """Four ``testbed node`` processes started by hand (no launcher) run a scenario to the end.

    Router: the plant is the run's router; the others authenticate with a secret file made by
    ``testbed secret``.  Peer: every link mutual TLS with a folder made by ``testbed secret --tls``;
    the others find each other through the plant.  The test itself is the run's collector (the
    launcher's credentials; the plant, started with ``--wait-collector``, waits for it).  Router-tls: the
    router topology over mutual TLS (``--topology router --tls-dir``, the way in for a device without
    passwords, docs/protocol.md): the plant is the router and checks by certificate name.  Every node's
    summary says the run ended because the plant finished all 20 samples, and the plant's telemetry
    holds every sample and the final state.
    """
    import threading

    import zenoh

    from testbed.wire import messages as msg
    from testbed.wire import transport

    peer = topology == "peer"
    tls = topology != "router"
    secret = str(tmp_path / ("tls" if tls else "run.secret"))
    assert subprocess.run(tb_cmd("secret", secret, *(["--tls"] if tls else [])), capture_output=True).returncode == 0
    cred = ["--topology", topology.split("-")[0], "--tls-dir", secret] if tls else ["--secret-file", secret]
    port = transport.free_port()
    ep = f"{'tls' if tls else 'tcp'}/127.0.0.1:{port}"
    keys = transport.Keys.for_run(run_id)
    summaries, rows, lock = {}, {}, threading.Lock()

    def on_summary(sample):
        s = msg.NodeSummary.decode(sample.payload)
        with lock:
            summaries[s.node] = s.data

    def on_telemetry(sample):
        role = transport.Keys.node_of(sample.key_expr)
        for rec in msg.unpack_batch(sample.payload):
            t = msg.TELEMETRY_TYPES[role].decode(rec)
            with lock:
                rows.setdefault(role, {})[t.k] = t

    procs = {}
    try:
        for role in ("encoder", "attacker", "controller", "plant"):  # plant last: the others wait for it
            net = ["--listen", ep, "--wait-collector"] if role == "plant" else ["--connect", ep]
            procs[role] = subprocess.Popen(tb_cmd("node", role, "paper", "--duration", "2", "--run-id", run_id,
                                                   *cred, *net),
                                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                           text=True, start_new_session=True)
        if tls:
            conf = transport.make_config(connect=[ep], mode="peer" if peer else "client",
                                         tls=transport.TlsCredentials(secret).zenoh(transport.LAUNCHER))
        else:
            cred_file = transport.Credentials.read(secret)
            conf = transport.make_config(connect=[ep], mode="client", user=transport.LAUNCHER,
                                         password=cred_file.password(transport.LAUNCHER))
        with zenoh.open(conf) as session:
            subs = [session.declare_subscriber(keys.summary("*"), on_summary),
                    session.declare_subscriber(keys.telemetry("*"), on_telemetry)]
            ready = session.liveliness().declare_token(keys.ready(transport.COLLECTOR))
            outs = {r: p.communicate(timeout=TIMEOUT)[0] for r, p in procs.items()}
            time.sleep(0.5)  # the last summaries in flight
            ready.undeclare()
            for sub in subs:
                sub.undeclare()
    finally:
        for p in procs.values():
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.communicate()
    for r, p in procs.items():
        assert p.returncode == 0, (r, outs[r][-2000:])
    # the plant ran every sample and ended the run: "done"
    done = ("done", "stop from plant: done")  # the plant's own: whichever of its stop and its message comes first
    assert summaries["plant"]["stop_reason"] in done and summaries["plant"]["samples"] == 20, summaries["plant"]
    assert summaries["plant"]["error"] is None
    plant_rows = dict(rows["plant"])
    final = plant_rows.pop(20)
    assert final.flags & msg.PlantTelemetry.FLAG_FINAL and len(final.x) == 2
    assert sorted(plant_rows) == list(range(20))
    assert all(math.isfinite(v) for t in plant_rows.values() for v in (*t.x, *t.u)), plant_rows
    # every other node took part from the first sample on (its telemetry), and ended when the plant did (its
    # stop, or its going away when that came first): the plant is the router, so a summary sent after it
    # closed is lost; those that arrived say so
    for r in ("encoder", "attacker", "controller"):
        assert set(range(10)) <= set(rows.get(r, {})), (r, sorted(rows.get(r, {})))
    for r, d in summaries.items():
        assert d["error"] is None and d["stop_reason"] in done + ("plant lost",), (r, d)


def test_mismatched_run_options_are_refused(run_id):
    """A node started with other run options than the plant's does not join the run."""
    from testbed.wire import transport

    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    procs = {}
    try:
        for role in ("plant", "encoder", "attacker", "controller"):
            extra = ["--duration", "3" if role == "controller" else "2"]
            net = ["--listen", ep] if role == "plant" else ["--connect", ep]
            procs[role] = subprocess.Popen(tb_cmd("node", role, "paper", "--run-id", run_id, "--ready-timeout",
                                                   "60", "--insecure", *extra, *net), stdout=subprocess.PIPE,
                                           stderr=subprocess.STDOUT, text=True, start_new_session=True)
        out = procs["controller"].communicate(timeout=TIMEOUT)[0]
        assert procs["controller"].returncode == 2, out[-2000:]
        assert "digest mismatch" in out
    finally:
        for p in procs.values():
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)
        for p in procs.values():
            try:
                p.communicate(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.communicate()
