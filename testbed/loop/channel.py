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
from typing import Any

import numpy as np
import numpy.typing as npt

from ..common import validate
from ..common.errors import BadInput
from .distributions import draw, names

LINKS = ("sensor", "symbol", "actuation", "ack")
DISTRIBUTIONS = names("uniform")  # the jitter's distributions (testbed.loop.distributions), its default first
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

    def __post_init__(self) -> None:
        object.__setattr__(self, "links", dict(self.links))   # a plain dict: the model pickles (campaign workers)

    def __hash__(self) -> int:
        return hash((self.seed, tuple(sorted(self.links.items()))))

    def __eq__(self, other: object) -> bool:
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
    seed = model.seed if model is not None else 0  # no model: a perfect link, nothing drawn
    if lm.loss > 0:
        lost = loss_chain(lm, _rng(seed, link, 0).random(n))
    else:
        lost = np.zeros(n, dtype=bool)
    delay = np.full(n, lm.delay, dtype=np.float64)
    if lm.jitter > 0:
        g = _rng(seed, link, 1)
        delay = np.maximum(delay + draw(g, lm.distribution, lm.jitter, n), 0.0)
    if bits and math.isfinite(lm.rate):
        delay = delay + bits / lm.rate
    return LinkDraws(lost=lost, delay=delay)


# ----------------------------------------------------------------------------- the channel per sample
#: why sample k was lost (``SimResult.loss_cause``, the summary's ``losses``); RECEIVED: not lost
RECEIVED, ATTACKER, CHANNEL, LATE, WITHHELD, NETWORK = 0, 1, 2, 3, 4, 5
#: the causes of a lost sample, each sample exactly one: the attacker dropped or corrupted it, the ``[network]``
#: channel model lost it, the real network lost it (a live run only: sent, not lost by the model, never
#: received), it came after the loss deadline, the encoder withheld it
LOSS_KINDS = ("attacker", "channel", "network", "late", "withheld")


def loss_text(losses: dict) -> str:
    """``losses`` in words, every cause named (what every command prints: the counts add up to the samples lost)."""
    return ", ".join(f"{k} {int(losses.get(k) or 0)}" for k in LOSS_KINDS)


def payload_bits(link: str, n: int, m: int, symbol_bytes: int) -> int:
    """The bits a ``rate`` charges for one message on ``link``: its payload (the summary's ``sizes``:
    the sensor's 8 n bytes, the symbol's codebook bytes, the actuation's 5 + 8 m, the ack's 5); the
    message header is not charged."""
    return 8 * {"sensor": 8 * n, "symbol": int(symbol_bytes), "actuation": 5 + 8 * m, "ack": 5}[link]


@dataclass(frozen=True)
class SampleChannel:
    """What the channel does to sample k's messages (k = 0..N-1), as the simulator applies it.

    sensed : x_k reaches the encoder (the sensor link did not lose it)
    symbol_lost : the symbol link loses the symbol (after the attacker: the attacker forwarded it)
    late : physical timing only: the symbol arrives after the controller's loss deadline
        (sensor delay + symbol delay > loss deadline): a loss by the deadline rule
    ack_lost : the controller's ack of sample k never reaches the encoder
    actuation_lost : u_k never reaches the plant (u_missing)
    upstream_ns : sensor + symbol delay [ns]: added to u_k's latency when the symbol was received
    actuation_ns : the actuation link's delay [ns]: added to u_k's latency
    withheld : the encoder withholds sample k (its ack of an earlier sent sample never came, and
        no later ack came before x_k): what ``protocol.EncoderProtocol`` does, computed ahead
        (acks cross only the ack link here, and arrive before the next sample when not lost)
    """

    sensed: np.ndarray
    symbol_lost: np.ndarray
    late: np.ndarray
    ack_lost: np.ndarray
    actuation_lost: np.ndarray
    upstream_ns: np.ndarray
    actuation_ns: np.ndarray
    withheld: np.ndarray

    @property
    def forced(self) -> np.ndarray:
        """The samples the controller cannot receive whatever the attacker does (theta_k = 1)."""
        return ~self.sensed | self.withheld | self.symbol_lost | self.late


def withheld_pattern(sensed: np.ndarray, ack_lost: np.ndarray) -> np.ndarray:
    """The samples the encoder withholds (Algorithm 1's ack protocol, ``EncoderProtocol``): it sends
    x_k when it has no unacknowledged sample; a sent sample stays unacknowledged until an ack of it or
    of a later sample arrives (before the next sample, unless the ack link loses it)."""
    N = len(sensed)
    out = np.zeros(N, dtype=bool)
    pending = False
    for k, (s, lost_ack) in enumerate(zip(sensed.tolist(), ack_lost.tolist())):
        if s:
            if pending:
                out[k] = True
            else:
                pending = True
        if not lost_ack:   # the ack of sample k (sent, withheld or not sensed) resolves what is pending
            pending = False
    return out


