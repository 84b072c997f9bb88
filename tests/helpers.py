"""What the tests share: running the testbed command in a subprocess, the live runs and their
processes, the keys a live run must reproduce bit for bit, and checks used by more than one module.
(The fixtures are in ``conftest.py``; the rerun policy and the capability checks in ``failclosed.py``.)"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np
import pytest
from failclosed import rerun_flags, rerun_while_stalled, stalled

from testbed.wire import messages as msg

PY = sys.executable
TIMEOUT = float(os.environ.get("TESTBED_PROCESS_TIMEOUT", "300"))  # JIT warm-up of 4 nodes on 2 cores


def tb_cmd(*args) -> list[str]:
    return [PY, "-m", "testbed.cli", *args]


def procs_with(token: str) -> list[int]:
    """Pids whose command line contains ``token`` (this process excluded)."""
    out = []
    for d in os.listdir("/proc"):
        if not d.isdigit() or int(d) == os.getpid():
            continue
        try:
            with open(f"/proc/{d}/cmdline", "rb") as f:
                cmd = f.read().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if token in cmd:
            out.append(int(d))
    return out


def cmdlines(pids: list[int]) -> list[str]:
    """``pid: command line`` of each pid, for assertion messages."""
    out = []
    for pid in pids:
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                cmd = f.read().replace(b"\0", b" ").decode(errors="replace")
            out.append(f"{pid}: {cmd[:200]}")
        except OSError:
            out.append(f"{pid}: (gone)")
    return out


def reap(token: str, wait: float = 5.0) -> list[int]:
    """Wait for processes of a run to go, SIGKILL whatever is left; returns the leftovers."""
    end = time.monotonic() + wait
    left = procs_with(token)
    while left and time.monotonic() < end:
        time.sleep(0.1)
        left = procs_with(token)
    for pid in left:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    return left


def run_cli(cmd: list[str], timeout: float = TIMEOUT):
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        out, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        out, err = p.communicate()
        pytest.fail(f"{' '.join(cmd)} did not finish in {timeout} s\n{err[-3000:]}")
    return p.returncode, out, err


#: node logs of the live runs (kept when a test failed)
LOGS = tempfile.mkdtemp(prefix="testbed-live-tests-")


def mismatch(s: dict, sim: dict, key: str) -> str:
    """Why a live run differs from the simulator: the first sample where ``key`` differs and the run's
    own account around it (for a failure that reports no stall: what happened there)."""
    a, b = s.get(key), sim.get(key)
    if not isinstance(a, list) or not isinstance(b, list):
        return f"{key}: {a!r} != {b!r}"
    k = next((i for i, (x, y) in enumerate(zip(a, b)) if x != y), min(len(a), len(b)))
    lo, hi = max(0, k - 2), k + 2
    near = {c: (s.get(c) or [])[lo:hi] for c in ("theta", "symbols", "E", "u", "x") if isinstance(s.get(c), list)}
    simnear = {c: (sim.get(c) or [])[lo:hi] for c in ("theta", "symbols", "E", "u", "x") if isinstance(sim.get(c), list)}
    tm = s.get("timing", {})
    return (f"{key} first differs at sample {k}; the run's own stall report: {stalled(s)}"
            f" (live {a[k] if k < len(a) else None!r}, simulator "
            f"{b[k] if k < len(b) else None!r}); live {lo}..{hi - 1}: {near}; simulator: {simnear}; "
            f"events {s.get('events')}; loss_reasons {s.get('loss_reasons')}; withheld_at {s.get('withheld_at')}; "
            f"stages {tm.get('stages_us')}; jitter {tm.get('sampling_jitter_us')}; "
            f"encoder {s.get('node_summaries', {}).get('encoder')}")


def live(run_id: str, scenario: str, *args, timeout: float = TIMEOUT):
    """``testbed run SCENARIO --json`` -> (exit code, summary, stderr)."""
    rc, out, err = run_cli(tb_cmd("run", scenario, "--json", "--run-id", run_id,
                                  "--run-dir", os.path.join(LOGS, run_id), *args), timeout)
    try:
        summary = json.loads(out)
    except json.JSONDecodeError:
        pytest.fail(f"no JSON summary (exit {rc})\nstdout: {out[-2000:]}\nstderr: {err[-3000:]}")
    return rc, summary, err


def live_exact(run_id: str, scenario: str, *args, timeout: float = TIMEOUT):
    """``live`` for the bit-exact tests, under the one rerun policy (``failclosed.rerun_while_stalled``):
    a run that reports a timing fault of its own is run again (a new run id; under SCHED_FIFO where
    permitted), up to ``STALL_RERUNS`` times; the last run is returned, for the test to compare whatever
    it reports."""
    def run(attempt):
        if attempt:
            reap(run_id + "r" * (attempt - 1))
        again = (*args, "--force") if attempt and "--out" in args else args  # a stalled run's recording is replaced
        return live(run_id + "r" * attempt, scenario, *again, *rerun_flags(attempt, args), timeout=timeout)

    return rerun_while_stalled(run, scenario)


def simulate(scenario: str, duration: float) -> dict:
    rc, out, err = run_cli(tb_cmd("simulate", scenario, "--duration", str(duration), "--json"))
    assert rc == 0, err
    return json.loads(out)


BIT_EXACT_KEYS = ("symbols", "theta", "E", "E_dec", "xi", "q", "x", "u", "saturated_at", "x_final")

#: the two topologies every key live test runs in, in the default network topology (``--topology auto``:
#: on one host the peer topology, direct links with mutual TLS): four node processes, and the encoder
#: inside the plant's process (``--colocate encoder``, three network hops per sample)
TOPOLOGIES = [pytest.param((), id="4proc"), pytest.param(("--colocate", "encoder"), id="colocated")]
#: ... and the router topology (every message through the launcher's router, user/password), for a few of them
WITH_ROUTER = TOPOLOGIES + [pytest.param(("--topology", "router"), id="router"),
                            pytest.param(("--topology", "router", "--colocate", "encoder"), id="router-colocated")]


def transport_of(flags) -> str:
    """The ``security.transport`` of an authenticated run on one host with these flags."""
    return "user/password" if "router" in flags else "mutual tls"


#: the shared options and the commands that must have them (docs/cli.md)
SHARED = {
    "--json": ["scenarios", "simulate", "run", "report", "replay", "analyze", "roa", "sweep", "resimulate",
               "plants", "check-plant", "worst-attack", "vulnerability", "secret", "compare", "noise"],
    "--out": ["run", "simulate", "record"],
    "--rrd": ["run", "simulate", "replay"],
    "--plot": ["simulate", "analyze", "roa", "sweep", "report", "vulnerability", "compare", "noise"],
    "--figsize": ["simulate", "analyze", "roa", "sweep", "report", "vulnerability", "compare", "noise"],
    "--no-roa": ["run", "simulate", "replay"],
    "--no-progress": ["analyze", "roa", "sweep", "worst-attack", "vulnerability", "noise"],
    "--workers": ["analyze", "roa", "sweep", "worst-attack", "vulnerability"],
}


def assert_columns_equal_reference(cols, rec):
    """Every field of every telemetry dataclass the reference reader decoded equals the column's value."""
    names = {"plant": msg.PlantTelemetry, "encoder": msg.EncoderTelemetry, "controller": msg.ControllerTelemetry,
             "attacker": msg.AttackerTelemetry}
    for role, cls in names.items():
        ref = rec.telemetry[role]
        has = cols.has(role)
        assert sorted(ref) == np.flatnonzero(has).tolist(), role
        for f in dataclasses.fields(cls):
            if f.name == "k":
                continue
            col = cols.get(role, f.name)
            for k, t in ref.items():
                want = getattr(t, f.name)
                if role == "encoder" and t.silent and f.name in ("xi", "q", "E", "symbol"):
                    continue  # not sent; the columns hold NaN / -1 there
                if f.name == "x_meas" and want == ():  # no sensor model: not sent; the column holds NaN
                    assert np.isnan(col[k]).all(), (role, f.name, k)
                elif isinstance(want, tuple):
                    assert np.array_equal(col[k], np.array(want)), (role, f.name, k)
                else:
                    assert col[k] == want, (role, f.name, k)
    if rec.plant_final is not None:
        assert cols.final["k"] == rec.plant_final.k and np.array_equal(cols.final["x"], rec.plant_final.x)
    assert len(cols.events) == len(rec.events) and len(cols.status) == len(rec.status)
    assert dict(cols.counts) == dict(rec.counts)


def sim_recording(tmp_path, name="paper", **over):
    """A simulation of scenario ``name`` (with ``over``) recorded to ``tmp_path/NAME.mcap``: (sc, res, path)."""
    from testbed import scenario
    from testbed.record import recording
    from testbed.simulate import simulate_scenario

    sc = scenario.with_overrides(scenario.load(name), over)
    res = simulate_scenario(sc)
    path = tmp_path / f"{name}.mcap"
    recording.record_simulation(path, sc, res, overrides=over)
    return sc, res, path
