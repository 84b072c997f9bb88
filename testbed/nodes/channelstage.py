"""The live channel stage: a link's ``[network.<link>]`` model applied at its receiving end.

A node's handler of one control-path stream is wrapped (``Node.subscribe(..., link=...)``) only
when the scenario has a non-ideal model for that link, so a run without ``[network]`` does no
extra work. The links and where they are received:

- ``sensor``: the encoder receiving x_k (plant and encoder in separate processes);
- ``symbol``: the controller receiving the symbol (after the attacker);
- ``actuation``: the plant receiving u_k;
- ``ack``: the encoder receiving theta_k (the actuation message that carries it, or the ack).

With ``--colocate encoder`` the sensor and ack links do not cross the network: their losses are
applied where the plant hands x_k and the ack over (``InProcessLink``).

Message k (the header's sample index) is dropped iff ``channel.draws(model, link, n, bits).lost[k]``,
the same draws the simulator makes with the same seed (``bits``: the payload a finite ``rate``
charges, ``channel.payload_bits``); otherwise it is handed to the node at
its send time (the header's stamp, run clock) plus ``delay[k]``, or at once if the real network
took longer (the realized delay is then max(real, model)). Held messages are delivered in
order of their due times by one thread per stage. The realized drops and delays go into the
node's summary (``channel``: per link ``lost_at``, ``delay_s`` as [k, model, realized] rows, the
first ``MAX_ROWS`` of them, the rest counted: ``delay_rows_dropped``); each drop is also an event
``channel_lost`` (rate-limited like every event).  The draws are kept as numpy arrays (9 bytes a
sample, allocated at the start), so a long run does not grow the node.
"""

from __future__ import annotations

import heapq
import itertools
import math
import threading
from collections.abc import Callable
from typing import Any

from ..loop import channel
from ..wire import messages as msg


def stage_for(node: Any, link: str, fn: Callable[[Any], Any]) -> Callable[[Any], Any]:
    """``fn`` wrapped in the link's channel stage, or ``fn`` itself when the link is ideal (or absent)."""
    net = getattr(node.sc, "network", None)
    if net is None or net.link(link).ideal:
        return fn
    return ChannelStage(node, link, net, fn)


def _bits(node: Any, link: str, model: channel.NetworkModel) -> int:
    """The payload bits a finite ``rate`` charges for one message (``channel.payload_bits``, as the simulator)."""
    if not math.isfinite(model.link(link).rate):
        return 0
    sc, plant = node.sc, node.model
    nbytes = sc.make_method().codebook(plant.n, sc.quantizer).nbytes if link == "symbol" else 0
    return channel.payload_bits(link, plant.n, plant.m, nbytes)


class ChannelStage:
    #: rows of realized delays kept for the node's summary (the run's first ones; the rest are counted)
    MAX_ROWS = 100_000

    def __init__(self, node: Any, link: str, model: channel.NetworkModel, fn: Callable[[Any], Any]) -> None:
        self.node = node
        self.link = link
        self.fn = fn
        n = node.ctx.n_steps + 2  # prefix-stable: a few samples more than the run has change nothing
        d = channel.draws(model, link, n, _bits(node, link, model))
        self.lost = d.lost                     # numpy: a byte a sample, not a Python object
        self.delay_s = d.delay
        self.lost_at: list[int] = []
        self.delays: list[list] = []           # [k, model delay s, realized delay s], the first MAX_ROWS
        self.delay_rows_dropped = 0
        self._heap: list = []
        self._seq = itertools.count()
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None

    def __call__(self, sample: Any) -> Any:
        ctx = self.node.ctx
        try:
            h = msg.Header.decode(sample.attachment)
        except msg.MessageError:
            return self.fn(sample)  # the node's own handler counts a malformed message
        k = h.k
        if h.warmup or not 0 <= k < len(self.lost) or ctx.clock is None:
            return self.fn(sample)
        if self.lost[k]:
            self.lost_at.append(k)
            ctx.event("channel_lost", k=k, detail=f"{self.link}: lost by the channel model", level=20)
            return None
        due = h.stamp_ns + int(round(float(self.delay_s[k]) * 1e9))
        now = ctx.clock.now()
        if due <= now:
            self._delayed(k, (now - h.stamp_ns) / 1e9)
            return self.fn(sample)
        with self._cond:
            heapq.heappush(self._heap, (due, next(self._seq), k, h.stamp_ns, sample))
            if self._thread is None:
                self._thread = threading.Thread(target=self._deliver, daemon=True, name=f"channel-{self.link}")
                self._thread.start()
            self._cond.notify()
        return None

    def _deliver(self) -> None:
        ctx = self.node.ctx
        clock = ctx.clock
        while not ctx.stop.is_set():
            with self._cond:
                if not self._heap:
                    self._cond.wait(0.05)
                    continue
                due = self._heap[0][0]
                rem = due - clock.now()
                if rem > 0:
                    self._cond.wait(min(rem / 1e9, 0.05))
                    continue
                _, _, k, stamp, sample = heapq.heappop(self._heap)
            self._delayed(k, (clock.now() - stamp) / 1e9)
            self.fn(sample)

    def _delayed(self, k: int, realized_s: float) -> None:
        if len(self.delays) < self.MAX_ROWS:
            self.delays.append([k, float(self.delay_s[k]), realized_s])
        else:
            self.delay_rows_dropped += 1

    def summary(self) -> dict:
        out = {"lost_at": list(self.lost_at), "delay_s": [list(r) for r in self.delays]}
        if self.delay_rows_dropped:
            out["delay_rows_dropped"] = self.delay_rows_dropped
        return out


class InProcessLink:
    """A link that does not cross the network (``--colocate encoder``: x_k and the ack handed over inside
    the plant's process): the model's losses alone, as the simulator applies them (a delay has nothing
    to hold here: the ack rides on the actuation message, which its own link delays)."""

    def __init__(self, node: Any, link: str, model: channel.NetworkModel) -> None:
        self.node = node
        self.link = link
        self.lost = channel.draws(model, link, node.ctx.n_steps + 2).lost
        self.lost_at: list[int] = []

    def drops(self, k: int) -> bool:
        """Whether the channel loses sample k's message (recorded when it does)."""
        if 0 <= k < len(self.lost) and self.lost[k]:
            self.lost_at.append(k)
            self.node.ctx.event("channel_lost", k=k, detail=f"{self.link}: lost by the channel model", level=20)
            return True
        return False

    def summary(self) -> dict:
        return {"lost_at": list(self.lost_at), "delay_s": []}


def in_process_links(guest: Any) -> dict[str, InProcessLink]:
    """The colocated encoder's ``sensor`` and ``ack`` links that lose messages (registered as its stages)."""
    net = getattr(guest.sc, "network", None)
    out = {}
    for link in ("sensor", "ack"):
        if net is not None and net.link(link).loss > 0:
            out[link] = guest.channel_stages[link] = InProcessLink(guest, link, net)
    return out
