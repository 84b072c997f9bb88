"""Controller node: Algorithm 2 and control law (2); u_k to the plant, theta_k to the encoder.

The logic is ``testbed.loop.protocol.ControllerProtocol`` (the simulator runs the same
object): samples are decided strictly in order k = 0, 1, ... Sample k is decided
when its symbol arrives (theta_k = 0, or 1 for a malformed / out-of-range
payload) or, if nothing has arrived by the loss deadline t_k + ``loss_fraction`` *
d * T (d = ``[run] deadline``, measured on the shared run clock), with theta_k = 1:
the attacker dropped it, or the encoder or attacker is dead.  The loss deadline
falls before the plant's own deadline t_k + d T, so u_k = 0 still reaches it in
time.  A symbol that arrives after its sample was decided is late and ignored; one
whose header names a sample whose instant t_k has not come yet on the run clock
cannot be genuine and is rejected (counted, logged).
"""

from __future__ import annotations

import threading
from typing import TYPE_CHECKING, Any

from ..loop.protocol import ControllerProtocol, Decision, MethodFault
from ..record.timingstats import Timings, percentiles
from ..wire import messages as msg
from .base import Node
from .context import warm_publisher

if TYPE_CHECKING:
    from plants.base import Plant

    from ..scenario import Scenario

CT = msg.ControllerTelemetry


def warm_kernels(sc: Scenario, model: Plant) -> None:
    """Load the decoder's compiled kernels: the node's warm-up, and the launcher's before it forks."""
    d = sc.make_method().make_decoder(model, sc.K, sc.quantizer, sc.flow)
    d.step(None)
    d.step(0 if hasattr(d.codebook, "M") else None)
    if d.codebook.resilient:
        d.step(d.codebook.overflow)


