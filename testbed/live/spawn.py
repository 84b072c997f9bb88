"""A node forked from the launcher (``--spawn fork``): the child becomes ``testbed node ...`` without
exec, the parent watches it like a ``subprocess.Popen``."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path


class Forked:
    """A node forked from the launcher (``--spawn fork``): the part of ``subprocess.Popen`` the launcher uses."""

    def __init__(self, pid: int):
        self.pid = pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            try:
                pid, status = os.waitpid(self.pid, os.WNOHANG)
            except ChildProcessError:  # reaped elsewhere: its status is gone
                self.returncode = 1
                return self.returncode
            if pid:
                self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        end = None if timeout is None else time.monotonic() + timeout
        while (rc := self.poll()) is None:
            if end is not None and timeout is not None and time.monotonic() > end:
                raise subprocess.TimeoutExpired(f"pid {self.pid}", timeout)
            time.sleep(0.005)
        return rc


def popen_logged(cmd: list[str], log: Path) -> subprocess.Popen:
    """A child in its own session and process group, its output in ``log``."""
    env = dict(os.environ)
    env.setdefault("PYTHONUNBUFFERED", "1")
    with open(log, "wb") as out:
        return subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True, env=env)


def log_tail(log: Path, lines: int = 6) -> str:
    """The last ``lines`` lines of a process's log ("" if it cannot be read)."""
    try:
        text = log.read_text(errors="replace")
    except OSError:
        return ""
    return "\n".join(text.rstrip().splitlines()[-lines:])


def _forked_node(argv: list[str], log_fd: int) -> None:
    """In the forked child: become ``testbed node ...`` (``argv``) with its output in the log; never returns."""
    import logging

    code = 1
    try:
        os.setsid()  # its own session and process group, as with Popen(start_new_session=True)
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.dup2(log_fd, 1)
        os.dup2(log_fd, 2)
        for fd in {null, log_fd} - {0, 1, 2}:
            os.close(fd)
        for s in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2):
            signal.signal(s, signal.SIG_DFL)
        try:  # its name in ps -o comm / top (its command line stays the launcher's): tb-plant, ...
            import ctypes

            ctypes.CDLL(None).prctl(15, ctypes.c_char_p(f"tb-{argv[1]}"[:15].encode()), 0, 0, 0)  # PR_SET_NAME
        except (OSError, AttributeError, IndexError):
            pass
        sys.stdout.reconfigure(line_buffering=True)  # type: ignore[union-attr]  # a TextIOWrapper here; typeshed: TextIO
        logging.root.handlers.clear()
        from ..common.dispatch import run_child

        code = run_child(argv)
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        if not isinstance(e.code, int) and e.code is not None:
            print(e.code, file=sys.stderr)
    except BaseException:  # noqa: BLE001 - a child of the launcher never returns into the launcher's code
        import traceback

        traceback.print_exc()
    finally:
        try:
            logging.shutdown()
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code if isinstance(code, int) else 1)
