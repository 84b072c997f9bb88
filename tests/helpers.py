"""What the tests share: running the testbed command in a subprocess, the live runs and their
processes, the keys a live run must reproduce bit for bit, the paper's loop as scenario text, the
batch-versus-per-sample checks, and the verdicts of the live tests that ``test_failclosed.py`` also runs
on broken builds.  A test module never imports another (``tests/test_layers.py``): what two share is here.
(The fixtures are in ``conftest.py``; the rerun policy and the capability checks in ``failclosed.py``.)"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np
import pytest
from failclosed import fifo_permitted, rerun_flags, rerun_while_stalled, stalled

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


def run_cli(cmd: list[str], timeout: float = TIMEOUT, *, cwd=None, env: dict | None = None):
    """``cmd`` in its own process group (``env`` added to this process's environment): (exit code, stdout,
    stderr); past ``timeout`` the group is killed and the test fails."""
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                         cwd=cwd, env=None if env is None else {**os.environ, **env})
    try:
        out, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        out, err = p.communicate()
        pytest.fail(f"{' '.join(cmd)} did not finish in {timeout} s\n{err[-3000:]}")
    return p.returncode, out, err


def tb(*args, cwd=None, env: dict | None = None, timeout: float = TIMEOUT) -> tuple[int, str, str]:
    """``testbed ARGS`` in its own process, in ``cwd``: (exit code, stdout, stderr)."""
    return run_cli(tb_cmd(*map(str, args)), timeout, cwd=cwd, env=env)


def tb_run(*args, cwd=None, env: dict | None = None, timeout: float = TIMEOUT) -> subprocess.CompletedProcess:
    """:func:`tb` as a ``subprocess.CompletedProcess`` (``returncode``, ``stdout``, ``stderr``)."""
    rc, out, err = tb(*args, cwd=cwd, env=env, timeout=timeout)
    return subprocess.CompletedProcess(tb_cmd(*map(str, args)), rc, out, err)


#: node logs of the live runs (kept when a test failed)
LOGS = tempfile.mkdtemp(prefix="testbed-live-tests-")


class JoinAnnounce:
    """Reads a ``testbed run --external ROLE`` process's stderr in a thread: every line (``lines``), and the
    join file's path once the run announces it (``wait``)."""

    def __init__(self, p: subprocess.Popen, role: str):
        from testbed.live.external import ANNOUNCE

        self.lines: list[str] = []
        self._prefix = ANNOUNCE.format(role=role, path="")
        self._seen = threading.Event()
        self._thread = threading.Thread(target=self._read, args=(p.stderr,), daemon=True)
        self._thread.start()

    def _read(self, stream) -> None:
        for line in stream:
            self.lines.append(line)
            if line.startswith(self._prefix):
                self._seen.set()
        self._seen.set()

    def wait(self, timeout: float) -> str:
        """The join file's path (the test fails when the run ends or ``timeout`` passes before it says one)."""
        assert self._seen.wait(timeout), self.text()
        path = next((ln for ln in self.lines if ln.startswith(self._prefix)), None)
        assert path is not None, self.text()
        return path[len(self._prefix):].strip()

    def text(self) -> str:
        return "".join(self.lines)

    def join(self, timeout: float = 5.0) -> None:
        self._thread.join(timeout)


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


def live(run_id: str, scenario: str, *args, timeout: float = TIMEOUT, cwd=None, env: dict | None = None,
         logs=LOGS):
    """``testbed run SCENARIO --json`` (in ``cwd``, with ``env`` added, its node logs in ``logs/RUN_ID``)
    -> (exit code, summary, stderr)."""
    rc, out, err = run_cli(tb_cmd("run", str(scenario), "--json", "--run-id", run_id,
                                  "--run-dir", os.path.join(logs, run_id), *map(str, args)), timeout, cwd=cwd, env=env)
    try:
        summary = json.loads(out)
    except json.JSONDecodeError:
        pytest.fail(f"no JSON summary (exit {rc})\nstdout: {out[-2000:]}\nstderr: {err[-3000:]}")
    return rc, summary, err


