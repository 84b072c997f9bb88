"""Plants: the interface, the registry and the bundled models.

    >>> import plants
    >>> p = plants.make("lienard", a=1/3, b=0.02)
    >>> p.n, p.m
    (2, 1)
"""

from __future__ import annotations

from .base import Plant
from .cartpole import CartPole
from .lienard import Lienard
from .linear import Linear
from .pendulum import Pendulum

_REGISTRY: dict[str, type[Plant]] = {}


def register(cls: type[Plant]) -> type[Plant]:
    """Add a plant class to the registry under ``cls.name``."""
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    _REGISTRY[cls.name] = cls
    return cls


for _c in (Lienard, Pendulum, CartPole, Linear):
    register(_c)


def names() -> list[str]:
    return sorted(_REGISTRY)


def get(name: str) -> type[Plant]:
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown plant {name!r}; registered plants: {', '.join(names())}") from None


def make(name: str, **params) -> Plant:
    """Instantiate the registered plant ``name`` with the given parameters.

    Unknown parameter names raise ValueError naming the accepted ones.
    """
    cls = get(name)
    if cls is Linear:
        bad = set(params) - {"A", "B"}
        if bad:
            raise ValueError(f"plant 'linear': unknown parameter(s) {sorted(bad)}; accepted: A, B")
        return Linear.from_params(**params)
    from dataclasses import fields

    accepted = [f.name for f in fields(cls)]
    bad = set(params) - set(accepted)
    if bad:
        raise ValueError(f"plant {name!r}: unknown parameter(s) {sorted(bad)}; accepted: {', '.join(accepted)}")
    try:
        kw = {k: float(v) for k, v in params.items()}
    except (TypeError, ValueError):
        raise ValueError(f"plant {name!r}: parameters must be numbers, got {params}") from None
    return cls(**kw)


__all__ = ["Plant", "Lienard", "Pendulum", "CartPole", "Linear", "register", "names", "get", "make"]
