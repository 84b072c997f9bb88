"""The node base class: ``setup`` (declare), ``warmup`` (JIT), ``run`` (after the start), ``summary``."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

from ..wire import messages as msg
from ..wire import transport
from .context import NodeContext
from .inlet import Inlet
from .options import NodeConfig

if TYPE_CHECKING:
    from ..loop.protocol import MethodFault

T = TypeVar("T")

log = logging.getLogger("testbed.nodes")


# ============================================================================ node base
class Node:
    """A node shell: ``setup`` (declare), ``warmup`` (JIT), ``run`` (after the start), ``summary``."""

    role = ""

    def __init__(self, ctx: NodeContext, cfg: NodeConfig):
        self.ctx = ctx
        self.cfg = cfg
        self.sc = ctx.sc
        self.model = ctx.sc.make_model()  # the predictions' model (n, m); the plant node has the true plant
        self.crash_at = cfg.crash_at
        self.malformed = 0
        self.error: BaseException | None = None
        self.method_fault: MethodFault | None = None  # the method's end raised (``protocol.MethodFault``): the node goes passive
        self._pubs: list = []
        self.rx_mode = cfg.rx or "thread"
        spin_us = cfg.rx_spin_us
        self.rx_spin_ns = int(spin_us * 1e3) if spin_us is not None else min(1_000_000, ctx.T_ns // 20)
        self.inlet: Inlet | None = None
        self.channel_stages: dict = {}  # link -> its ChannelStage ([network]: ``channelstage``)

    # -- to override
    def setup(self) -> None: ...

    def declare_alive(self) -> None:
        self.ctx.declare_alive()

    def declare_ready(self) -> None:
        self.ctx.declare_ready()

    def warmup(self) -> None: ...

    def warm_publishers(self) -> None: ...

    def run(self) -> None:
        self.wait_end()

    def summary(self) -> dict:
        return {}

    # -- helpers
    def publisher(self, key: str, control: bool = True) -> Any:
        qos = transport.control_qos() if control else transport.telemetry_qos()
        return self.ctx.session.declare_publisher(key, **qos)

    def guard(self, fn: Callable[[Any], Any]) -> Callable[[Any], Any]:
        """Wrap a Zenoh callback: an exception stops the node (exit code 1) instead of vanishing."""

        def wrapped(sample: Any) -> Any:
            if self.error is not None or self.method_fault is not None:
                return None
            try:
                return fn(sample)
            except Exception as e:  # noqa: BLE001 - a handler's failure fails its node, not the Zenoh callback thread
                self.fail(e)
                return None

        return wrapped

    def subscribe(self, key: str, fn: Callable[[Any], int | None], *, blocking: bool = False, primary: bool = False,
                  thread: bool = True, link: str | None = None) -> Any:
        """Subscribe ``fn(sample)`` (guarded) the way the node's ``--rx`` mode says.

        ``thread``: zenoh-python's callback thread runs it (one thread per subscriber, woken
        for each sample).  ``direct``: Zenoh's own receive thread runs it, one thread wake-up
        less per message; only for a handler that never waits (``blocking=False``): one that
        waits for another message there would wait for ever.  ``spin``: as ``direct``, and the
        node's primary input (``primary``, the one on the loop's path) is an ``Inlet``: its
        own thread handles it and spins just before it is due (``thread=False``: the node's
        loop calls ``Inlet.spin`` itself).  ``fn`` returns the sample index of a control
        message (the inlet learns when it is due) or None.  ``link``: the channel link this stream
        is received on; with a non-ideal ``[network.<link>]`` model, its channel stage drops and
        holds the messages (``testbed.nodes.channelstage``); without one, nothing is added.
        """
        import zenoh

        h = self.guard(fn)
        if link is not None and self.sc.network is not None:
            from .channelstage import stage_for

            stage = stage_for(self, link, h)
            if stage is not h:
                self.channel_stages[link] = stage
                h = self.guard(stage)
        if self.rx_mode == "spin" and primary:
            self.inlet = Inlet(self, key, h, budget_ns=self.rx_spin_ns, thread=thread)
            return self.inlet.sub
        if self.rx_mode != "thread" and not blocking:
            return self.ctx.session.declare_subscriber(key, zenoh.handlers.Callback(h, indirect=False))
        return self.ctx.session.declare_subscriber(key, h)

    def channel_summary(self) -> dict:
        """The realized channel drops and delays of each link this node receives (``channel``), if any."""
        return {"channel": {k: s.summary() for k, s in self.channel_stages.items()}} if self.channel_stages else {}

    def rx_summary(self) -> dict:
        d: dict = {"rx": self.rx_mode}
        if self.inlet is not None:
            d["rx_inlet"] = self.inlet.stats()
        return d

    def method_call(self, k: int | Callable[[], int], fn: Callable[..., T], *args: Any, **kw: Any) -> T:
        """``fn(*args, **kw)``, a call into the method's end through the protocol; what it raises becomes a
        ``MethodFault`` at sample ``k`` (an int, or a function giving it after the raise: the sample
        ``testbed simulate`` names)."""
        try:
            return fn(*args, **kw)
        except Exception as e:  # a method's end raised: a method fault, not a crash of the node
            from ..loop.protocol import MethodFault  # here, not at the top: the attacker node loads no numba

            if isinstance(e, MethodFault):
                raise
            at = k() if callable(k) else k
            raise MethodFault(self.sc.make_method().display_name(), at, e, self.role) from e

    def fail(self, e: BaseException) -> None:
        from ..loop.protocol import MethodFault  # here, not at the top: the attacker node loads no numba

        if isinstance(e, MethodFault):  # the run ends there: one event, then nothing more from this node
            if self.method_fault is None and self.error is None:
                self.method_fault = e
                log.error("%s: %s", self.role, e.line)
                self.ctx.event("method_fault", k=e.k, detail=e.line, level=logging.ERROR)
            return
        if self.error is None:
            self.error = e
            import traceback

            tb = "".join(traceback.format_exception(e)).rstrip()
            log.error("%s crashed:\n%s", self.role, tb)
            self.ctx.event("crash", detail=f"{type(e).__name__}: {e}", level=logging.ERROR)
            self.ctx.request_stop(f"crash: {type(e).__name__}: {e}")

    def maybe_crash(self, k: int) -> None:
        """Fault injection (``--crash-at K``): raise at sample K."""
        if self.crash_at is not None and k == self.crash_at:
            raise RuntimeError(f"injected crash of the {self.role} at sample {k}")

    def bad_message(self, what: str, e: Exception, k: int = -1) -> None:
        self.malformed += 1
        if self.malformed <= 20:
            self.ctx.event("malformed", k=k, detail=f"{what}: {e}")

    def rx_header(self, sample: Any, what: str) -> msg.Header | None:
        """The sample's header, or None for a warm-up put or a malformed header (counted)."""
        try:
            h = msg.Header.decode(sample.attachment)
        except msg.MessageError as e:
            self.bad_message(what, e)
            return None
        return None if h.warmup else h

    def stamped(self, fn: Callable[[Any, msg.Header, int], int | None], what: str) -> Callable[[Any], int | None]:
        """A subscriber callback that calls ``fn(sample, header, rx)``, ``rx`` the receive time on the run
        clock; it ignores a warm-up put, a malformed header (counted as ``what``) and a sample that arrives
        before the run clock (no Start within ``ctx.wait_clock``'s wait)."""

        def handler(sample: Any) -> int | None:
            h = self.rx_header(sample, what)
            if h is None:
                return None
            clock = self.ctx.wait_clock()
            if clock is None:
                return None
            return fn(sample, h, clock.now())

        return handler

    def wait_end(self, grace_s: float = 5.0) -> None:
        """Until a stop arrives, or the run's end plus ``grace_s`` (no plant to say so)."""
        ctx = self.ctx
        while not ctx.stop.is_set():
            if ctx.clock is not None and ctx.now() > ctx.end_ns + int(grace_s * 1e9):
                ctx.request_stop("run over (no stop message)")
                break
            ctx.stop.wait(0.05)
