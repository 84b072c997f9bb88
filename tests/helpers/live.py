"""Live runs in a test: ``testbed run --json`` in its own process (``live``), under the one rerun policy
(``live_exact``), the keys it must reproduce bit for bit and the topologies it runs in, the simulator's
reference (``simulate``, ``resimulated``), the account of where a run left the simulator (``mismatch``), and
the join file a ``--external`` run announces (``JoinAnnounce``)."""

from __future__ import annotations

import json
import os
import subprocess
import tempfile
import threading

import pytest
from failclosed import rerun_flags, rerun_while_stalled, stalled

from helpers.cli import TIMEOUT, run_cli, tb_cmd
from helpers.procs import reap

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
