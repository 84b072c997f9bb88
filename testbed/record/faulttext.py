"""A run's fault as one console line, the same in ``testbed run`` and ``testbed report``: its node and kind,
why, its one sample and its one time, and for a node that was lost when it came back (``back_s``)."""

from __future__ import annotations


def fault_time(f: dict) -> float | None:
    """The fault's time (s after t0): ``t_s``, or for a stall the end of the gap (``to_s``, when its
    ``at_sample`` came), or None."""
    t = f.get("t_s")
    return f.get("to_s") if t is None else t


def fault_line(f: dict) -> str:
    """``FAULT node: kind (why) at sample K (t s)[; back at B s][; last log line]``."""
    k, t = f.get("at_sample"), fault_time(f)
    where = ""
    if k is not None:
        where = f" at sample {k}" + (f" ({t:g} s)" if t is not None else "")
    elif t is not None:
        where = f" at {t:g} s"
    back = ""
    if "back_s" in f:
        back = (f"; back at {f['back_s']:g} s" if f["back_s"] is not None
                else "; not back by the end of the run")
    return (f"FAULT {f.get('node') or 'run'}: {f.get('kind')} ({f.get('why')}){where}{back}"
            + (f"; {f['last_log_line']}" if f.get("last_log_line") else ""))


__all__ = ["fault_line", "fault_time"]
