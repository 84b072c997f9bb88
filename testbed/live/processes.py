"""The node processes of a live run: their start (exec'd or forked), their exits and deaths (a ``Fault``
each), a colocated role that died alone, and their stop (``Stop`` message, SIGINT, SIGKILL to each group)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from ..record.faults import Fault
from ..wire import messages as msg
from .faultlog import FaultLog
from .spawn import Forked, _forked_node, log_tail, popen_logged

if TYPE_CHECKING:
    import zenoh

    from .collect import Collector


class NodeProcesses:
    """The node processes ``processes`` (roles; ``colocated`` roles run inside ``process_of(role)``'s), each
    started by ``command(role)`` (its ``testbed node ...`` command line) with its log in ``run_dir``;
    ``fork``: ``--spawn fork`` (only roles without a ``--node-prefix``); ``external``: a role not started.
    Deaths go to ``faults``."""

    #: a colocated role's liveliness loss without a crash counts as its death only this long after:
    #: its host also closes it at the run's end, and that loss can arrive before the plant's Stop
    GUEST_GRACE_NS = 500_000_000

    def __init__(self, *, run_dir: Path, processes: tuple[str, ...], colocated: tuple[str, ...],
                 process_of: Callable[[str], str], node_prefix: dict[str, str], fork: bool, external: str | None,
                 command: Callable[[str], list[str]], faults: FaultLog):
        self.run_dir = run_dir
        self.processes = processes
        self.colocated = colocated
        self.process_of = process_of
        self.node_prefix = node_prefix
        self.fork_ok = fork
        self.external = external
        self.command = command
        self.faults = faults
        self.procs: dict[str, subprocess.Popen | Forked] = {}
        self.exits: dict[str, dict] = {}
        self.kill_sent: dict[str, int] = {}   # role -> monotonic ns of its --kill
        self.stopping = False

    def log(self, role: str) -> Path:
        return self.run_dir / f"{role}.log"

    def log_tail(self, role: str, lines: int = 6) -> str:
        return log_tail(self.log(role), lines)

    # ---- start
    def forks(self, role: str) -> bool:
        """Whether ``role`` is forked from the launcher (``--spawn fork``, and no ``--node-prefix`` for it).

        Only while the launcher has started no threads of a library (Zenoh's session, rerun's
        streams: a fork copies none of them, and a lock one of them held stays held in the child);
        ``run`` forks before it opens its session, and nothing imports rerun before that."""
        return self.fork_ok and role not in self.node_prefix

    def any_forked(self) -> bool:
        return any(self.forks(r) for r in self.processes)

    def spawn(self, *, forked: bool) -> None:
        """Start the node processes that are forked (before the launcher has any Zenoh thread) or exec'd."""
        for role in self.processes:
            if self.forks(role) == forked and role not in self.procs and role != self.external:
                self.procs[role] = self._fork(role) if forked else popen_logged(self.command(role), self.log(role))

    def _fork(self, role: str) -> Forked:
        import gc

        cmd = self.command(role)
        argv = cmd[cmd.index("testbed.cli") + 1:]
        gc.freeze()  # the launcher's objects: the child's collector never walks them (nor copies their pages)
        log_fd = os.open(self.log(role), os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            _forked_node(argv, log_fd)  # never returns
        os.close(log_fd)
        return Forked(pid)

    # ---- signals and stop
    def signal_group(self, role: str, sig: int) -> None:
        p = self.procs[role]
        if p.poll() is None:
            try:
                os.killpg(p.pid, sig)
            except ProcessLookupError:
                pass

    def kill_all(self) -> None:
        for r in self.procs:
            self.signal_group(r, signal.SIGKILL)

    def kill(self, role: str) -> None:
        """``--kill ROLE@S``: SIGKILL to its process group; a colocated role's host kills it alone (SIGUSR2)."""
        self.kill_sent[role] = time.monotonic_ns()
        if role in self.colocated:
            self.signal_group(self.process_of(role), signal.SIGUSR2)
        else:
            self.signal_group(role, signal.SIGKILL)

    def stop_all(self, session: zenoh.Session, stop_key: str, reason: str, grace: float = 3.0) -> None:
        """``Stop`` on ``stop_key``, then SIGINT to each live group after ``grace`` s, then SIGKILL."""
        self.stopping = True
        alive = [r for r, p in self.procs.items() if p.poll() is None]
        if not alive:
            return
        try:
            session.put(stop_key, msg.Stop(reason=reason, origin="launcher").encode())
        except Exception:  # noqa: BLE001 - the stop is best effort; the processes are stopped below
            pass
        end = time.monotonic() + grace
        while time.monotonic() < end and any(self.procs[r].poll() is None for r in alive):
            time.sleep(0.02)
        for r in alive:
            self.signal_group(r, signal.SIGINT)
        end = time.monotonic() + grace
        while time.monotonic() < end and any(self.procs[r].poll() is None for r in alive):
            time.sleep(0.02)
        for r in alive:
            self.signal_group(r, signal.SIGKILL)
        for r in alive:
            try:
                self.procs[r].wait(5)
            except subprocess.TimeoutExpired:
                pass

    # ---- exits
    def all_exited(self) -> bool:
        return all(r in self.exits for r in self.procs)

    def plant_ok(self, col: Collector) -> bool:
        return col.plant_done() or self.exits.get("plant", {}).get("exit_code") == 0

    def poll(self, col: Collector, t0_mono: int | None, *, interrupted: bool) -> None:
        """Record each process that exited since the last poll (``interrupted``: the run got a signal)."""
        for role, p in self.procs.items():
            rc = p.poll()
            if rc is not None and role not in self.exits:
                self.record_exit(role, rc, col, t0_mono, interrupted=interrupted)

    def record_exit(self, role: str, rc: int, col: Collector, t0_mono: int | None, *, interrupted: bool) -> None:
        now = time.monotonic_ns()
        info = {"exit_code": rc, "signal": signal.Signals(-rc).name if rc < 0 else None,
                "at_sample": col.last_k(role),
                "t_s": None if t0_mono is None else round((now - t0_mono) / 1e9, 4)}
        self.exits[role] = info
        plant_done = col.plant_done()
        injected = role in self.kill_sent
        asked = interrupted or self.stopping or plant_done
        abnormal = rc != 0 and not (asked and rc in (130, 143, -2, -15))
        if abnormal:
            why = f"killed by {info['signal']}" if rc < 0 else f"exit code {rc}"
            tail = self.log_tail(role)
            last = tail.splitlines()[-1] if tail else ""
            self.faults.append(Fault(role=role, kind="killed" if rc < 0 else "crashed", detail=why,
                                     last_log_line=last, exit_code=rc, signal=info["signal"],
                                     sample=info["at_sample"], time=info["t_s"], injected=injected))
            print(f"testbed run: node {role} died ({why}) at sample {info['at_sample']}"
                  + (f": {last}" if last else ""), file=sys.stderr)

    def check_guest(self, role: str, col: Collector, t0_mono: int | None, *, final: bool = False) -> None:
        """A colocated role whose liveliness went while its host runs on: it died alone (killed or crashed).

        At the run's end its host closes it as well, after its summary and the plant's Stop, which
        may still be on their way when the liveliness loss arrives: a loss without a crash event
        counts once ``GUEST_GRACE_NS`` has passed with neither in, or (``final``, after the
        summaries were waited for) when the host exited cleanly and published its summary but the
        role's, which the host publishes first, never came.
        """
        if role in self.exits:
            return
        host = self.process_of(role)
        lost = col.lost_at(role)
        if lost is None or t0_mono is None:
            return
        crash = col.event_of(role, "crash")
        if final:
            if self.exits.get(host, {}).get("exit_code") != 0:
                return  # the host itself died or was stopped: its fault says it
            got = col.snapshot_summaries()
            if crash is None and (role in got or host not in got):
                return  # closed by its host at the end (its account is published before the host's)
        else:
            if host in self.exits or col.plant_done():
                return
            if crash is None and (time.monotonic_ns() - lost < self.GUEST_GRACE_NS
                                  or role in col.snapshot_summaries()):
                return
        injected = role in self.kill_sent
        why = (f"exception: {crash.detail}" if crash is not None else
               f"killed (colocated in the {host}: the {role} alone stopped)")
        info = {"exit_code": None, "signal": None if crash is not None else "SIGKILL",
                "at_sample": col.last_k(role), "t_s": round((lost - t0_mono) / 1e9, 4), "colocated_in": host}
        self.exits[role] = info
        self.faults.append(Fault(role=role, kind="crashed" if crash is not None else "killed", detail=why,
                                 last_log_line=(self.log_tail(host).splitlines() or [""])[-1],
                                 exit_code=None, signal=info["signal"], sample=info["at_sample"],
                                 time=info["t_s"], injected=injected, colocated_in=host))
        print(f"testbed run: node {role} died ({why}) at sample {info['at_sample']}", file=sys.stderr)

    def check_guests(self, col: Collector, t0_mono: int | None, *, final: bool = False) -> None:
        for guest in self.colocated:
            self.check_guest(guest, col, t0_mono, final=final)

    def summaries_due(self, col: Collector) -> set[str]:
        """The roles that owe the launcher a summary: none before the run's Start (a node publishes it after the
        run's loop); then each node process that exited cleanly, and the colocated roles it hosted that did not
        die alone."""
        if col.start is None:
            return set()
        due = {r for r, e in self.exits.items() if e.get("exit_code") == 0 and r in self.procs}
        return due | {g for g in self.colocated if self.process_of(g) in due and g not in self.exits}

    def wait_summaries(self, col: Collector, timeout: float = 1.0, telemetry_timeout: float = 3.0) -> None:
        """Until every summary due is in (a node publishes it before it exits), then until the telemetry each
        summary counts has arrived (at most ``telemetry_timeout`` more: what is still missing then is the
        telemetry check's to report)."""
        want = self.summaries_due(col)
        end = time.monotonic() + timeout
        while time.monotonic() < end and not want <= set(col.snapshot_summaries()):
            time.sleep(0.01)
        end = time.monotonic() + telemetry_timeout
        while time.monotonic() < end and col.telemetry_behind():
            time.sleep(0.02)

    def check_summaries(self, col: Collector) -> None:
        """A summary due (``summaries_due``) that is not in is the fault ``summary_missing``: the node's telemetry
        cannot be checked."""
        for r in sorted(self.summaries_due(col) - set(col.snapshot_summaries())):
            self.faults.append(Fault(role=r, kind="summary_missing",
                                     detail="it exited cleanly, but its summary (its own account of its telemetry) "
                                            "never arrived: its telemetry is unchecked"))
            print(f"testbed run: node {r}: exited cleanly, but its summary never arrived", file=sys.stderr)

    def nodes(self, roles: tuple[str, ...]) -> dict:
        """The summary's ``nodes``: each role's exit and log (a colocated role: its host's, unless it died alone)."""
        nodes = {r: dict(self.exits.get(r, {}), log=str(self.log(r))) for r in self.processes}
        for r in self.colocated:
            host = self.process_of(r)
            nodes[r] = dict(self.exits.get(r) or self.exits.get(host, {}), colocated_in=host, log=str(self.log(host)))
        return {r: nodes[r] for r in roles}


__all__ = ["NodeProcesses"]
