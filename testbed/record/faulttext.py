"""A run's fault as one console line, the same in ``testbed run`` and ``testbed report``: its node and kind,
why, its one sample and its one time, and for a node that was lost when it came back (``back_s``)."""

from __future__ import annotations

from .faults import Fault, as_fault, given


def fault_time(f: Fault | dict) -> float | None:
    """The fault's time (s after t0): ``t_s``, or for a stall the end of the gap (``to_s``, when its
    ``at_sample`` came), or None."""
    f = as_fault(f)
    t = given(f.time)
    return given(f.to_s) if t is None else t


def fault_line(f: Fault | dict) -> str:
    """``FAULT node: kind (why) at sample K (t s)[; back at B s][; last log line]``."""
    f = as_fault(f)
    k, t = given(f.sample), fault_time(f)
    where = ""
    if k is not None:
        where = f" at sample {k}" + (f" ({t:g} s)" if t is not None else "")
    elif t is not None:
        where = f" at {t:g} s"
    back = ""
    if f.has_back:
        back = (f"; back at {f.back_s:g} s" if f.back_s is not None
                else "; not back by the end of the run")
    return (f"FAULT {f.role or 'run'}: {given(f.kind)} ({given(f.detail)}){where}{back}"
            + (f"; {f.last_log_line}" if f.last_log_line else ""))


__all__ = ["fault_line", "fault_time"]
