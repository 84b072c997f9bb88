"""The one table of noise distributions a scenario names (``distribution = "uniform" | "normal"``): the
network channel's jitter (``[network.LINK]``, ``testbed.loop.channel``) and the plant's sensor noise and
disturbance (``[plant.sensor]``, ``[plant.disturbance]``, ``testbed.loop.device``) draw from it.  Each user
keeps its own default (the channel's jitter ``uniform``, the device's noise ``normal``)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

#: name -> n draws of unit scale from a generator: "uniform" U[-1, 1) (half-width 1), "normal" N(0, 1)
DISTRIBUTIONS: dict[str, Callable[[np.random.Generator, int], np.ndarray]] = {
    "uniform": lambda rng, n: 2.0 * rng.random(n) - 1.0,
    "normal": lambda rng, n: rng.standard_normal(n),
}


def draw(rng: np.random.Generator, distribution: str, scale: float, n: int) -> np.ndarray:
    """``n`` draws of ``distribution`` at ``scale`` (uniform: half-width; normal: standard deviation)."""
    return scale * DISTRIBUTIONS[distribution](rng, n)


def names(default: str) -> tuple[str, ...]:
    """The names, ``default`` first (as a user's error message lists them)."""
    return (default, *(d for d in DISTRIBUTIONS if d != default))


__all__ = ["DISTRIBUTIONS", "draw", "names"]
