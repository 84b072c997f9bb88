"""A recorder that cannot write (a full disk, an I/O error, its file removed), and the run's exit code.

The loop does not depend on the disk: by default (``--on-record-error continue``) the run goes on
unrecorded and its summary says the recording is incomplete; ``stop`` ends the run instead.  The
exit code of ``testbed run`` then says so (``RECORDING_INCOMPLETE``), unless something worse happened.
"""

from __future__ import annotations

from ..nodes.recorder import RECORD_FAILED
from ..wire import transport

#: ``testbed run``'s exit code when the run itself was clean but its recording is incomplete
RECORDING_INCOMPLETE = 3


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


__all__ = ["RECORD_FAILED", "RECORDING_INCOMPLETE", "add_record_error_argument", "recorder_fault", "exit_code"]
