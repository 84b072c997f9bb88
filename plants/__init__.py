"""Plants: the interface, the registry, plant references and the bundled models.

    >>> import plants
    >>> p = plants.make("lienard", a=1/3, b=0.02)
    >>> p.n, p.m
    (2, 1)

A plant reference (``[plant] name`` of a scenario) is a registered name, the name
of an installed entry point (group ``dos_testbed.plants``) or
``"module.path:ClassName"`` (``plants.refs``).
"""

from __future__ import annotations

from dataclasses import fields
from typing import TYPE_CHECKING, Any

from .base import Plant, PlantFault, PlantProcess
from .cartpole import CartPole
from .lienard import Lienard
from .linear import Linear
from .pendulum import Pendulum
from .refs import _REGISTRY, ENTRY_POINT_GROUP, PlantRefError, entry_points, names, register, resolve

if TYPE_CHECKING:
    import os

BUILT_IN: tuple[type[Plant], ...] = (Lienard, Pendulum, CartPole, Linear)


for _c in BUILT_IN:
    register(_c)


def get(name: str, base_dir: str | os.PathLike | None = None) -> type[Plant]:
    """The plant class a reference names (``plants.refs.resolve``); ValueError when it cannot."""
    return resolve(name, base_dir)


def make(name: str, base_dir: str | os.PathLike | None = None, **params: Any) -> Plant:
    """Instantiate the plant ``name`` (any plant reference) with the given parameters.

    ``base_dir``: where a ``"module:Class"`` reference is imported from first (the
    scenario file's folder).  Unknown parameter names raise ValueError naming the
    accepted ones.
    """
    cls = resolve(name, base_dir)
    return instantiate(cls, name, params)


def instantiate(cls: type[Plant], name: str, params: dict) -> Plant:
    """``cls(**params)`` with the checks of ``make`` (numbers only; unknown names rejected)."""
    if cls is Linear:
        bad = set(params) - {"A", "B"}
        if bad:
            raise ValueError(f"plant 'linear': unknown parameter(s) {sorted(bad)}; accepted: A, B")
        return Linear.from_params(**params)
    accepted = [f.name for f in fields(cls)]
    bad = set(params) - set(accepted)
    if bad:
        raise ValueError(f"plant {name!r}: unknown parameter(s) {sorted(bad)}; accepted: {', '.join(accepted)}")
    try:
        kw = {k: float(v) for k, v in params.items()}
    except (TypeError, ValueError):
        raise ValueError(f"plant {name!r}: parameters must be numbers, got {params}") from None
    try:
        return cls(**kw)
    except ValueError:
        raise
    except Exception as e:  # noqa: BLE001 - a user's __post_init__: one line
        raise ValueError(f"plant {name!r}: {type(e).__name__}: {e}") from None


def available() -> list[dict]:
    """Every plant a scenario can name without a module path: the registered ones, then the entry points.

    Each row: ``name``, ``source`` ("built-in", "registered" or "entry point"),
    ``ref`` (``module:Class``), ``n``, ``m``, ``description`` (from an instance
    with default parameters), ``dist`` (entry points), ``shadowed`` (an entry point
    whose name a registered plant takes), ``error`` (None, or why it does not load).
    """
    from .refs import load_entry_point

    rows = []
    for name in names():
        cls = _REGISTRY[name]
        rows.append(_row(name, cls, "built-in" if cls in BUILT_IN else "registered",
                         f"{cls.__module__}:{cls.__qualname__}"))
    for name, ep in sorted(entry_points().items()):
        dist = getattr(getattr(ep, "dist", None), "name", None)
        try:
            cls = load_entry_point(ep)
        except PlantRefError as e:
            rows.append({"name": name, "source": "entry point", "ref": ep.value, "dist": dist, "n": None,
                         "m": None, "description": "", "shadowed": name in _REGISTRY, "error": str(e)})
            continue
        row = _row(name, cls, "entry point", ep.value)
        row.update(dist=dist, shadowed=name in _REGISTRY)
        rows.append(row)
    return rows


def _row(name: str, cls: type[Plant], source: str, ref: str) -> dict:
    row: dict[str, Any] = {"name": name, "source": source, "ref": ref, "n": None, "m": None,
           "description": cls.description or (cls.__doc__ or "").strip().split("\n")[0], "error": None}
    try:
        p = cls.from_params() if cls is Linear else cls()
        row["n"], row["m"] = int(p.n), int(p.m)
    except Exception as e:  # noqa: BLE001 - a plant without defaults: listed, with the reason
        row["error"] = f"cannot instantiate with default parameters: {type(e).__name__}: {e}"
    return row


__all__ = ["Plant", "PlantFault", "PlantProcess", "PlantRefError", "Lienard", "Pendulum", "CartPole", "Linear",
           "register", "names", "get", "make", "instantiate", "resolve", "available", "entry_points",
           "ENTRY_POINT_GROUP"]
