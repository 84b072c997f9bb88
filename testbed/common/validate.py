"""The checks of an input's numbers, ranges and choices, one wording for every parser of input (the
scenario, its ``[network]`` and ``[plant.*]`` device tables, a method's parameters, a campaign file,
the flags of ``testbed run``).

Each check returns the value (an ``int`` where it asks for an integer) or raises :class:`Invalid` with
the phrase of what is wrong ("must be > 0, got -1"); the parser puts its field's name before it in its
own error type (``ScenarioError``: "paper.toml: [quantizer.T] must be > 0, got -1").  :func:`number` and
:class:`Invalid` are ``attackers.checks``' (the lowest package that checks numbers: an attack's
parameters are checked by the same function).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Any

from attackers.checks import Invalid, number

from .errors import BadInput


def positive(v: Any) -> float:
    """A finite number > 0 (one phrase for all of it: "must be a positive number")."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise Invalid(f"must be a positive number, got {v!r}")
    return float(v)


def count(v: Any, lo: int = 0) -> int:
    """An ``int`` (not a bool, not a float with an integral value) >= ``lo``: a seed, a repeat count."""
    if isinstance(v, bool) or not isinstance(v, int) or v < lo:
        raise Invalid(f"must be an integer >= {lo}, got {v!r}")
    return int(v)


def choice(v: Any, choices: Iterable[Any]) -> Any:
    """One of ``choices`` (listed in their order in the message)."""
    choices = tuple(choices)
    if v not in choices:
        raise Invalid(f"must be one of {', '.join(repr(c) for c in choices)}, got {v!r}")
    return v


def text_number(text: str, kind: Callable[[str], Any] = float) -> Any:
    """A command line's number (``kind``: ``float`` or ``int``), finite and >= 0; the phrase follows the
    value ("'-1' is not a finite number >= 0")."""
    try:
        v = kind(text)
    except ValueError:
        raise Invalid(f"{text!r} is not a number") from None
    if not (math.isfinite(v) and v >= 0):
        raise Invalid(f"{text!r} is not a finite number >= 0")
    return v


def flag(name: str, v: Any, check: Callable[..., Any] = number, *args: Any, **kw: Any) -> Any:
    """``check(v, *args, **kw)`` of a command's flag ``name`` ("--beam"): ``BadInput`` "NAME PHRASE" (one
    line, exit 2) where it fails."""
    try:
        return check(v, *args, **kw)
    except Invalid as e:
        raise BadInput(f"{name} {e}") from None


__all__ = ["Invalid", "number", "positive", "count", "choice", "text_number", "flag"]