def live_exact(run_id: str, scenario: str, *args, timeout: float = TIMEOUT, no_leftovers: bool = False,
               what: str | None = None, **where):
    """``live`` for the bit-exact tests, under the one rerun policy (``failclosed.rerun_while_stalled``):
    a run that reports a timing fault of its own is run again (a new run id; under SCHED_FIFO where
    permitted), up to ``STALL_RERUNS`` times; the last run is returned, for the test to compare whatever
    it reports.  A stalled run's processes still there 5 s on are killed; with ``no_leftovers`` they fail
    the test, and so do the processes of any attempt still there when the last one has ended.  ``where``:
    ``cwd``, ``env``, ``logs`` of :func:`live`."""
    def run(attempt):
        if attempt:
            left = reap(run_id + "r" * (attempt - 1))
            assert not (no_leftovers and left), f"processes of a stalled run left: {left}"
        again = (*args, "--force") if attempt and "--out" in args else args  # a stalled run's recording is replaced
        return live(run_id + "r" * attempt, scenario, *again, *rerun_flags(attempt, args), timeout=timeout, **where)

    try:
        return rerun_while_stalled(run, what or str(scenario))
    finally:
        if no_leftovers:
            assert not reap(run_id)  # every attempt's processes (their run ids begin with run_id)


def simulate(scenario: str, duration: float) -> dict:
    rc, out, err = run_cli(tb_cmd("simulate", scenario, "--duration", str(duration), "--json"))
    assert rc == 0, err
    return json.loads(out)


def resimulated(s: dict) -> dict:
    """``testbed resimulate --json`` of a live run's recording."""
    rc, out, err = run_cli(tb_cmd("resimulate", s["recording"]["path"], "--json"))
    assert rc in (0, 1), err
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
    "--plot": ["simulate", "analyze", "roa", "sweep", "report", "vulnerability", "compare", "noise", "campaign"],
    "--figsize": ["simulate", "analyze", "roa", "sweep", "report", "vulnerability", "compare", "noise", "campaign"],
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


def paper_loop_toml(x0=(0.1, 0.1), E0=0.1, mode: str | None = None) -> str:
    """The ``[plant]``, ``[quantizer]`` and ``[controller]`` tables of the paper's example (the Lienard plant
    a = 1/3, b = 0.02; T = 0.1, M = 6, L = 10; the paper's K) as scenario text, for a test's own scenario;
    ``x0``, ``E0`` and the quantizer's ``mode`` (none: the default) as given."""
    return (f'[plant]\nname = "lienard"\nparams = {{ a = 0.3333333333333333, b = 0.02 }}\nx0 = [{x0[0]}, {x0[1]}]\n\n'
            f"[quantizer]\nT = 0.1\nM = 6\nL = 10.0\nE0 = {E0}\n" + (f'mode = "{mode}"\n' if mode else "")
            + "\n[controller]\nK = [[-1.81, -1.90]]\n")


def sim_recording(tmp_path, name="paper", **over):
    """A simulation of scenario ``name`` (with ``over``) recorded to ``tmp_path/NAME.mcap``: (sc, res, path)."""
    from testbed import scenario
    from testbed.record import recording
    from testbed.sim.batch import simulate_scenario

    sc = scenario.with_overrides(scenario.load(name), over)
    res = simulate_scenario(sc)
    path = tmp_path / f"{name}.mcap"
    recording.record_simulation(path, sc, res, overrides=over)
    return sc, res, path


#: the per-sample arrays of a ``SimResult`` that the batch kernel and the per-sample loop must agree on
SIM_ARRAYS = ("t", "x", "u", "q", "q_enc", "xi_enc", "E_enc", "xi_dec", "E_dec", "theta", "symbols", "saturated",
              "x_final", "reason", "withheld", "delays", "u_missing", "loop_state")


def same_bits(a, b) -> bool:
    """Bit for bit (NaN where NaN, -0.0 where -0.0), dtype and shape too."""
    if a is None or b is None:
        return a is None and b is None
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype != b.dtype or a.shape != b.shape:
        return False
    return a.tobytes() == b.tobytes()


def both_simulators(sc, **kw):
    """``simulate_scenario`` of ``sc`` on the per-sample loop and on the batch kernel: (per, batch)."""
    from testbed.sim.trajectory import simulate_scenario

    per = simulate_scenario(sc, simulator="per-sample", **kw)
    bat = simulate_scenario(sc, simulator="batch", **kw)
    assert per.simulator == "per-sample" and bat.simulator == "batch"
    return per, bat


