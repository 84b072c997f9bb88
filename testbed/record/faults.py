"""A run's fault: one typed record built by every fault site of a live run (the launcher, the recorder's
control, the stall and loss watch, the link cuts, the device watch, the telemetry check) and written to the
summary JSON and the recording one way, ``Fault.to_dict``.

The written form is a JSON object whose keys are the user interface (docs/live.md "Faults"): ``node``,
``kind``, ``why`` always; ``at_sample``, ``t_s``, ``injected`` and the kind's own keys only where the fault
has them.  A field left ``UNSET`` is not written (``None`` is written as ``null``: ``back_s`` null means
"not back by the end of the run", an absent ``back_s`` that the node was never lost).  ``Fault.from_dict``
reads the written form back, keys it does not know included (an older or newer recording), so that
``Fault.from_dict(d).to_dict() == d``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Final


class _Unset:
    """The value of a field the fault does not have (not written)."""

    _it: _Unset | None = None

    def __new__(cls) -> _Unset:
        if cls._it is None:
            cls._it = super().__new__(cls)
        return cls._it

    def __repr__(self) -> str:
        return "UNSET"

    def __bool__(self) -> bool:
        return False


UNSET: Final = _Unset()

#: field name -> its key in the written form (the fields not named here are written under their own name)
_KEYS: Final = {"role": "node", "detail": "why", "sample": "at_sample", "time": "t_s"}


@dataclass(eq=True)
class Fault:
    """One fault of a run.  ``role``: the node (``None``: the run itself); ``kind``: what happened (``killed``,
    ``crashed``, ``stalled``, ``lost``, ``link_cut``, ``record_error``, ...); ``detail``: why, one line;
    ``sample``: its one sample (``at_sample``); ``time``: its one time, s after t0 (``t_s``); ``injected``:
    whether the run's own ``--kill``/``--stall``/``--cut`` caused it.  The other fields belong to some kinds."""

    kind: str
    role: str | None = None
    detail: Any = None
    sample: Any = UNSET
    time: Any = UNSET
    injected: Any = UNSET
    # a node that died (``killed``, ``crashed``) or the recorder
    last_log_line: Any = UNSET
    exit_code: Any = UNSET
    signal: Any = UNSET
    colocated_in: Any = UNSET
    # a stall (``stalled``): the gap in the node's own stamps
    from_s: Any = UNSET
    to_s: Any = UNSET
    duration_s: Any = UNSET
    last_sample_before: Any = UNSET
    colocated: Any = UNSET
    # a loss (``lost``), a device's faults
    external: Any = UNSET
    ends_run: Any = UNSET
    back_s: Any = UNSET
    # a link cut (``link_cut``)
    down_s: Any = UNSET
    up_s: Any = UNSET
    # the run's start-up timeout: the nodes alive then
    alive: Any = UNSET
    # when the node's liveliness token went (``Launcher``'s end of run)
    liveliness_lost: Any = UNSET
    liveliness_detect_ms: Any = UNSET
    #: keys of the written form this version does not know (an older or newer recording), written back as read
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """The written form (the summary's ``faults`` entries, the recording's launcher events)."""
        out = {}
        for f in dataclasses.fields(self):
            if f.name == "extra":
                continue
            v = getattr(self, f.name)
            if v is not UNSET:
                out[_KEYS.get(f.name, f.name)] = v
        out.update(self.extra)
        return out

    @classmethod
    def from_dict(cls, d: dict) -> Fault:
        """A fault read back from its written form; a key this version does not know is kept in ``extra``."""
        names = {_KEYS.get(f.name, f.name): f.name for f in dataclasses.fields(cls) if f.name != "extra"}
        kw: dict[str, Any] = {"kind": d.get("kind", UNSET), "role": UNSET, "detail": UNSET,
                              "extra": {k: v for k, v in d.items() if k not in names}}
        for k, v in d.items():
            if k in names:
                kw[names[k]] = v
        return cls(**kw)

    @property
    def has_back(self) -> bool:
        """Whether the fault says when its node came back (``back_s`` written, maybe null)."""
        return self.back_s is not UNSET


def given(v: Any) -> Any:
    """A field's value, None where the fault does not have it (as ``dict.get`` on the written form)."""
    return None if v is UNSET else v


def as_fault(f: Fault | dict) -> Fault:
    """A fault from either form (a reader of recordings and summaries gets dicts)."""
    return f if isinstance(f, Fault) else Fault.from_dict(f)


__all__ = ["Fault", "UNSET", "as_fault", "given"]
