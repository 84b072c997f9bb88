"""The one rule for swapping the method of a scenario.

``--method`` (``simulate``, ``run``, the analyses), ``testbed.simulate(method=...)``, ``testbed versus``
and a campaign's ``method.name`` axis (with its ``[methods.NAME] params``) all swap through
:func:`swap`, so that they agree:

- swapping in the scenario's own method (the same reference, or a reference to the same class) keeps
  its ``[method] params``; params given with the swap are written over them;
- another method gets only the params given with it (its defaults for the rest); the scenario's
  params it drops are named in the note;
- the ``[quantizer]`` keys the method does not use are left out (named in the note).

The note is one line (``note(...)``), printed once on stderr by the command that swapped.
"""

from __future__ import annotations

from collections.abc import Collection
from typing import TYPE_CHECKING, Any, NamedTuple

from .spec import ScenarioError

if TYPE_CHECKING:
    from ..methods.base import Method


class Swapped(NamedTuple):
    """A swap's result: the new document, the note, and the method object the swap built to check it
    (handed to the scenario's build, so that a ``--method`` swap builds its method once)."""

    data: dict[str, Any]
    note: str
    method: Method


def own_method(data: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    """The ``[method] name`` (default ``paper``) and ``params`` of a parsed scenario document."""
    from .. import methods

    mt = data.get("method")
    if not isinstance(mt, dict):
        mt = {}
    params = mt.get("params")
    if not isinstance(params, dict):
        params = {}
    return mt.get("name", methods.DEFAULT), dict(params)


def same_method(a: str, b: str, base_dir: str | None) -> bool:
    """Whether references ``a`` and ``b`` name the same method class (a reference that cannot be
    resolved is the same only as itself)."""
    if a == b:
        return True
    from .. import methods

    try:
        return methods.resolve(a, base_dir) is methods.resolve(b, base_dir)
    except methods.MethodError:
        return False


def note(name: str, old: str, ignored: list[str], dropped: list[str]) -> str:
    """The swap's one line (empty when it leaves nothing out)."""
    parts = []
    if ignored:
        parts.append(f"ignores [quantizer] {', '.join(ignored)} of this scenario")
    if dropped:
        parts.append(f"drops the [method] params {', '.join(dropped)} of {old!r}")
    return f"method {name!r} " + " and ".join(parts) if parts else ""


def swap(data: dict[str, Any], new: str | dict[str, Any], base_dir: str | None, *,
         known_quantizer_keys: Collection[str] | None = None, where: str = "<scenario>") -> Swapped:
    """``data`` (a parsed scenario document; not changed) with the method ``new`` swapped in by the rule
    of the module docstring: (the new document, the note, the method object built to check it).

    ``new``: a reference, or ``{"name": ref, "params": {...}}`` (no name: the scenario's own method).
    Only ``known_quantizer_keys`` are ever left out of ``[quantizer]`` (an unknown key stays, for the
    scenario's own check to name).  A method that cannot be made is a ``ScenarioError`` (one line).
    """
    from .. import methods

    old, old_params = own_method(data)
    if isinstance(new, str):
        new = {"name": new}
    if not isinstance(new, dict) or set(new) - {"name", "params"}:
        raise ScenarioError(f"{where}: [method] a swapped method is a name or {{name, params}}, got {new!r}")
    name = new.get("name", old)
    given = new.get("params") or {}
    if not isinstance(name, str) or not name:
        raise ScenarioError(f"{where}: [method.name] must be a non-empty string, got {name!r}")
    if not isinstance(given, dict):
        raise ScenarioError(f"{where}: [method.params] must be a table, got {given!r}")
    same = same_method(name, old, base_dir)
    params = {**old_params, **given} if same else dict(given)
    dropped = [] if same else sorted(k for k in old_params if k not in given)
    try:
        obj = methods.make(name, base_dir, params)
    except methods.MethodError as e:
        raise ScenarioError(f"{where}: [method] {e}") from None
    used = {"T", *obj.uses}
    qt = data.get("quantizer")
    ignored = [k for k in qt if k not in used and (known_quantizer_keys is None or k in known_quantizer_keys)] \
        if isinstance(qt, dict) else []
    out = {**data, "method": {"name": name, **({"params": params} if params else {})}}
    if ignored and isinstance(qt, dict):
        out["quantizer"] = {k: v for k, v in qt.items() if k not in ignored}
    return Swapped(out, note(name, old, ignored, dropped), obj)