def assert_simulators_identical(sc, per, bat):
    """The two simulators' results of ``sc`` are one: every array bit for bit, the scalars, the gain, the
    counters and the JSON summary (but its ``simulator``)."""
    from testbed.sim.batch import summarize

    for name in SIM_ARRAYS:
        assert same_bits(getattr(per, name), getattr(bat, name)), name
    for name in ("T", "flow_status", "diverged_at", "plant_fault", "plant_fault_at", "method_fault",
                 "lockstep_breaks"):
        assert getattr(per, name) == getattr(bat, name), name
    assert np.array_equal(per.K, bat.K)
    assert per.counters == bat.counters
    sp, sb = summarize(sc, per), summarize(sc, bat)
    assert sp.pop("simulator") == "per-sample" and sb.pop("simulator") == "batch"
    assert json.dumps(sp) == json.dumps(sb)


# ------------------------------------------------------------------ live tests that test_failclosed.py also runs on a
# broken build (their verdicts here, so that one test module need not import another)
#: the outsider's run (test_security_process.py): long enough for at least 10 attempts after the start-up
OUTSIDER_S = 8


def assert_outsider_changed_nothing(run_id: str, topology: str, outsider_run, foreign=None):
    """The verdict of ``test_an_outsider_without_credentials_changes_nothing``: ``outsider_run(rid, peer,
    foreign, more)`` -> (exit code, summary, stderr) is one run under attack by an outsider without
    credentials (``foreign``: its TLS folder made by another authority, peer topology).  A run the machine
    stalled is run again (a new run id); what the outsider could cause is no stall, and the last run is
    compared whatever it reports: complete, authenticated, the simulator's bit for bit, nothing reached a node."""
    peer = topology == "peer"
    rc, s, err = rerun_while_stalled(lambda attempt: outsider_run(run_id + "r" * attempt, peer, foreign,
                                                                  rerun_flags(attempt)),
                                     f"outsider ({topology})", attacker=True)
    assert rc == 0, (s["faults"], err[-2000:])
    assert s["complete"] and s["outcome"] == "done" and not s["faults"]
    assert s["security"]["authenticated"] and s["security"]["topology"] == topology
    assert s["security"]["transport"] == ("mutual tls" if peer else "user/password")
    sim = simulate("paper", OUTSIDER_S)
    for key in BIT_EXACT_KEYS:
        assert s[key] == sim[key], mismatch(s, sim, key)
    assert s["recording"]["complete"]
    for ev in ("stop_rejected", "future_symbol", "future_actuation", "input_rejected", "input_clamped"):
        assert ev not in s["events"], s["events"]  # nothing even reached the nodes
    assert s["security"]["topology_auto"] == peer  # the peer run is the default's (--topology auto)


def assert_physical_timing_on_the_paper(run_id: str, topology: tuple):
    """``test_physical_timing_converges_on_the_paper_and_resimulates`` (test_live_process.py): the paper's
    scenario and attacks with u_k acting at a real instant: scheduled actuation, the delay-aware rule; it
    converges (the whole 30 s), equals the simulator bit for bit, and the recording re-simulates exactly.
    A u_k later than its instant is a stall (``failclosed.stalled``): such a run is run again, and the last
    run is compared whatever it reports."""
    # under SCHED_FIFO where permitted (as a physical-timing lab would run it): on a busy shared
    # machine the plain scheduler left u_k late for its instant in run after run
    rt = ("--realtime",) if fifo_permitted() else ()
    # deadline 0.9 T: u_k of a received sample scheduled at 0.4 d T = 36 ms (20 ms at the default
    # 0.5), lost at 72 ms; a busy CI machine still left u_k later than 20 ms now and then under FIFO
    dl = ("--deadline", "0.9")
    rc, s, err = live_exact(run_id, "paper", "--duration", "30", "--timing", "physical", *dl, *rt, *topology)
    assert rc == 0, (s["faults"], err[-2000:])
    assert s["timing_mode"] == "physical" and s["complete"] and s["rule"] == "delay-aware"
    assert s["samples"] == 300 and s["converged"] and s["final_norm"] < 1e-4, s["final_norm"]
    assert s["encoder_decoder_agree_where_known"] is True
    r = resimulated(s)
    assert r["reproduced"] and r["max_state_error"] <= 1e-9 and r["symbols_identical"], r
    # u_k acted exactly on schedule (received samples at 36 ms): the live run is the simulator's, bit for bit
    rc, out, err = run_cli(tb_cmd("simulate", "paper", "--timing", "physical", *dl, "--json"))
    sim = json.loads(out)
    for key in ("symbols", "theta", "E", "x"):
        assert s[key] == sim[key], mismatch(s, sim, key)
