"""Process tier: what an outsider and a misbehaving insider can do to a live run.

Outsider: any local process, without the run's credentials, that finds the run's
ports (in /proc) and connects to every one of them.  It must change nothing: the
run completes, equals the simulator bit for bit, and its recording is complete.

Insider: a process that holds the credentials of one node (the run is started with
a given ``--secret-file``, or in the peer topology a given ``--tls-dir``) and misbehaves.
The access control (the router's, or in the peer topology every receiver's) drops
whatever it publishes outside its own keys; what it may publish is
checked by the receivers (non-finite or huge u, a sample index from the future,
telemetry of a sample outside the run, a stop from the wrong node, telemetry that
differs from the node's own account): each is counted and logged, nothing crashes,
and a falsified run never reports success.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import threading
import time

import pytest
from failclosed import rerun_flags, rerun_while_stalled
from helpers.cli import TIMEOUT, tb_cmd
from helpers.live import LOGS, mismatch, simulate
from helpers.procs import procs_with
from helpers.verdicts import OUTSIDER_S, assert_outsider_changed_nothing

from testbed.wire import messages as msg
from testbed.wire import transport

pytestmark = pytest.mark.process


def listening_ports(token: str) -> list[int]:
    """TCP ports the processes of a run listen on (their sockets' inodes against /proc/net/tcp)."""
    inodes = set()
    for pid in procs_with(token):
        try:
            for fd in os.listdir(f"/proc/{pid}/fd"):
                try:
                    link = os.readlink(f"/proc/{pid}/fd/{fd}")
                except OSError:
                    continue
                if link.startswith("socket:["):
                    inodes.add(link[8:-1])
        except OSError:
            continue
    ports = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = open(table).read().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            f = line.split()
            if f[3] == "0A" and f[9] in inodes:  # LISTEN
                ports.add(int(f[1].rsplit(":", 1)[1], 16))
    return sorted(ports)


def start_run(run_id: str, *args) -> subprocess.Popen:
    return subprocess.Popen(tb_cmd("run", "paper", "--json", "--run-id", run_id,
                                   "--run-dir", os.path.join(LOGS, run_id), *args),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)


def finish(p: subprocess.Popen) -> tuple[int, dict, str]:
    try:
        out, err = p.communicate(timeout=TIMEOUT)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.communicate()
    try:
        return p.returncode, json.loads(out), err
    except json.JSONDecodeError:
        pytest.fail(f"no JSON summary (exit {p.returncode})\n{out[-2000:]}\n{err[-3000:]}")


def wait_running(run_id: str, p: subprocess.Popen, timeout: float = TIMEOUT) -> None:
    """Until the run's processes are there and (at a guess) past their start-up."""
    end = time.monotonic() + timeout
    while time.monotonic() < end and p.poll() is None:
        if len(procs_with(f"--run-id {run_id}")) >= 5:
            break
        time.sleep(0.1)
    time.sleep(1.5)  # start-up (imports, JIT warm-up)


def forge_everything(session, keys: transport.Keys, n_steps: int, k_now: int, symbol_tx: bool = True) -> None:
    """Every attack of the issue: a stop, a symbol from the future, huge and NaN actuation, forged telemetry."""
    session.put(keys.stop, msg.Stop(reason="forged", origin="plant").encode())
    session.put(keys.symbol_rx, b"\x00", attachment=msg.Header(n_steps - 1, 0).encode())
    for u in (1e12, math.nan, 3.0):
        p, a = msg.Actuation(k_now, 0, 0, (u,)).encode()
        session.put(keys.actuation, p, attachment=a)
    fake = msg.PlantTelemetry(k=2**32 - 2, t_ns=0, sensor_tx_ns=0, u_rx_ns=0, delay_ns=0, theta=0, flags=0,
                              flow_status=0, x=(1e-9, 1e-9), u=(0.0,))
    session.put(keys.telemetry("plant"), msg.pack_batch([fake.encode()]))
    final = msg.PlantTelemetry(k=n_steps, t_ns=0, sensor_tx_ns=msg.NO_TIME, u_rx_ns=msg.NO_TIME, delay_ns=0,
                               theta=msg.THETA_NONE, flags=msg.PlantTelemetry.FLAG_FINAL, flow_status=0,
                               x=(1e-9, 1e-9), u=())
    session.put(keys.telemetry("plant"), msg.pack_batch([final.encode()]))
    for _ in range(5):  # valid symbols for the current sample
        if symbol_tx:
            session.put(keys.symbol_tx, b"\x07", attachment=msg.Header(k_now, 0).encode())
        session.put(keys.symbol_rx, b"\x07", attachment=msg.Header(k_now, 0).encode())


def _run_ca(run_id, into) -> str:
    """A copy of the run's authority certificate (no secret; the run removes its folder as it ends)."""
    import glob
    import shutil

    (ca,) = glob.glob(os.path.join(LOGS, run_id, "secrets-*", "tls", "ca.pem"))
    return shutil.copyfile(ca, os.path.join(into, f"{run_id}-ca.pem"))


def _outsider_configs(pt, peer, foreign, ca=None):
    """How an outsider tries port ``pt``: no credentials and a wrong password (router), or (peer, whose
    links are TLS) plain TCP, and TLS that trusts the run's authority (its certificate is no secret) with a
    certificate named "plant" of another authority (``foreign``)."""
    if not peer:
        return [transport.make_config(connect=[f"tcp/127.0.0.1:{pt}"], mode="peer", user=user, password=pw)
                for user, pw in ((None, None), ("plant", "guess"))]
    tls = dict(transport.TlsCredentials(foreign).zenoh("plant"), root_ca_certificate=ca)
    return [transport.make_config(connect=[f"tcp/127.0.0.1:{pt}"], mode="peer"),
            transport.make_config(connect=[f"tls/127.0.0.1:{pt}"], mode="peer", tls=tls)]


def _outsider_run(run_id, peer=False, foreign=None, more=()):
    """An 8 s run with an outsider forging everything on every port it listens on, until it ends."""
    import zenoh

    port = transport.free_port()
    keys = transport.Keys.for_run(run_id)
    p = start_run(run_id, "--duration", str(OUTSIDER_S), "--listen", f"{'tls' if peer else 'tcp'}/127.0.0.1:{port}",
                  *(() if peer else ("--topology", "router")), *more)  # peer: the default on one host
    forged, refused, seen = [], [], set()
    try:
        wait_running(run_id, p)
        ca = _run_ca(run_id, LOGS) if peer else None
        while p.poll() is None:  # again and again, on every port the run's processes listen on, until it ends
            ports = listening_ports(run_id)
            seen.update(ports)
            for pt in ports:
                for conf in _outsider_configs(pt, peer, foreign, ca):
                    try:
                        with zenoh.open(conf) as session:
                            forge_everything(session, keys, 10 * OUTSIDER_S, 30)
                            time.sleep(0.1)
                    except zenoh.ZError as e:
                        refused.append((pt, str(e)))
                        continue
                    forged.append(pt)  # a session that opened and published everything
            time.sleep(0.2)
    finally:
        rc, s, err = finish(p)
    # only attempts whose session opened count: an outsider that never got to publish proves nothing
    assert port in forged and len(forged) >= 10, (seen, len(forged), refused[:3])
    return rc, s, err


@pytest.mark.parametrize("topology", ["router", "peer"])
def test_an_outsider_without_credentials_changes_nothing(run_id, topology, tmp_path):
    """Router: no password or a wrong one.  Peer (mutual TLS): plain TCP, or a certificate named after a
    node but made by another authority.  Neither gets a link: nothing reaches a node."""
    foreign = transport.TlsCredentials.new(tmp_path / "foreign").folder if topology == "peer" else None
    assert_outsider_changed_nothing(run_id, topology, _outsider_run, foreign)


def insider(secret: str, user: str, port: int, peer: bool = False):
    """A session with ``user``'s credentials: a client of the run's router, or (``peer``: ``secret`` is the
    run's TLS folder) a peer of the mesh holding ``user``'s certificate."""
    import zenoh

    if peer:
        conf = transport.make_config(connect=[f"tls/127.0.0.1:{port}"], mode="peer",
                                     tls=transport.TlsCredentials(secret).zenoh(user))
        return zenoh.open(conf)
    cred = transport.Credentials.read(secret)
    conf = transport.make_config(connect=[f"tcp/127.0.0.1:{port}"], mode="client", user=user,
                                 password=cred.password(user))
    return zenoh.open(conf)


def _insider_run(run_id, secret, colocated, peer=False, more=()):
    """A 6 s run with the encoder's credentials used to forge everything."""
    port = transport.free_port()
    keys = transport.Keys.for_run(run_id)
    net = (("--listen", f"tls/127.0.0.1:{port}", "--topology", "peer", "--tls-dir", secret) if peer else
           ("--listen", f"tcp/127.0.0.1:{port}", "--topology", "router", "--secret-file", secret))
    p = start_run(run_id, "--duration", "6", *net, *(("--colocate", "encoder") if colocated else ()), *more)
    try:
        wait_running(run_id, p)
        with insider(secret, "encoder", port, peer) as session:
            started = threading.Event()
            sub = session.declare_subscriber(keys.actuation, lambda smp: started.set())
            assert started.wait(TIMEOUT), "the run never started"
            sub.undeclare()
            # its own key, unless colocated: an encoder sends symbols
            forge_everything(session, keys, 60, 30, symbol_tx=colocated)
            time.sleep(0.3)
    finally:
        rc, s, err = finish(p)
    return rc, s, err


@pytest.mark.parametrize("colocated,peer", [(False, False), (True, False), (False, True)],
                         ids=["4proc", "colocated", "peer"])
def test_an_insider_outside_its_keys_is_stopped_by_access_control(run_id, tmp_path, colocated, peer):
    """The encoder's credentials, used to publish on every other node's keys: all of it dropped.

    Colocated (the encoder runs in the plant's process), the encoder's user has no keys at all:
    not even its symbols get through.  Peer: the encoder's certificate, on a peer of the mesh that
    links to every process; each receiver drops it."""
    secret = str(tmp_path / ("tls" if peer else "run.secret"))
    assert subprocess.run(tb_cmd("secret", secret, *(("--tls",) if peer else ())),
                          capture_output=True).returncode == 0
    # a run the machine stalled is run again (a new run id); what the insider could cause is no stall,
    # and the last run is compared whatever it reports
    rc, s, err = rerun_while_stalled(lambda attempt: _insider_run(run_id + "r" * attempt, secret, colocated, peer,
                                                                  rerun_flags(attempt)),
                                     "insider outside its keys", attacker=True)
    assert rc == 0, (s["faults"], err[-2000:])
    assert s["complete"] and not s["faults"]
    sim = simulate("paper", 6)
    for key in ("symbols", "theta", "E", "x", "u"):
        assert s[key] == sim[key], mismatch(s, sim, key)


@pytest.mark.parametrize("topology", ["router", "peer"])
def test_an_insider_within_its_keys_is_checked_counted_and_logged(run_id, tmp_path, topology):
    """Credentials of the controller, the attacker and the plant, misused within their keys: a client of
    the run's router each, or (peer) a peer of the mesh with that node's certificate."""
    from testbed import scenario

    peer = topology == "peer"
    secret = str(tmp_path / ("tls" if peer else "run.secret"))
    assert subprocess.run(tb_cmd("secret", secret, *(("--tls",) if peer else ())),
                          capture_output=True).returncode == 0
    sc_file = tmp_path / "paper-umax.toml"  # an actuator limit the forged u runs into without wrecking the run
    sc_file.write_text(scenario.load("paper").source.replace("[controller]\n", "[controller]\nu_max = 2.0\n"))
    port = transport.free_port()
    keys = transport.Keys.for_run(run_id)
    net = (("--listen", f"tls/127.0.0.1:{port}", "--topology", "peer", "--tls-dir", secret) if peer else
           ("--listen", f"tcp/127.0.0.1:{port}", "--topology", "router", "--secret-file", secret))
    p = subprocess.Popen(tb_cmd("run", str(sc_file), "--json", "--run-id", run_id, "--run-dir",
                                os.path.join(LOGS, run_id), "--duration", "6", *net),
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    forged = []
    try:
        wait_running(run_id, p)
        with insider(secret, "controller", port, peer) as ctl, insider(secret, "attacker", port, peer) as att, \
                insider(secret, "plant", port, peer) as plant:
            # each kind three times: under load the real u_k may win a race now and then
            bad_u = [50.0, math.nan, math.inf] * 3
            started, done = threading.Event(), threading.Event()

            def on_sensor(sample):  # u_k forged right after x_k: it reaches the plant before the real one
                h = msg.Header.decode(sample.attachment)
                if h.warmup:
                    return
                started.set()
                if bad_u and h.k >= 15:
                    pl, a = msg.Actuation(h.k, 0, 0, (bad_u.pop(0),)).encode()
                    ctl.put(keys.actuation, pl, attachment=a)
                    forged.append(h.k)
                    if not bad_u:
                        done.set()

            sub = ctl.declare_subscriber(keys.sensor, on_sensor)
            assert started.wait(TIMEOUT), "the run never started"
            ctl.put(keys.actuation, b"\x00", attachment=b"\x00" * 12)                       # malformed
            att.put(keys.symbol_rx, b"\x00", attachment=msg.Header(59, 0).encode())         # from the future
            att.put(keys.symbol_rx, b"\x01", attachment=b"\x00" * 5)                        # bad header
            for _ in range(3):  # not from the plant; three times: a new peer's links to the mesh form under load
                plant.put(keys.stop, msg.Stop(reason="forged", origin="encoder").encode())
                time.sleep(0.2)
            fake = msg.PlantTelemetry(k=2**32 - 2, t_ns=0, sensor_tx_ns=0, u_rx_ns=0, delay_ns=0, theta=0,
                                      flags=0, flow_status=0, x=(1e-9, 1e-9), u=(0.0,))
            for _ in range(3):  # k outside [0, N); three times: a new peer's links to the mesh form under load
                plant.put(keys.telemetry("plant"), msg.pack_batch([fake.encode()]))
                time.sleep(0.2)
            falsified = msg.PlantTelemetry(k=58, t_ns=0, sensor_tx_ns=0, u_rx_ns=0, delay_ns=0, theta=0, flags=0,
                                           flow_status=0, x=(1e-9, 1e-9), u=(0.0,))
            plant.put(keys.telemetry("plant"), msg.pack_batch([falsified.encode()]))       # ahead of the real one
            done.wait(10.0)
            sub.undeclare()
    finally:
        rc, s, err = finish(p)
    assert len(forged) == 9, (forged, s.get("faults"), s.get("samples"), s.get("outcome"), err[-2500:])
    ev = s["events"]
    # a falsified sample never reads as a clean run: the plant's own account differs from what arrived
    assert rc == 1 and any(f["kind"] == "telemetry_mismatch" and f["node"] == "plant" for f in s["faults"]), \
        s["faults"]
    assert s["complete"] and s["samples"] == 60  # every sample ran: no crash, no stop
    ps = s["node_summaries"]["plant"]
    assert ps["inputs_clamped"] >= 1 and ev.get("input_clamped", 0) >= 1, (ps, ev)
    assert ps["inputs_rejected"] >= 1 and ev.get("input_rejected", 0) >= 1, (ps, ev)
    assert s["malformed"]["plant"] >= 1
    assert s["node_summaries"]["controller"]["future"] >= 1 and ev.get("future_symbol", 0) >= 1
    assert s["malformed"]["controller"] >= 1
    assert ev.get("stop_rejected", 0) >= 1
    # the recording counts the sample outside the run, it does not record it
    from testbed.record import reader

    rec = reader.read(s["recording"]["path"])
    assert max(rec.telemetry["plant"]) == 59
    assert json.loads(rec.metadata["testbed.recorder"]["rejected_k"]) >= 1
