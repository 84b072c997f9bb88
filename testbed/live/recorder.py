"""The launcher's side of the recorder process: its command line, its start, its errors, its stop; and
the run's exit code.

A recorder that cannot write (a full disk, an I/O error, its file removed) says so and stops writing.
The loop does not depend on the disk: by default (``--on-record-error continue``) the run goes on
unrecorded and its summary says the recording is incomplete; ``stop`` ends the run instead.  The
exit code of ``testbed run`` then says so (``RECORDING_INCOMPLETE``), unless something worse happened.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

from ..common.errors import EXIT_RECORDING_INCOMPLETE
from ..nodes.options import RECORD_FAILED, RecorderConfig
from ..record.faults import Fault
from ..wire import transport
from .faultlog import FaultLog
from .spawn import log_tail, popen_logged

if TYPE_CHECKING:
    from .collect import Collector

#: ``testbed run``'s exit code when the run itself was clean but its recording is incomplete
RECORDING_INCOMPLETE = EXIT_RECORDING_INCOMPLETE


def add_record_error_argument(g: argparse._ActionsContainer) -> None:
    g.add_argument("--on-record-error", choices=["continue", "stop"], default="continue",
                   help="when the recorder cannot write (disk full, I/O error, file removed): go on unrecorded "
                        "(default) or stop the run; either way the summary's recording_complete is false and "
                        f"the exit code is {RECORDING_INCOMPLETE} unless a node failed")


def recorder_fault(rc: int, info: dict, log_tail: str, injected: bool) -> tuple[Fault, str]:
    """The fault of a recorder that exited during the run, and the launcher's line about it."""
    lines = log_tail.splitlines() or [""]
    last_line = lines[-1]
    if rc == RECORD_FAILED:
        last_line = next((x for x in reversed(lines) if "cannot write" in x), last_line)
        why = last_line.removeprefix("testbed record: ").split("; the recording")[0] or "it could not write its file"
        f = Fault(role=transport.RECORDER, kind="record_error", detail=why, time=info["t_s"], injected=False,
                  last_log_line=last_line)
        return f, f"testbed run: the recording failed ({why})"
    why = f"killed by {info['signal']}" if rc < 0 else f"exit code {rc}"
    f = Fault(role=transport.RECORDER, kind="killed" if rc < 0 else "crashed", detail=why, time=info["t_s"],
              injected=injected, last_log_line=last_line)
    return f, f"testbed run: the recorder died ({why})"


def exit_code(sig: int | None, faults: Iterable[Fault], summary: dict, ridden: tuple = ()) -> int:
    """128 + signal when interrupted; 1 when a node failed or the run did not complete; 3 when only the
    recording is incomplete; 0 otherwise (a stall is no failure: it shows in ``timing_degraded``; nor are
    the fault kinds in ``ridden``, e.g. a ``--cut`` link the run rode through)."""
    if sig is not None:
        return 128 + sig
    if any(f.kind != "stalled" and f.kind not in ridden and f.role != transport.RECORDER for f in faults) \
            or not summary.get("complete"):
        return 1
    if summary.get("recording_complete") is False:
        return RECORDING_INCOMPLETE
    return 0


#: how long the launcher waits for the recorder after its SIGINT: more than the recorder's own drain time
#: (``testbed.nodes.recorder.RECORDER_STOP_GRACE_S``, 60 s), which then ends the file itself
STOP_WAIT_S = 65.0


def recorder_command(config: RecorderConfig) -> list[str]:
    """The recorder's command line: ``testbed record`` with its ``RecorderConfig`` as flags."""
    return [sys.executable, "-P", "-m", "testbed.cli", *config.argv()]


class RecorderProcess:
    """The run's recorder process (``testbed record``): its start, its errors (a ``Fault`` each, in
    ``faults``), its stop and what the summary says of the recording."""

    def __init__(self, path: Path, run_dir: Path, faults: FaultLog, on_record_error: str = "continue"):
        self.path = path
        self.log = run_dir / f"{transport.RECORDER}.log"
        self.faults = faults
        self.on_record_error = on_record_error
        self.proc: subprocess.Popen | None = None
        self.exit: dict | None = None  # its exit code, signal and time (``recorder_exit``)

    def start(self, config: RecorderConfig) -> None:
        self.proc = popen_logged(recorder_command(config), self.log)

    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def kill(self) -> None:
        """``--kill recorder@S``: SIGKILL to its process group."""
        if self.proc is not None and self.proc.poll() is None:  # running()
            os.killpg(self.proc.pid, signal.SIGKILL)

    def startup(self, col: Collector) -> str:
        """During start-up: ``ready`` (in the collector's ready nodes), ``waiting``, or ``failed`` (it died
        first: a fault ``startup_failed``)."""
        if transport.RECORDER in col.ready_nodes():
            return "ready"
        assert self.proc is not None  # started
        rc = self.proc.poll()
        if rc is None:
            return "waiting"
        self.faults.append(Fault(role=transport.RECORDER, kind="startup_failed", detail=f"exit code {rc}",
                                 last_log_line=(log_tail(self.log).splitlines() or [""])[-1]))
        return "failed"

    def check(self, t0_mono: int | None, *, stopping: bool, injected: bool) -> None:
        """Once it exited: its exit, and a fault unless the launcher stopped it (a write error always is one)."""
        if self.proc is None or self.exit is not None:
            return
        rc = self.proc.poll()
        if rc is None:
            return
        now = time.monotonic_ns()
        self.exit = {"exit_code": rc, "signal": signal.Signals(-rc).name if rc < 0 else None,
                     "t_s": None if t0_mono is None else round((now - t0_mono) / 1e9, 4)}
        if not stopping or rc == RECORD_FAILED:
            f, line = recorder_fault(rc, self.exit, log_tail(self.log), injected)
            self.faults.append(f)
            stop = f.kind == "record_error" and self.on_record_error == "stop"
            go = "as the run ended" if stopping else ("the run stops (--on-record-error stop)" if stop else
                                                      "the run goes on unrecorded")
            print(f"{line}; {go}, the file keeps what was flushed: {self.path}", file=sys.stderr)

    def info(self) -> dict:
        """The summary's ``recording``."""
        ok = self.exit is not None and self.exit["exit_code"] == 0
        err = next((f.detail for f in self.faults if f.kind == "record_error"), None)
        return {"path": str(self.path), "complete": ok, "error": err, "recorder_exit": self.exit,
                "log": str(self.log)}

    def stop(self, grace: float | None = None) -> None:
        """SIGINT the recorder and wait for it to drain its queue and close the file (``STOP_WAIT_S``:
        longer than the recorder gives itself, so a recorder behind on a long run is never killed mid-file)."""
        grace = STOP_WAIT_S if grace is None else grace
        p = self.proc
        if p is None or p.poll() is not None:
            return
        try:
            os.killpg(p.pid, signal.SIGINT)
        except ProcessLookupError:
            return
        try:
            p.wait(grace)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(5)


__all__ = ["RecorderProcess", "recorder_command", "RECORD_FAILED", "RECORDING_INCOMPLETE", "add_record_error_argument",
           "recorder_fault", "exit_code"]
