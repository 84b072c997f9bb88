"""``timing_degraded``: whether a live run kept its timing, by one documented criterion (docs/live.md).

A run whose nodes were starved or frozen may still converge and still be reproduced by
``testbed resimulate`` (what happened is recorded), but it is not the loop the scenario describes:
some samples were lost or late for the machine's sake, not the network's or the attacker's.  The
run says so itself, in ``testbed run --json`` and ``testbed report``, rather than passing as a
clean result.
"""

from __future__ import annotations

#: what an attacker (or a forged message) can cause as well as a stalled node
ATTACKER_CAUSED = ("late_symbols", "superseded", "future_sensor", "future_symbol", "future_actuation")


def timing_faults(s: dict) -> dict:
    """The timing faults a run reports about itself: {name: count} of those that happened.

    Deadline misses and overruns at the plant; sensor samples the encoder got out of order
    (``stale_sensor``); under physical timing with scheduled actuation a u_k later than its instant
    (``late_for_schedule``); with the ideal ack, an ack that missed the encoder's grace window
    (``ack_missing``), which only a stall of about a period can cause (less what a ``[network]``
    channel model lost on purpose: u_k on the actuation link, acks); late and superseded symbols;
    genuine messages a node took for ones from the future (its clock read during a stall); and the
    launcher's ``stalled`` faults (a node whose samples stopped while its liveliness stayed).
    """
    tm = s.get("timing") or {}
    ev = s.get("events") or {}
    enc = (s.get("node_summaries") or {}).get("encoder") or {}
    out = {"deadline_misses": tm.get("deadline_misses"), "overruns": tm.get("overruns"),
           "stale_sensor": enc.get("stale_sensor"), "late_for_schedule": tm.get("late_for_schedule"),
           "late_symbols": s.get("late_symbols"), "superseded": (s.get("loss_reasons") or {}).get("superseded")}
    chan = {r: (n or {}).get("channel") or {} for r, n in (s.get("node_summaries") or {}).items()}
    if not s.get("ack_via_attacker") and not chan.get("encoder", {}).get("ack", {}).get("lost_at"):
        out["ack_missing"] = ev.get("ack_missing")  # (an ack a [network] channel model lost: no stall)
    u_lost = set(chan.get("plant", {}).get("actuation", {}).get("lost_at") or ())
    if u_lost:  # a u_k the channel model lost is the channel's miss, not a stalled machine's
        out["deadline_misses"] = len(set(s.get("deadline_missed_at") or ()) - u_lost)
    out.update({k: ev.get(k) for k in ("future_sensor", "future_symbol", "future_actuation")})
    out["stalled"] = sum(1 for f in s.get("faults") or [] if f.get("kind") == "stalled")
    return {k: int(v) for k, v in out.items() if v}


def timing_degraded(s: dict) -> dict:
    """``timing_degraded`` (bool) and ``timing_degraded_why`` (the faults that made it so, or None)."""
    faults = timing_faults(s)
    why = ", ".join(f"{k} {v}" for k, v in faults.items())
    stalls = [f"{f['node']} {f.get('from_s')}-{f.get('to_s')} s" for f in s.get("faults") or []
              if f.get("kind") == "stalled"]
    if stalls:
        why += f" ({'; '.join(stalls)})"
    return {"timing_degraded": bool(faults), "timing_degraded_why": why or None, "timing_faults": faults}


__all__ = ["timing_degraded", "timing_faults", "ATTACKER_CAUSED"]