def sample_channel(model: NetworkModel, N: int, *, physical: bool, loss_ns: int, n: int, m: int,
                   symbol_bytes: int) -> SampleChannel:
    """The channel of a simulated run of N samples: the draws of every link (``draws``) turned into
    what happens to each sample.  Under ideal timing only losses matter (delays are not applied: no
    sample is late, u_k's latency is not simulated); under physical timing a symbol whose sensor +
    symbol delay exceeds the loss deadline ``loss_ns`` is late, and the delays add to u_k's latency."""
    d = {k: draws(model, k, N, payload_bits(k, n, m, symbol_bytes)) for k in LINKS}

    def ns(a: np.ndarray) -> np.ndarray:
        return np.round(a * 1e9).astype(np.int64)

    sensed = ~d["sensor"].lost
    up = ns(d["sensor"].delay) + ns(d["symbol"].delay)
    late = (up > loss_ns) & sensed & ~d["symbol"].lost if physical else np.zeros(N, dtype=bool)
    act = ns(d["actuation"].delay) if physical else np.zeros(N, dtype=np.int64)
    return SampleChannel(sensed=sensed, symbol_lost=d["symbol"].lost & sensed, late=late,
                         ack_lost=d["ack"].lost, actuation_lost=d["actuation"].lost,
                         upstream_ns=up if physical else np.zeros(N, dtype=np.int64), actuation_ns=act,
                         withheld=withheld_pattern(sensed, d["ack"].lost))


def loss_cause(theta: npt.ArrayLike, *, withheld: npt.ArrayLike | None = None, sensed: npt.ArrayLike | None = None,
               attacker: npt.ArrayLike | None = None, symbol_lost: npt.ArrayLike | None = None,
               late: npt.ArrayLike | None = None) -> np.ndarray:
    """Why each lost sample (theta_k = 1) was lost, the first cause on the symbol's way: the encoder
    withheld it (WITHHELD), the sensor link lost x_k (CHANNEL), the attacker dropped or corrupted it
    (ATTACKER), the symbol link lost it (CHANNEL), it came after the loss deadline (LATE).  A loss with
    none of the causes given is the channel's (sent, forwarded, never received).  RECEIVED where theta_k = 0."""
    th = np.asarray(theta) != 0
    N = len(th)
    out = np.where(th, CHANNEL, RECEIVED).astype(np.int8)
    done = ~th
    for mask, code in ((withheld, WITHHELD), (None if sensed is None else ~np.asarray(sensed, dtype=bool), CHANNEL),
                       (attacker, ATTACKER), (symbol_lost, CHANNEL), (late, LATE)):
        if mask is None:
            continue
        sel = np.asarray(mask, dtype=bool)[:N] & ~done
        out[sel] = code
        done |= sel
    return out


def loss_counts(cause: np.ndarray) -> dict:
    """``{"attacker", "channel", "network", "late", "withheld"}`` (``LOSS_KINDS``): how many samples each
    cause lost (a simulation has no real network: its ``network`` is 0)."""
    return loss_counts_of(np.bincount(np.asarray(cause, dtype=np.int64), minlength=len(LOSS_KINDS) + 1))


def loss_counts_of(c: np.ndarray) -> dict:
    """``loss_counts`` of the counts of each cause (``np.bincount`` of ``loss_cause``, summed over chunks of a run)."""
    return {"attacker": int(c[ATTACKER]), "channel": int(c[CHANNEL]), "network": int(c[NETWORK]),
            "late": int(c[LATE]), "withheld": int(c[WITHHELD])}


def late_of_rest(rest: int, late_symbols: int | None) -> int:
    """Of ``rest`` lost samples that were sent, forwarded, not lost by the channel model and not received by
    the loss deadline, how many were late rather than the real network's: the controller's count of symbols
    that arrived after their sample was decided (``late_symbols``), at most ``rest`` (``recorded_losses``;
    the live status line at its end)."""
    return min(max(int(late_symbols or 0), 0), int(rest))


def model_lost(model: NetworkModel | None, n: int) -> np.ndarray:
    """Per sample 0 .. n - 1: the channel model loses x_k on the sensor link or the symbol on the symbol link
    (``draws``: the decisions the live channel stages make, known ahead; all False without a model)."""
    out = np.zeros(int(n), dtype=bool)
    if model is not None:
        for link in ("sensor", "symbol"):
            if model.link(link).loss > 0:
                out |= draws(model, link, n).lost
    return out