class ControllerNode(Node):
    role = "controller"

    def setup(self) -> None:
        ctx, keys, sc = self.ctx, self.ctx.keys, self.sc
        self.dec = sc.make_method().make_decoder(self.model, sc.K, sc.quantizer, sc.flow)
        # u_k goes out before the decoder's prediction for k+1 is computed (the same numbers)
        self.proto = ControllerProtocol(self.dec, ctx.n_steps, defer_update=True)
        self.codebook = self.dec.codebook
        self.pub_act = self.publisher(keys.actuation)
        # the ideal ack rides on the actuation message; a message of its own only on request or via the attacker
        self.pub_ack = None if ctx.opts.ack_on_actuation else self.publisher(keys.ack_tx)
        self._cond = threading.Condition()
        self.decode_time = Timings()  # fixed memory however long the run
        self.net_latency = Timings()  # fixed memory however long the run
        self.loss_ns = int(sc.timing_params[4])  # t_k + loss_fraction d T
        self._sub = self.subscribe(keys.symbol_rx, self.stamped(self._on_symbol, "symbol header"), primary=True,
                                   link="symbol")
        ctx.on_peer(self._on_peer)

    @property
    def next_k(self) -> int:
        return self.proto.next_k

    def warmup(self) -> None:
        warm_kernels(self.sc, self.model)

    def warm_publishers(self) -> None:
        m = self.model.m
        warm_publisher(self.pub_act, msg.Actuation(0, 0, 1, (0.0,) * m).encode()[0])
        if self.pub_ack is not None:
            warm_publisher(self.pub_ack, msg.Ack(0, 0, 1, -1).encode()[0])

    def _on_peer(self, node: str, alive: bool) -> None:
        if self.ctx.start_msg is None or self.ctx.stop.is_set():
            return
        if node in ("encoder", "attacker") and not alive:
            with self._cond:  # _publish holds it between publishing u_{N-1} and advancing next_k
                k = self.proto.next_k
            if k >= self.ctx.n_steps:
                return  # every sample decided: a peer leaving now is the normal end of the run
            self.ctx.event("peer_lost", k=k,
                           detail=f"{node} liveliness lost: its samples will be treated as losses")
        elif node == "plant" and not alive:
            self.ctx.request_stop("plant lost")

    # ---- one decision (hold self._cond)
    def _publish(self, d: Decision, rx: int, stamp: int) -> None:
        self.maybe_crash(d.k)
        clock = self.ctx.clock
        assert clock is not None  # set by the Start before any sample is handled
        tx = clock.now()
        ut = tuple(d.u.tolist())
        p, a = msg.Actuation(d.k, tx, d.theta, ut, d.last_rx).encode()
        self.pub_act.put(p, attachment=a)
        if self.pub_ack is not None:
            p, a = msg.Ack(d.k, tx, d.theta, d.last_rx).encode()
            self.pub_ack.put(p, attachment=a)
        self._cond.notify_all()
        if rx != msg.NO_TIME:
            self.decode_time.append(tx - rx)
        self.ctx.telemetry.put(CT(k=d.k, sym_stamp_ns=stamp, rx_ns=rx, tx_ns=tx, symbol=d.symbol, theta=d.theta,
                                  reason=d.reason, E=d.E, xi=tuple(d.xi.tolist()), q=tuple(d.q.tolist()),
                                  u=ut).encode())

    def _on_symbol(self, sample: Any, h: msg.Header, rx: int) -> int | None:
        ctx = self.ctx
        k = h.k
        proto = self.proto
        with self._cond:
            late, future, invalid = proto.late, proto.future, proto.invalid
            payload = sample.payload.to_bytes()
            decs = self.method_call(lambda: proto.next_k, proto.symbol, k, payload, newest_k=ctx.newest_k(rx))
            if proto.late > late:
                ctx.event("late_symbol", k=k, detail=f"arrived {(rx - k * ctx.T_ns) / 1e3:.0f} us after "
                                                     f"t_k, sample already decided (theta = 1)", level=20)
            elif proto.future > future:
                ctx.event("future_symbol", k=k, detail=f"header names sample {k}, whose instant is "
                                                       f"{(k * ctx.T_ns - rx) / 1e6:.1f} ms ahead: rejected")
            for d in decs:
                if d.reason == CT.RECEIVED:
                    self.net_latency.append(rx - h.stamp_ns)
                    self._publish(d, rx, h.stamp_ns)
                elif d.k == k:  # an invalid payload
                    self._publish(d, rx, h.stamp_ns)
                else:
                    self._publish(d, msg.NO_TIME, msg.NO_TIME)
            self._settle()  # the decoder's prediction for the next sample, after u_k went out
            if proto.invalid > invalid:
                ctx.event("invalid_payload", k=k, detail="not a code of the codebook: treated as a loss (theta = 1)")
        return k

    def _settle(self) -> None:
        """The decoder's deferred update of the last decided sample (a raise there is that sample's fault)."""
        proto = self.proto
        self.method_call(lambda: proto.next_k - 1, proto.settle)

    # ---- the loss deadlines
    def run(self) -> None:
        ctx = self.ctx
        clock = ctx.clock
        assert clock is not None  # set by the Start before the loop runs
        N, T_ns = ctx.n_steps, ctx.T_ns
        proto = self.proto
        try:
            while not ctx.stop.is_set() and self.method_fault is None:
                with self._cond:
                    k = proto.next_k
                    if k >= N:
                        break
                    rem = k * T_ns + self.loss_ns - clock.now()
                    if rem > 0:
                        self._cond.wait(min(rem / 1e9, 0.05))
                        continue
                    d = self.method_call(k, proto.deadline, k)
                    if d is not None:
                        self._publish(d, msg.NO_TIME, msg.NO_TIME)
                    self._settle()
            if self.method_fault is None:
                with self._cond:
                    self._settle()
        except MethodFault as e:  # the method raised: the run ends at that sample (the launcher stops it)
            self.fail(e)
        self.wait_end()

    def summary(self) -> dict:
        d = self.proto.counters()
        d.update({"malformed": self.malformed, "loss_deadline_us": self.loss_ns / 1e3,
                  "decode_us": percentiles(self.decode_time), "uplink_us": percentiles(self.net_latency),
                  "ack": "separate" if self.pub_ack is not None and not self.ctx.opts.ack_via_attacker
                  else ("via attacker" if self.ctx.opts.ack_via_attacker else "on the actuation")})
        d.update(self.rx_summary())
        return d
