"""The C plant device on zenoh-pico (``devices/pico-plant``, docs/devices.md): built from the vendored
sources by its ``build.sh``, it refuses what it cannot run with one line, and as the plant of a live
run of the paper's example (router topology over mutual TLS, ``--external plant``) the run converges,
is recorded completely, and every step of the device's plant is within 1e-9 of the testbed's flow map
phi_T(x_k, u_k) with the u that acted."""

from __future__ import annotations

import json
import os
import shutil
import signal
import stat
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from failclosed import require, rerun_while_stalled
from helpers.cli import PY, run_cli, tb_cmd
from helpers.live import LOGS, JoinAnnounce
from helpers.procs import reap

from testbed.wire import join

ROOT = Path(__file__).resolve().parents[2]
BUILD = ROOT / "devices" / "pico-plant" / "build.sh"
TARBALLS = ("mbedtls-3.6.6.tar.gz", "zenoh-pico-1.9.0.tar.gz")


def _sources_missing() -> str | None:
    """Why build.sh would find no sources here (None: it will), as build.sh looks them up."""
    if os.environ.get("MBEDTLS_SRC") and os.environ.get("ZENOH_PICO_SRC"):
        return None
    dirs = [Path(os.environ["TESTBED_VENDOR"])] if os.environ.get("TESTBED_VENDOR") else \
        [ROOT.parent / "shared" / "vendor", ROOT.parent.parent / "shared" / "vendor"]
    if any(all((d / t).is_file() for t in TARBALLS) for d in dirs):
        return None
    return f"no {' and '.join(TARBALLS)} in {' or '.join(map(str, dirs))} (nor MBEDTLS_SRC and ZENOH_PICO_SRC)"


@pytest.fixture(scope="module")
def device() -> str:
    """The built device (build.sh's last line); its build is cached by source hash under the user's cache."""
    missing = [t for t in ("cmake", "make", "pkg-config") if shutil.which(t) is None]
    if shutil.which("cc") is None and shutil.which("gcc") is None:
        missing.append("cc/gcc")
    if missing:
        require("zenoh-pico", f"building the C device needs {', '.join(missing)} (Debian: apt-get install cmake "
                              "make pkg-config gcc)")
    why = _sources_missing()
    if why:
        require("zenoh-pico", why)
    out = os.environ.get("TESTBED_PICO_OUT") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "testbed", "pico-plant")
    rc, so, se = run_cli(["bash", str(BUILD), out], timeout=1800)
    assert rc == 0, se[-3000:]
    assert "warning:" not in se, se[-3000:]  # the device compiles cleanly with -Wall -Wextra (when it compiles)
    path = so.strip().splitlines()[-1]
    assert os.access(path, os.X_OK) and os.path.realpath(path).startswith(os.path.realpath(out)), (path, se[-2000:])
    return path


def _join_data(tmp_path: Path, **over) -> dict:
    """A join file's fields for an --insecure router run whose router is not there (nothing listens)."""
    toml = (Path(__file__).resolve().parents[2] / "testbed" / "scenario" / "bundled" / "paper.toml").read_text()
    d = {"join_version": 1, "protocol": 1, "role": "plant", "run_id": "nobody", "key_prefix": "testbed/nobody",
         "ack_key": "loop/actuation", "topology": "router", "mode": "client", "connect": ["tcp/127.0.0.1:9"],
         "listen": [], "low_latency": False, "credentials": {"kind": "none"}, "T_ns": 100_000_000, "n_steps": 10,
         "timing": "ideal", "ack_via_attacker": False, "digest": "0123456789abcdef", "t0_ns": None,
         "start_lead_ns": 200_000_000, "wait_ready": ["plant", "encoder", "attacker", "controller", "collector"],
         "ready_timeout_s": 1.0, "run_options": {"deadline": None, "colocate": []},
         "scenario": {"name": "paper", "toml": toml, "base_dir": None}}
    assert set(d) == set(join.NAMES)
    d.update(over)
    return d


def _device_with(device: str, path: Path, text: str, mode: int = 0o600):
    path.write_text(text)
    os.chmod(path, mode)
    p = subprocess.run([device], capture_output=True, text=True, timeout=60, env={**os.environ, join.ENV: str(path)})
    return p.returncode, p.stderr