def recorded_losses(theta: npt.ArrayLike, *, withheld: npt.ArrayLike, attacker: npt.ArrayLike,
                    invalid: npt.ArrayLike, superseded: npt.ArrayLike, late_symbols: int | None,
                    channel_lost: npt.ArrayLike | None = None) -> dict:
    """``losses`` of a recording, from what its telemetry holds: per sample theta_k, the encoder's
    ``silent`` (withheld), the attacker's ``dropped`` (attacker; a payload the controller found
    invalid counts as the attacker's too: only the attacker corrupts), the controller's reason
    (``superseded``: decided only after a later sample came: late), the samples the ``[network]``
    channel model loses on the sensor or the symbol link (``channel_lost``: ``model_lost``, the draws the
    live channel stages decide by; None: no model), and the controller's count of symbols that arrived
    after their sample was decided (``late_symbols``, its summary's ``late``).  Every other lost sample
    was sent (and forwarded) and did not arrive by the loss deadline: the ``late_symbols`` that did
    arrive, later, are late, the rest the real network's (a cut link, a stalled host).  The five add up to the samples lost."""
    return losses_of_tally(loss_tally(theta, withheld=withheld, attacker=attacker, invalid=invalid,
                                      superseded=superseded, channel_lost=channel_lost), late_symbols)


def loss_tally(theta: npt.ArrayLike, *, withheld: npt.ArrayLike, attacker: npt.ArrayLike, invalid: npt.ArrayLike,
               superseded: npt.ArrayLike, channel_lost: npt.ArrayLike | None = None) -> np.ndarray:
    """``recorded_losses``' counts of some samples (a chunk of a run: the tallies of a run's chunks add up):
    [attacker, channel, other, superseded, withheld], ``other`` being sent, not the model's and not received."""
    lost = np.asarray(theta) != 0
    w = lost & np.asarray(withheld, dtype=bool)
    a = lost & ~w & (np.asarray(attacker, dtype=bool) | np.asarray(invalid, dtype=bool))
    sup = lost & ~w & ~a & np.asarray(superseded, dtype=bool)
    rest = lost & ~w & ~a & ~sup
    ch = rest & (np.zeros(len(lost), dtype=bool) if channel_lost is None else np.asarray(channel_lost, dtype=bool))
    return np.array([a.sum(), ch.sum(), np.count_nonzero(rest & ~ch), sup.sum(), w.sum()], dtype=np.int64)


def losses_of_tally(t: np.ndarray, late_symbols: int | None) -> dict:
    """``recorded_losses`` of a run from its ``loss_tally`` (summed over its chunks)."""
    a, ch, others, sup, w = (int(v) for v in t)
    late = late_of_rest(others, late_symbols)
    return {"attacker": a, "channel": ch, "network": others - late, "late": late + sup, "withheld": w}


# ----------------------------------------------------------------------------- parsing
def _num(key: str, v: object, **bounds: Any) -> float:
    try:
        return validate.number(v, **bounds)
    except validate.Invalid as e:
        raise ChannelError(f"[{key}] {e}") from None


def parse_link(name: str, table: object) -> LinkModel:
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
    try:
        validate.choice(dist, DISTRIBUTIONS)
    except validate.Invalid as e:
        raise ChannelError(f"[{key}.distribution] {e}") from None
    loss = _num(f"{key}.loss", table.get("loss", d.loss), lo=0, hi=1, hi_open=True)
    burst = _num(f"{key}.loss_burst", table.get("loss_burst", d.loss_burst), lo=1)
    if burst > 1 and loss > 0 and burst < loss / (1 - loss):
        raise ChannelError(f"[{key}.loss_burst] a mean loss of {loss:g} needs a mean burst length >= loss / (1 - loss)"
                           f" = {loss / (1 - loss):.4g} (P(good -> bad) would exceed 1), got {burst:g}")
    rate = _num(f"{key}.rate", table.get("rate", d.rate), lo=0, lo_open=True, allow_inf=True)
    return LinkModel(delay=delay, jitter=jitter, distribution=str(dist), loss=loss, loss_burst=burst, rate=rate)


def parse_network(table: object) -> NetworkModel:
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
           "loss_chain", "parse_link", "parse_network", "SampleChannel", "sample_channel", "withheld_pattern",
           "payload_bits", "loss_cause", "late_of_rest", "loss_counts", "loss_counts_of", "loss_tally",
           "losses_of_tally", "loss_text", "model_lost", "recorded_losses",
           "LOSS_KINDS", "RECEIVED", "ATTACKER", "CHANNEL", "LATE", "WITHHELD", "NETWORK"]
