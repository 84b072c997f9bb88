"""A node process's own settings: signals, CPU affinity, SCHED_FIFO, logging, start-up milestones."""

from __future__ import annotations

import ctypes
import faulthandler
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable

log = logging.getLogger("testbed.nodes")


# ============================================================================ process setup
_libc = None


def _prctl(option: int, arg: int) -> bool:
    global _libc
    try:
        if _libc is None:
            _libc = ctypes.CDLL(None, use_errno=True)
        return _libc.prctl(option, arg, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def tune_process(parent_pid: int | None = None) -> dict:
    """Fine timer slack, death with the parent (launcher), stacks on SIGUSR1.

    ``kill -USR1 PID`` prints every thread's Python stack to the node's stderr
    (its log file under ``testbed run``): the way to see where a node hangs.
    """
    try:
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    except (AttributeError, ValueError, OSError):
        pass
    info = {"timerslack": _prctl(29, 1)}  # PR_SET_TIMERSLACK = 29: 1 ns instead of 50 us
    if parent_pid:
        _prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG = 1
        if os.getppid() != parent_pid:  # the launcher died before we got here
            raise SystemExit(f"testbed node: launcher (pid {parent_pid}) is gone")
    return info


def on_stop_signals(callback: Callable[[int], object], *, main_handler: Callable[[int], object] | None = None,
                    grace: float | None = None, signals: Iterable[int] = (signal.SIGINT, signal.SIGTERM),
                    others: dict[int, Callable[[], object]] | None = None) -> None:
    """Call ``callback(signum)`` on a helper thread when one of ``signals`` arrives.

    A Python signal handler runs on the main thread between two bytecodes, which
    may be inside ``threading.Event.wait`` holding the event's lock: a handler that
    sets an event or notifies a condition deadlocks there (seen: a node hung for
    ever after the launcher's death sent it SIGTERM).  So the Python handler does
    nothing but (optionally) ``main_handler``; the interpreter's C-level handler
    writes the signal number to a wake-up pipe, and a daemon thread reads it and
    calls ``callback``, outside any lock the main thread holds.

    ``grace``: after the first signal, exit hard (``os._exit(1)``) if the process
    is still alive ``grace`` seconds later, so a stop that hangs anyway cannot leave
    an orphan behind.  ``others``: {signal: handler()} for signals that do not stop
    the process (fault injection), called the same way.
    """
    r, w = os.pipe()
    os.set_blocking(w, False)
    wanted = {int(s) for s in signals}
    extra = {int(s): h for s, h in (others or {}).items()}

    def py_handler(signum: int, _frame: object) -> None:
        if main_handler is not None and signum in wanted:
            main_handler(signum)

    for s in (*signals, *extra):
        signal.signal(s, py_handler)
    signal.set_wakeup_fd(w, warn_on_full_buffer=False)

    def pump() -> None:
        armed = False
        while True:
            try:
                data = os.read(r, 64)
            except OSError:
                return
            for b in data:
                if b in extra:
                    try:
                        extra[b]()
                    except Exception:
                        logging.getLogger(__name__).exception("signal handler failed")
                    continue
                if b not in wanted:
                    continue
                if grace is not None and not armed:
                    armed = True
                    threading.Thread(target=_exit_after, args=(grace, b), daemon=True,
                                     name="stop-deadline").start()
                try:
                    callback(b)
                except Exception:
                    logging.getLogger(__name__).exception("stop callback failed")

    threading.Thread(target=pump, daemon=True, name="signals").start()


def _exit_after(seconds: float, signum: int) -> None:
    time.sleep(seconds)
    try:
        name = signal.Signals(signum).name
    except ValueError:
        name = str(signum)
    print(f"testbed: still running {seconds:g} s after {name}; exiting hard", file=sys.stderr, flush=True)
    os._exit(1)


def parse_cpus(spec: str) -> set[int]:
    """``2``, ``2,3``, ``0-3,6`` -> a set of CPU numbers (BadInput on anything else)."""
    from ..common.errors import BadInput

    out: set[int] = set()
    try:
        for part in spec.split(","):
            part = part.strip()
            lo, sep, hi = part.partition("-")
            out.update(range(int(lo), int(hi) + 1) if sep else [int(lo)])
    except ValueError:
        raise BadInput(f"CPU list {spec!r}: expected e.g. 2 or 2,3 or 0-3") from None
    avail = os.sched_getaffinity(0)
    if not out or not out <= avail:
        raise BadInput(f"CPU list {spec!r}: this machine offers CPUs {','.join(map(str, sorted(avail)))}")
    return out


def fifo_permitted() -> bool:
    """Whether this process may run under SCHED_FIFO (root or CAP_SYS_NICE, and an RT budget): tried on the
    calling thread and undone."""
    try:
        before = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except (OSError, AttributeError):
        return False
    os.sched_setscheduler(0, before[0], before[1])
    return True


def set_realtime(on: bool, priority: int = 1) -> bool:
    """SCHED_FIFO (``on``) or back to SCHED_OTHER for every thread of this process.

    Applied only for the loop itself (after start-up, JIT and warm-up), so a node
    never competes at real-time priority while compiling or connecting.  The
    kernel's RT throttling still leaves 5% of each CPU to everybody else.

    Threads with a higher nice value than the main thread (the Rerun logging thread and the threads
    Rerun created from it, ``rerun_tap.NICE``) are background work and stay
    SCHED_OTHER: a real-time thread would preempt the loop it is meant to stay off.
    """
    policy = os.SCHED_FIFO if on else os.SCHED_OTHER
    param = os.sched_param(priority if on else 0)
    try:
        base = os.getpriority(os.PRIO_PROCESS, os.getpid())  # the main thread's nice value
    except OSError:
        base = 0
    ok = True
    for tid in os.listdir("/proc/self/task"):
        try:
            if on and os.getpriority(os.PRIO_PROCESS, int(tid)) > base:
                continue
            os.sched_setscheduler(int(tid), policy, param)
        except (OSError, ValueError):
            ok = False
    return ok


def setup_logging(role: str, verbose: bool) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, stream=sys.stderr,
                        format=f"%(asctime)s {role:10s} %(levelname)s %(message)s")


def process_age() -> float:
    """Seconds since this process was created (10 ms resolution), or NaN."""
    try:
        with open("/proc/self/stat") as f:
            start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])
        return time.clock_gettime(time.CLOCK_BOOTTIME) - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, AttributeError):
        return float("nan")


def peak_rss_mb() -> float | None:
    """This process's peak resident memory so far (``VmHWM``), in MB; None where /proc has none."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def phase(who: str, name: str) -> None:
    """A start-up or shut-down milestone in the log (``-v``): ``benchmarks/bench_startup.py`` reads them."""
    if log.isEnabledFor(logging.INFO):
        log.info("%s: phase %s t=%.6f age=%.3f cpu=%.3f", who, name, time.time(), process_age(), time.process_time())