@pytest.mark.process
def test_the_device_refuses_a_bad_or_unsupported_join_file_with_one_line(device, tmp_path):
    """Untrusted input: every bad or unsupported join file gives one line naming the problem and exit 2;
    a good one with no router behind its endpoint: exit 1 once the startup timeout has passed."""
    f = tmp_path / "join-plant.json"
    good = _join_data(tmp_path)
    sc = good["scenario"]
    cases = [
        (json.dumps(good)[:-7], "not a JSON join file"),
        (json.dumps({**good, "extra": 1}), "unknown extra"),
        (json.dumps({k: v for k, v in good.items() if k != "digest"}), "missing digest"),
        (json.dumps(_join_data(tmp_path, role="controller")), "this device is a plant"),
        (json.dumps(_join_data(tmp_path, topology="peer", mode="peer")), "router topology only"),
        (json.dumps(_join_data(tmp_path, low_latency=True)), "no low-latency transport"),
        (json.dumps(_join_data(tmp_path, timing="physical")), "ideal timing only"),
        (json.dumps(_join_data(tmp_path, n_steps=-1)), "n_steps"),
        (json.dumps(_join_data(tmp_path, T_ns=0.1)), "T_ns: expected an integer"),
        (json.dumps(_join_data(tmp_path, credentials={"kind": "user_password", "user": "plant", "password": "x",
                                                      "secret_file": "/nonexistent"})), "password"),
        (json.dumps(_join_data(tmp_path, credentials={"kind": "mutual_tls", "ca": "/nonexistent/ca.pem",
                                                      "cert": "c", "key": "k"})), "credentials.ca"),
        (json.dumps(_join_data(tmp_path, scenario={**sc, "toml": sc["toml"] + "\n[plant.sensor]\nnoise = 0.1\n"})),
         "no sensor, actuator or disturbance model"),
        (json.dumps(_join_data(tmp_path, scenario={**sc, "toml": sc["toml"].replace('"lienard"', '"pendulum"')})),
         "lienard"),
        (json.dumps(_join_data(tmp_path, scenario={**sc, "toml": sc["toml"].replace("x0 = [0.1, 0.1]", "x0 = [0.1]")})),
         "x0"),
        (json.dumps(_join_data(tmp_path, scenario={**sc, "toml": sc["toml"] + "\n[run\n"})), "scenario TOML line"),
        ("[" * 100 + "]" * 100, "nested deeper"),
        ('{"a": "\\ud800"}', "surrogate"),
    ]
    for text, why in cases:
        rc, err = _device_with(device, f, text)
        assert rc == 2 and err.count("\n") == 1 and why in err and err.startswith("tb-pico-plant: join file"), \
            (why, rc, err)
    rc, err = _device_with(device, f, json.dumps(good), mode=0o644)
    assert rc == 2 and "readable by others" in err, err
    p = subprocess.run([device], capture_output=True, text=True, timeout=60,
                       env={k: v for k, v in os.environ.items() if k != join.ENV})
    assert p.returncode == 2 and "no TESTBED_JOIN" in p.stderr, p.stderr
    rc, err = _device_with(device, f, json.dumps(good))
    assert rc == 1 and "cannot open a Zenoh session to tcp/127.0.0.1:9" in err, err


def _live_with_device(device: str, run_id: str, tls: str, out: Path, *args: str, netns: bool = False):
    """``testbed run paper --topology router --tls-dir TLS --external plant --json --out OUT ARGS`` with the
    device started on the join file the run announces (``netns``: in the plant's namespace of the run's
    ``--netns``, with ``ip netns exec``): (rc, summary, stderr, facts: the join file, the device's exit code
    and stderr)."""
    p = subprocess.Popen(tb_cmd("run", "paper", "--topology", "router", "--tls-dir", tls, "--external", "plant",
                                "--json", "--out", str(out), "--run-id", run_id,
                                "--run-dir", os.path.join(LOGS, run_id), *(("--netns",) if netns else ()), *args),
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    err = JoinAnnounce(p, "plant")
    dev = None
    facts = {}
    try:
        path = err.wait(300)
        facts["join"] = json.loads(Path(path).read_text())
        cmd = [device]
        if netns:  # the run's namespaces are made after the join file is written: wait for the plant's
            from testbed.live.netns import _SAFE, PREFIX

            name = f"{PREFIX}{p.pid}-{_SAFE.sub('_', run_id)[:100]}-plant"
            end = time.monotonic() + 120
            while not os.path.exists(f"/run/netns/{name}") and time.monotonic() < end and p.poll() is None:
                time.sleep(0.1)
            cmd = ["ip", "netns", "exec", name, device]
        dev = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, join.ENV: path}, start_new_session=True)
        so, _ = p.communicate(timeout=300)
        dso, dse = dev.communicate(timeout=60)
        facts["device_rc"], facts["device_err"] = dev.returncode, dse
    finally:
        for proc in (p, dev):
            if proc is not None and proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    err.join()
    try:
        s = json.loads(so)
    except json.JSONDecodeError:
        pytest.fail(f"no JSON summary (exit {p.returncode}): {err.text()[-3000:]}")
    return p.returncode, s, err.text(), facts


