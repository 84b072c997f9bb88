"""Emulated network channels: the ``[network]`` scenario section and its seeded per-sample draws.

One message per link per sample k.  Each link (``LINKS``) has a model (``LinkModel``): a delay with
jitter, a serialization time at a bit rate, and losses that are independent (Bernoulli) or bursty
(a Gilbert-Elliott chain).  ``draws(model, link, n)`` gives, for samples 0..n-1, whether the
channel loses sample k's message on that link and how long the message takes.  The draws are a
pure function of the model and its seed and are prefix-stable (``draws(m, l, n)`` restricted to
its first j samples equals ``draws(m, l, j)``), so a live channel stage and the simulator that
draw for different numbers of samples see the same channel.

The loss model.  ``loss_burst = 1``: sample k is lost with probability ``loss``, independently of
the others.  ``loss_burst = b > 1``: a two-state Markov chain (Gilbert-Elliott, a loss in the bad
state only) with P(good -> bad) = p = loss r / (1 - loss) and P(bad -> good) = r = 1 / b, started
in its stationary law; its stationary loss probability is p / (p + r) = loss and a burst of
losses lasts 1 / r = b samples on average (a geometric length).  p <= 1 needs
b >= loss / (1 - loss).

Pure: numpy only, no clock, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from .errors import BadInput

LINKS = ("sensor", "symbol", "actuation", "ack")
DISTRIBUTIONS = ("uniform", "normal")
_LINK_KEYS = ("delay", "jitter", "distribution", "loss", "loss_burst", "rate")


class ChannelError(BadInput):
    """A ``[network]`` table that cannot be used (one line naming the key)."""


@dataclass(frozen=True)
class LinkModel:
    """One ``[network.<link>]`` table; every field optional (the defaults are an ideal link)."""

    delay: float = 0.0              # s, the nominal one-way delay
    jitter: float = 0.0             # s: uniform U(-jitter, +jitter), or normal with standard deviation jitter
    distribution: str = "uniform"   # the jitter's distribution: "uniform" or "normal" (clipped: delay >= 0)
    loss: float = 0.0               # the mean loss probability, 0 <= loss < 1
    loss_burst: float = 1.0         # the mean burst length (>= 1); 1: independent losses
    rate: float = math.inf          # bits/s: a message of b bits takes b / rate s more

    @property
    def ideal(self) -> bool:
        return self.delay == 0 and self.jitter == 0 and self.loss == 0 and math.isinf(self.rate)

    def chain(self) -> tuple[float, float]:
        """The Gilbert-Elliott transition probabilities (p, r) = (P(good -> bad), P(bad -> good))."""
        r = 1.0 / self.loss_burst
        return self.loss * r / (1.0 - self.loss), r

    def to_dict(self) -> dict:
        """The keys that differ from the defaults (what a ``[network.<link>]`` table writes)."""
        d = LinkModel()
        return {k: getattr(self, k) for k in _LINK_KEYS if getattr(self, k) != getattr(d, k)}


@dataclass(frozen=True)
class NetworkModel:
    """The ``[network]`` section: a seed and one model per link; an absent link is ideal."""

    seed: int = 0
    links: Mapping[str, LinkModel] = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "links", dict(self.links))   # a plain dict: the model pickles (campaign workers)

    def __hash__(self):
        return hash((self.seed, tuple(sorted(self.links.items()))))

    def __eq__(self, other):
        return (isinstance(other, NetworkModel) and self.seed == other.seed
                and dict(self.links) == dict(other.links))

    def link(self, name: str) -> LinkModel:
        if name not in LINKS:
            raise ValueError(f"unknown link {name!r}; the links are {', '.join(LINKS)}")
        return self.links.get(name, LinkModel())

    def to_dict(self) -> dict:
        """The ``[network]`` table (``parse_network`` reads it back to an equal model)."""
        out: dict = {"seed": self.seed}
        for name in LINKS:
            if name in self.links:
                out[name] = self.links[name].to_dict()
        return out


@dataclass(frozen=True)
class LinkDraws:
    lost: np.ndarray    # (n,) bool: sample k's message on this link is lost by the channel
    delay: np.ndarray   # (n,) float64 seconds (the serialization time of ``bits`` at the rate included)


def _rng(seed: int, link: str, kind: int) -> np.random.Generator:
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([seed, LINKS.index(link), kind])))


def loss_chain(lm: LinkModel, u: np.ndarray) -> np.ndarray:
    """The losses of ``lm`` driven by uniforms ``u`` in [0, 1), one per sample (prefix-stable).

    Bernoulli (``loss_burst == 1``): lost[k] = u[k] < loss.  Gilbert-Elliott: the state at k = 0 is
    bad when u[0] < loss (the stationary law); then from good it turns bad when u[k] < p, from bad
    it turns good when u[k] < r."""
    n = len(u)
    if lm.loss == 0 or n == 0:
        return np.zeros(n, dtype=bool)
    if lm.loss_burst == 1:
        return u < lm.loss
    p, r = lm.chain()
    out = np.empty(n, dtype=bool)
    bad = bool(u[0] < lm.loss)
    out[0] = bad
    for k, uk in enumerate(u[1:].tolist(), start=1):
        bad = (uk >= r) if bad else (uk < p)
        out[k] = bad
    return out


def draws(model: NetworkModel | None, link: str, n: int, bits: int = 0) -> LinkDraws:
    """Sample k's loss and delay on ``link`` for k = 0..n-1: deterministic in (model, link) and
    prefix-stable.  The loss chain draws from the stream SeedSequence([seed, link index, 0]), the
    jitter from [seed, link index, 1]; the delay is max(delay + jitter draw, 0) + bits / rate."""
    if link not in LINKS:
        raise ValueError(f"unknown link {link!r}; the links are {', '.join(LINKS)}")
    n = int(n)
    lm = model.link(link) if model is not None else LinkModel()
    if lm.loss > 0:
        lost = loss_chain(lm, _rng(model.seed, link, 0).random(n))
    else:
        lost = np.zeros(n, dtype=bool)
    delay = np.full(n, lm.delay, dtype=np.float64)
    if lm.jitter > 0:
        g = _rng(model.seed, link, 1)
        j = g.uniform(-1.0, 1.0, n) * lm.jitter if lm.distribution == "uniform" else g.standard_normal(n) * lm.jitter
        delay = np.maximum(delay + j, 0.0)
    if bits and math.isfinite(lm.rate):
        delay = delay + bits / lm.rate
    return LinkDraws(lost=lost, delay=delay)


# ----------------------------------------------------------------------------- parsing
def _num(key: str, v, *, lo: float | None = None, lo_open: bool = False, hi: float | None = None,
         hi_open: bool = False, integer: bool = False, allow_inf: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ChannelError(f"[{key}] must be a number, got {v!r}")
    if math.isnan(v) or (math.isinf(v) and not allow_inf):
        raise ChannelError(f"[{key}] must be finite, got {v!r}")
    if integer and not float(v).is_integer():
        raise ChannelError(f"[{key}] must be an integer, got {v!r}")
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise ChannelError(f"[{key}] must be {'>' if lo_open else '>='} {lo:g}, got {v!r}")
    if hi is not None and (v >= hi if hi_open else v > hi):
        raise ChannelError(f"[{key}] must be {'<' if hi_open else '<='} {hi:g}, got {v!r}")
    return int(v) if integer else float(v)


def parse_link(name: str, table) -> LinkModel:
    """One ``[network.<name>]`` table -> ``LinkModel`` (``ChannelError`` naming the key)."""
    key = f"network.{name}"
    if not isinstance(table, dict):
        raise ChannelError(f"[{key}] must be a table")
    bad = sorted(set(table) - set(_LINK_KEYS))
    if bad:
        raise ChannelError(f"[{key}] unknown key(s) {bad}; allowed: {sorted(_LINK_KEYS)}")
    d = LinkModel()
    delay = _num(f"{key}.delay", table.get("delay", d.delay), lo=0)
    jitter = _num(f"{key}.jitter", table.get("jitter", d.jitter), lo=0)
    dist = table.get("distribution", d.distribution)
    if dist not in DISTRIBUTIONS:
        raise ChannelError(f"[{key}.distribution] must be one of {', '.join(map(repr, DISTRIBUTIONS))}, got {dist!r}")
    loss = _num(f"{key}.loss", table.get("loss", d.loss), lo=0, hi=1, hi_open=True)
    burst = _num(f"{key}.loss_burst", table.get("loss_burst", d.loss_burst), lo=1)
    if burst > 1 and loss > 0 and burst < loss / (1 - loss):
        raise ChannelError(f"[{key}.loss_burst] a mean loss of {loss:g} needs a mean burst length >= loss / (1 - loss)"
                           f" = {loss / (1 - loss):.4g} (P(good -> bad) would exceed 1), got {burst:g}")
    rate = _num(f"{key}.rate", table.get("rate", d.rate), lo=0, lo_open=True, allow_inf=True)
    return LinkModel(delay=delay, jitter=jitter, distribution=str(dist), loss=loss, loss_burst=burst, rate=rate)


def parse_network(table) -> NetworkModel:
    """The ``[network]`` table -> ``NetworkModel``: ``seed`` (an integer >= 0, default 0) and one
    table per link of ``LINKS``.  Raises ``ChannelError`` (one line naming the key)."""
    if not isinstance(table, dict):
        raise ChannelError("[network] must be a table")
    bad = sorted(set(table) - {"seed", *LINKS})
    if bad:
        raise ChannelError(f"[network] unknown key(s) {bad}; allowed: {['seed', *LINKS]}")
    seed = _num("network.seed", table.get("seed", 0), lo=0, integer=True)
    return NetworkModel(seed=int(seed), links={k: parse_link(k, table[k]) for k in LINKS if k in table})


__all__ = ["LINKS", "DISTRIBUTIONS", "ChannelError", "LinkModel", "NetworkModel", "LinkDraws", "draws",
           "loss_chain", "parse_link", "parse_network"]
