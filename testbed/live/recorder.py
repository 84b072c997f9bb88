"""The launcher's side of the recorder process: its command line, its start, its errors, its stop; and
the run's exit code.

A recorder that cannot write (a full disk, an I/O error, its file removed) says so and stops writing.
The loop does not depend on the disk: by default (``--on-record-error continue``) the run goes on
unrecorded and its summary says the recording is incomplete; ``stop`` ends the run instead.  The
exit code of ``testbed run`` then says so (``RECORDING_INCOMPLETE``), unless something worse happened.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

from ..errors import EXIT_RECORDING_INCOMPLETE
from ..nodes.options import RECORD_FAILED, RecorderConfig
from ..wire import transport

#: ``testbed run``'s exit code when the run itself was clean but its recording is incomplete
RECORDING_INCOMPLETE = EXIT_RECORDING_INCOMPLETE


def add_record_error_argument(g) -> None:
    g.add_argument("--on-record-error", choices=["continue", "stop"], default="continue",
                   help="when the recorder cannot write (disk full, I/O error, file removed): go on unrecorded "
                        "(default) or stop the run; either way the summary's recording_complete is false and "
                        f"the exit code is {RECORDING_INCOMPLETE} unless a node failed")


def recorder_fault(rc: int, info: dict, log_tail: str, injected: bool) -> tuple[dict, str]:
    """The fault entry of a recorder that exited during the run, and the launcher's line about it."""
    lines = log_tail.splitlines() or [""]
    last_line = lines[-1]
    if rc == RECORD_FAILED:
        last_line = next((x for x in reversed(lines) if "cannot write" in x), last_line)
        why = last_line.removeprefix("testbed record: ").split("; the recording")[0] or "it could not write its file"
        f = {"node": transport.RECORDER, "kind": "record_error", "why": why, "t_s": info["t_s"],
             "injected": False, "last_log_line": last_line}
        return f, f"testbed run: the recording failed ({why})"
    why = f"killed by {info['signal']}" if rc < 0 else f"exit code {rc}"
    f = {"node": transport.RECORDER, "kind": "killed" if rc < 0 else "crashed", "why": why, "t_s": info["t_s"],
         "injected": injected, "last_log_line": last_line}
    return f, f"testbed run: the recorder died ({why})"


def exit_code(sig: int | None, faults: list, summary: dict, ridden: tuple = ()) -> int:
    """128 + signal when interrupted; 1 when a node failed or the run did not complete; 3 when only the
    recording is incomplete; 0 otherwise (a stall is no failure: it shows in ``timing_degraded``; nor are
    the fault kinds in ``ridden``, e.g. a ``--cut`` link the run rode through)."""
    if sig is not None:
        return 128 + sig
    if any(f["kind"] != "stalled" and f["kind"] not in ridden and f.get("node") != transport.RECORDER for f in faults) \
            or not summary.get("complete"):
        return 1
    if summary.get("recording_complete") is False:
        return RECORDING_INCOMPLETE
    return 0


#: how long the launcher waits for the recorder after its SIGINT: more than the recorder's own drain time
#: (``testbed.nodes.recorder.RECORDER_STOP_GRACE_S``, 60 s), which then ends the file itself
STOP_WAIT_S = 65.0


class RecorderControl:
    """The launcher's recorder process (a mixin of ``Launcher``: it uses the launcher's configuration, keys,
    credentials, faults and run folder)."""

    def recorder_config(self) -> RecorderConfig:
        """What the recorder process runs: the run's options, its session, the file."""
        c = self.cfg
        return RecorderConfig(scenario=self.scenario_ref, opts=self.opts, session=self.session_options(transport.RECORDER),
                              out=str(self.record_path), loop=c.record_loop, launched=True, parent_pid=os.getpid(),
                              scenario_ref=c.scenario, force=c.force, cpus=self.cpus.get(transport.RECORDER),
                              verbose=c.verbose)

    def recorder_command(self) -> list[str]:
        return [sys.executable, "-P", "-m", "testbed.cli", *self.recorder_config().argv()]

    def recorder_started(self, session, col) -> bool:
        """During start-up: declare the collector ready once the recorder is (False: it died first)."""
        if self._collector_ready or self.recorder is None:
            return True
        if transport.RECORDER in col.ready_nodes():
            self.declare_collector_ready(session)
            return True
        rc = self.recorder.poll()
        if rc is None:
            return True
        self.faults.append({"node": transport.RECORDER, "kind": "startup_failed", "why": f"exit code {rc}",
                            "last_log_line": (self.log_tail(transport.RECORDER).splitlines() or [""])[-1]})
        return False

    def check_recorder(self, col, t0_mono: int | None) -> None:
        if self.recorder is None or self.recorder_exit is not None:
            return
        rc = self.recorder.poll()
        if rc is None:
            return
        now = time.monotonic_ns()
        self.recorder_exit = {"exit_code": rc, "signal": signal.Signals(-rc).name if rc < 0 else None,
                              "t_s": None if t0_mono is None else round((now - t0_mono) / 1e9, 4)}
        if not self.stopping or rc == RECORD_FAILED:
            f, line = recorder_fault(rc, self.recorder_exit, self.log_tail(transport.RECORDER),
                                     transport.RECORDER in self.kill_sent)
            self.faults.append(f)
            stop = f["kind"] == "record_error" and self.cfg.on_record_error == "stop"
            go = "as the run ended" if self.stopping else ("the run stops (--on-record-error stop)" if stop else
                                                           "the run goes on unrecorded")
            print(f"{line}; {go}, the file keeps what was flushed: {self.record_path}", file=sys.stderr)

    def recording_info(self) -> dict | None:
        if self.record_path is None:
            return None
        ok = self.recorder_exit is not None and self.recorder_exit["exit_code"] == 0
        err = next((f["why"] for f in self.faults if f.get("kind") == "record_error"), None)
        return {"path": str(self.record_path), "complete": ok, "error": err, "recorder_exit": self.recorder_exit,
                "log": str(self.run_dir / f"{transport.RECORDER}.log")}

    def stop_recorder(self, grace: float | None = None) -> None:
        """SIGINT the recorder and wait for it to drain its queue and close the file (``STOP_WAIT_S``:
        longer than the recorder gives itself, so a recorder behind on a long run is never killed mid-file)."""
        grace = STOP_WAIT_S if grace is None else grace
        p = self.recorder
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


__all__ = ["RecorderControl", "RECORD_FAILED", "RECORDING_INCOMPLETE", "add_record_error_argument", "recorder_fault", "exit_code"]