def plant_model_error(rec: Path) -> tuple[float, int]:
    """max_k ||x_{k+1} - phi_T(x_k, u_k)||_inf over a recording (x_N from the final record), and its k."""
    import testbed
    from testbed.loop.flow import phi_T

    r = testbed.open(rec)
    a, sc, s = r.arrays, r.scenario, r.summary
    xs = np.vstack([np.asarray(a["x"]), np.asarray(s["x_final"])[None]])
    pred, status = phi_T(sc.make_plant(), xs[:-1], np.asarray(a["u"]), sc.T, sc.flow)
    assert not status.any()
    e = np.abs(xs[1:] - pred).max(axis=1)
    return float(e.max()), int(e.argmax())


@pytest.mark.process
def test_a_live_run_with_the_device_as_plant_over_mutual_tls(device, run_id, tmp_path):
    """The goal run of docs/devices.md: the C device is the plant of `testbed run paper --topology router
    --tls-dir DIR --external plant`; it joins over mutual TLS with the plant's certificate, the run converges,
    the recording is complete, the launcher's telemetry check of the device's NodeSummary holds, and the
    device's plant follows the model: max_k ||x_{k+1} - phi_T(x_k, u_k)||_inf <= 1e-9."""
    tls = str(tmp_path / "tls")
    assert subprocess.run(tb_cmd("secret", "--tls", tls), capture_output=True).returncode == 0
    res = {}

    def run(attempt):
        if attempt:
            reap(run_id + "r" * (attempt - 1))
        rec = tmp_path / f"run{attempt}.mcap"
        rc, s, err, facts = _live_with_device(device, run_id + "r" * attempt, tls, rec)
        res.update(facts=facts, rec=rec)
        return rc, s, err

    rc, s, err = rerun_while_stalled(run, "paper with the pico plant")
    facts, rec = res["facts"], res["rec"]
    assert rc == 0 and facts["device_rc"] == 0, (s["faults"], err[-2000:], facts.get("device_err"))
    assert "did not confirm" not in facts["device_err"], facts["device_err"]  # the collector held its summary
    d = facts["join"]
    assert d["credentials"]["kind"] == "mutual_tls" and d["mode"] == "client" and d["connect"][0].startswith("tls/")
    assert s["security"]["transport"] == "mutual tls" and s["external"] == "plant", s["security"]
    assert s["outcome"] == "done" and s["complete"] and s["samples"] == 300 and s["faults"] == [], s["faults"]
    assert s["converged"], s["final_norm"]
    ps = s["node_summaries"]["plant"]
    assert ps["implementation"].startswith("tb-pico-plant") and ps["telemetry_records"] == 301, ps
    assert ps["malformed"] == 0 and ps["late_u"] == 0 and ps["future_u"] == 0, ps
    assert s["recording_complete"] and rec.stat().st_size > 0
    p = subprocess.run([PY, "-m", "testbed.cli", "report", str(rec), "--json"], capture_output=True, text=True,
                       timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    rep = json.loads(p.stdout)
    assert rep["samples"] == 300 and rep["converged"] and rep["resimulation"]["checked"] == 300, rep["resimulation"]
    err_max, at = plant_model_error(rec)
    assert err_max <= 1e-9, (err_max, at)
    rs = rep["resimulation"]  # the external plant: the loop re-run on the device's reported states
    assert rs["plant"] == "recorded" and "external" in rs["plant_why"], rs
    assert rs["loop_identical"] is True and rs["loop_first_divergence"] is None and rs["reproduced"] is True, rs
    assert rs["plant_model_error"]["max"] <= 1e-9, rs["plant_model_error"]
    p = subprocess.run([PY, "-m", "testbed.cli", "report", str(rec)], capture_output=True, text=True, timeout=600)
    assert "reproduced: the loop is identical on the recorded plant" in p.stdout, p.stdout[-3000:]
    assert stat.S_IMODE(os.stat(tls).st_mode) == 0o700


@pytest.mark.process
def test_the_device_in_its_own_network_namespace(device, run_id, tmp_path):
    """``--netns``: the device runs in the plant's namespace of the run (``ip netns exec``), its only way to
    the router the emulated link (a veth pair and a bridge) to ``tls/10.77.0.1:7447``, over mutual TLS: the
    run completes without a fault, every node in a namespace of its own, and the plant follows the model."""
    if os.geteuid() != 0:
        require("netns", "network namespaces need root (CAP_SYS_ADMIN, CAP_NET_ADMIN)")
    if shutil.which("ip") is None:
        require("netns", "network namespaces need iproute2 ('ip' not found)")
    tls = str(tmp_path / "tls")
    assert subprocess.run(tb_cmd("secret", "--tls", tls), capture_output=True).returncode == 0
    res = {}

    def run(attempt):
        if attempt:
            reap(run_id + "r" * (attempt - 1))
        rec = tmp_path / f"ns{attempt}.mcap"
        rc, s, err, facts = _live_with_device(device, run_id + "r" * attempt, tls, rec, "--duration", "5",
                                              netns=True)
        res.update(facts=facts, rec=rec)
        return rc, s, err

    rc, s, err = rerun_while_stalled(run, "paper --netns with the pico plant")
    facts, rec = res["facts"], res["rec"]
    assert rc == 0 and facts["device_rc"] == 0, (s["faults"], err[-2000:], facts.get("device_err"))
    assert facts["join"]["connect"] == ["tls/10.77.0.1:7447"], facts["join"]["connect"]
    assert s["outcome"] == "done" and s["complete"] and s["samples"] == 50 and s["faults"] == [], s["faults"]
    assert s["security"]["transport"] == "mutual tls"
    ids = {r: s["node_summaries"][r]["netns"] for r in ("plant", "encoder", "attacker", "controller")}
    assert len(set(ids.values())) == 4 and os.readlink("/proc/self/ns/net") not in ids.values(), ids
    assert s["node_summaries"]["plant"]["implementation"].startswith("tb-pico-plant")
    err_max, at = plant_model_error(rec)
    assert err_max <= 1e-9, (err_max, at)


@pytest.mark.process
def test_the_device_passes_conformance_as_a_device(device, tmp_path):
    """`testbed conformance plant paper --topology router --tls-dir DIR --json -- DEVICE`: the device joins the
    router topology over mutual TLS and passes every required requirement, the adverse cases included (the u
    that acted at each targeted sample is the controller's); equals_simulator is reported but not required
    (its own integrator is not the testbed's bit for bit)."""
    tls = str(tmp_path / "tls")
    assert subprocess.run(tb_cmd("secret", "--tls", tls), capture_output=True).returncode == 0

    def run(attempt):
        p = subprocess.run(tb_cmd("conformance", "plant", "paper", "--topology", "router", "--tls-dir", tls, "--json",
                                  "--duration", "3", "--", device), capture_output=True, text=True, timeout=900)
        try:
            res = json.loads(p.stdout)
        except json.JSONDecodeError:
            pytest.fail(f"no JSON (exit {p.returncode}): {p.stdout[-1000:]} {p.stderr[-2000:]}")
        return p.returncode, res["runs"][-1]["report"] or {}, (res, p.stderr)

    rc, _, (res, err) = rerun_while_stalled(run, "conformance of the pico plant")
    verdict = {q["name"]: q for q in res["requirements"]}
    assert rc == 0 and res["passed"] is True, json.dumps(res["requirements"], indent=1)
    assert all(q["status"] == "pass" for q in res["requirements"] if q["required"]), verdict
    assert [q["name"] for q in res["requirements"] if not q["required"]] == ["equals_simulator"], verdict
    assert all(verdict[f"adverse_{c}"]["status"] == "pass" for c in ("duplicate", "late", "invalid")), verdict
    assert "is the controller's genuine u_k" in verdict["adverse_late"]["detail"], verdict["adverse_late"]
    assert "tolerance 1e-06" in verdict["plant_follows_model"]["detail"], verdict["plant_follows_model"]
    fed = res["runs"][-1]["fed"]
    assert fed["late"]["as"] == "controller" and fed["invalid"]["k"] >= 13, fed
