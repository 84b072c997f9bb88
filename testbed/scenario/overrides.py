"""Run-time overrides of a scenario (``testbed run|simulate --duration ...``): which keys they are, and how
they are checked and written into a parsed scenario document as if written in its file.

``testbed.scenario`` applies them (``load``/``loads(..., overrides=)`` and ``with_overrides``) and builds
the Scenario; this module only edits the parsed document.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from ..common.errors import BadInput
from .methodswap import Swapped

if TYPE_CHECKING:
    import numpy.typing as npt

#: run-time overrides a scenario accepts (``testbed run|simulate --duration ...``): name -> (table, key)
OVERRIDES = {"duration": ("run", "duration"), "timing": ("run", "timing"), "deadline": ("run", "deadline"),
             "mode": ("quantizer", "mode"), "T": ("quantizer", "T"), "loss_fraction": ("run", "loss_fraction"),
             "actuation": ("run", "actuation"), "rule": ("quantizer", "rule"), "seed": ("attack", "seed"),
             "x0": ("plant", "x0"), "E0": ("quantizer", "E0"), "M": ("quantizer", "M"), "method": ("method", None),
             "attack": ("attack", None)}


INT_OVERRIDES = {"seed", "M"}


def checked(overrides: dict | None, name: str) -> dict:
    """The overrides that are set (None values left out); an unknown one is a ``BadInput``."""
    over = {k: v for k, v in (overrides or {}).items() if v is not None}
    unknown = set(over) - set(OVERRIDES)
    if unknown:
        raise BadInput(f"unknown override(s): {', '.join(sorted(unknown))}; the overrides are "
                       f"{', '.join(OVERRIDES)} (any other key: write it in a copy of the scenario, "
                       f"testbed scenarios --show {name} > my.toml)")
    return over


def apply(data: dict, over: dict, swap: Callable[[dict, Any], Swapped]) -> tuple[dict, Swapped | None]:
    """``over`` written into the parsed document ``data`` (edited in place) as if in the file; a method
    swapped in last by ``swap(data, method)`` (``testbed.scenario.swap_method``: the one rule).  Returns the
    document and the swap (its note and the method it built), None without a method override."""
    for k, v in over.items():
        table, key = OVERRIDES[k]
        if table == "method":  # --method NAME (or {"name": ..., "params": {...}}): swapped in last, below
            if not isinstance(v, (str, dict)):
                raise BadInput(f"override method must be a method name, got {v!r}")
            continue
        if key is None:  # attack: a table merged into [attack] (a new kind replaces it)
            if not isinstance(v, dict):
                raise BadInput(f"override {k} must be a dict of [{table}] keys (e.g. attack={{\"intervals\": "
                               f"[[1.0, 0.5]]}} or attack={{\"kind\": \"none\"}}), got {v!r}")
            old = data.get(table, {})
            data[table] = {**({} if "kind" in v and v["kind"] != old.get("kind") else old), **v}
            continue
        if isinstance(v, np.ndarray):
            v = v.tolist()
        as_float = isinstance(v, int) and not isinstance(v, bool) and k not in INT_OVERRIDES
        data.setdefault(table, {})[key] = float(v) if as_float else v
    if "method" in over:
        swapped = swap(data, over["method"])
        return swapped.data, swapped
    return data, None


def hint(msg: str, name: str, x0: npt.ArrayLike, over: dict) -> str:
    """A scenario error caused by overrides, reworded so that a caller of overrides can act on it."""
    names = ", ".join(f"{k}={v!r}" for k, v in over.items())
    x0 = over.get("x0", x0)
    try:
        nx = max(abs(float(v)) for v in np.ravel(x0))
    except (TypeError, ValueError):
        nx = None
    if "allow_x0_outside" in msg and nx is not None:
        msg = msg.replace("(set allow_x0_outside = true to run it anyway)",
                          f"(pass E0={nx:g} or larger with it; or, to run it anyway, set allow_x0_outside = true in "
                          f"[quantizer] of a copy of the scenario: testbed scenarios --show {name})")
    if "allow_M_le_Lambda" in msg:
        msg = msg.replace("(set allow_M_le_Lambda = true to run it anyway)",
                          "(pass a larger M or a smaller T; or, to run it anyway, set allow_M_le_Lambda = true in "
                          f"[quantizer] of a copy of the scenario: testbed scenarios --show {name})")
    return f"override(s) {names}: {msg}"
