"""The check of a number: a real number (not a bool), finite, in a range, with one wording.

It lives here, in the lowest package that checks numbers (``attackers`` imports nothing of
``testbed``), and ``testbed.common.validate.number`` is this same function: an attack's parameter, the
scenario's keys, a channel's, a device's, a method's and a flag's numbers are all checked by it.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import numpy as np


class Invalid(ValueError):
    """What is wrong with a value, as a phrase that follows the field's name ("must be finite, got nan")."""


def number(v: Any, *, integer: bool = False, lo: float | None = None, lo_open: bool = False,
           hi: float | None = None, hi_open: bool = False, allow_inf: bool = False) -> Any:
    """A real number (not a bool; numpy's scalars too), finite (``allow_inf``: +inf too), an integral value
    if ``integer`` (returned as an ``int``), in the range ``lo``..``hi`` (each bound open or closed)."""
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real):
        raise Invalid(f"must be a number, got {v!r}")
    x = float(v)
    if math.isnan(x) or (math.isinf(x) and not (allow_inf and x > 0)):
        raise Invalid(f"must be finite, got {v!r}")
    if integer and not x.is_integer():
        raise Invalid(f"must be an integer, got {v!r}")
    if lo is not None and (x <= lo if lo_open else x < lo):
        raise Invalid(f"must be {'>' if lo_open else '>='} {lo:g}, got {v!r}")
    if hi is not None and (x >= hi if hi_open else x > hi):
        raise Invalid(f"must be {'<' if hi_open else '<='} {hi:g}, got {v!r}")
    if integer:
        return int(v) if isinstance(v, (int, np.integer)) else int(x)  # an int exactly, however large
    return x


def field(what: str, v: Any, why: str = "", **bounds: Any) -> Any:
    """:func:`number` of ``v`` with ``what`` before the phrase ("attack kind 'random': parameter 'rho_D'
    must be < 1, got 1.5") and ``why`` after it in parentheses; ``ValueError`` (an :class:`Invalid`)."""
    try:
        return number(v, **bounds)
    except Invalid as e:
        raise Invalid(f"{what} {e}" + (f" ({why})" if why else "")) from None


#: Assumption 4's range of rho_D, as ``field``'s bounds and reason
RHO_D = {"lo": 0.0, "hi": 1.0, "hi_open": True}
RHO_D_WHY = "Assumption 4: rho_D in [0, 1)"
