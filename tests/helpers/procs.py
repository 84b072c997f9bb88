"""The processes of a run: which are still there (by a token of their command line), and reaping them."""

from __future__ import annotations

import os
import signal
import time


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
