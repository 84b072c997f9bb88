"""Controller node: Algorithm 2 and control law (2); u_k to the plant, theta_k to the encoder.

Samples are decided strictly in order k = 0, 1, ...  Sample k is decided when its
symbol arrives (theta_k = 0, or 1 for a malformed / out-of-range payload) or, if
nothing has arrived by the loss deadline t_k + ``loss_fraction`` * d * T (d =
``[run] deadline``, measured on the shared run clock), with theta_k = 1: the
attacker dropped it, or the encoder or attacker is dead.  The loss deadline falls
before the plant's own deadline t_k + d T, so u_k = 0 still reaches it in time.
A symbol that arrives after its sample was decided is counted as late and ignored.
"""

from __future__ import annotations

import threading

from ..io import messages as msg
from ..quantizer import Decoder, InvalidSymbol
from ..runsummary import percentiles
from .common import Node, warm_publisher

CT = msg.ControllerTelemetry


class ControllerNode(Node):
    role = "controller"

    def setup(self) -> None:
        ctx, keys, sc = self.ctx, self.ctx.keys, self.sc
        self.dec = Decoder(self.plant, sc.K, sc.quantizer, sc.flow)
        self.codebook = self.dec.codebook
        self.pub_act = self.publisher(keys.actuation)
        self.pub_ack = self.publisher(keys.ack_tx)
        self._cond = threading.Condition()
        self.next_k = 0
        self.last_rx = -1
        self.received = 0
        self.lost_deadline = 0
        self.invalid = 0
        self.late = 0
        self.superseded = 0
        self.decode_time: list[int] = []
        self.net_latency: list[int] = []
        frac = self.args.loss_fraction
        self.loss_ns = int(frac * sc.run.deadline * ctx.T_ns)
        self._sub = ctx.session.declare_subscriber(keys.symbol_rx, self.guard(self._on_symbol))
        ctx.on_peer(self._on_peer)

    def warmup(self) -> None:
        d = Decoder(self.plant, self.sc.K, self.sc.quantizer, self.sc.flow)
        d.step(0)
        d.step(None)
        if self.codebook.resilient:
            d.step(self.codebook.overflow)

    def warm_publishers(self) -> None:
        m = self.plant.m
        warm_publisher(self.pub_act, msg.Actuation(0, 0, 1, (0.0,) * m).encode()[0])
        warm_publisher(self.pub_ack, msg.Ack(0, 0, 1, -1).encode()[0])

    def _on_peer(self, node: str, alive: bool) -> None:
        if self.ctx.start_msg is None or self.ctx.stop.is_set():
            return
        if node in ("encoder", "attacker") and not alive:
            with self._cond:  # _decide holds it between publishing u_{N-1} and advancing next_k
                k = self.next_k
            if k >= self.ctx.n_steps:
                return  # every sample decided: a peer leaving now is the normal end of the run
            self.ctx.event("peer_lost", k=k,
                           detail=f"{node} liveliness lost: its samples will be treated as losses")
        elif node == "plant" and not alive:
            self.ctx.request_stop("plant lost")

    # ---- one sample (hold self._cond)
    def _decide(self, k: int, symbol: int | None, reason: int, rx: int, stamp: int) -> None:
        self.maybe_crash(k)
        dec = self.dec
        xi, E = dec.xi, dec.E
        u, q, theta = dec.step(symbol)
        if theta == 0:
            self.last_rx = k
        clock = self.ctx.clock
        tx = clock.now()
        ut = tuple(u.tolist())
        p, a = msg.Actuation(k, tx, theta, ut).encode()
        self.pub_act.put(p, attachment=a)
        p, a = msg.Ack(k, tx, theta, self.last_rx).encode()
        self.pub_ack.put(p, attachment=a)
        self.next_k = k + 1
        self._cond.notify_all()
        if rx != msg.NO_TIME:
            self.decode_time.append(tx - rx)
        self.ctx.telemetry.put(CT(k=k, sym_stamp_ns=stamp, rx_ns=rx, tx_ns=tx,
                                  symbol=-1 if symbol is None else int(symbol), theta=theta, reason=reason,
                                  E=E, xi=tuple(xi.tolist()), q=tuple(q.tolist()), u=ut).encode())

    def _on_symbol(self, sample) -> None:
        ctx = self.ctx
        clock = ctx.clock
        if clock is None:
            return
        rx = clock.now()
        h = self.rx_header(sample, "symbol header")
        if h is None:
            return
        k = h.k
        with self._cond:
            if k < self.next_k or k >= ctx.n_steps:
                self.late += 1
                ctx.event("late_symbol", k=k, detail=f"arrived {(rx - k * ctx.T_ns) / 1e3:.0f} us after "
                                                     f"t_k, sample already decided (theta = 1)", level=20)
                return
            while self.next_k < k:  # a later sample arrived first: the earlier ones are lost
                self.superseded += 1
                self._decide(self.next_k, None, CT.SUPERSEDED, msg.NO_TIME, msg.NO_TIME)
            try:
                sym = self.codebook.unpack(sample.payload.to_bytes())
            except InvalidSymbol as e:
                self.invalid += 1
                ctx.event("invalid_payload", k=k, detail=f"{e}: treated as a loss (theta = 1)")
                self._decide(k, None, CT.INVALID, rx, h.stamp_ns)
                return
            self.received += 1
            self.net_latency.append(rx - h.stamp_ns)
            self._decide(k, sym, CT.RECEIVED, rx, h.stamp_ns)

    # ---- the loss deadlines
    def run(self) -> None:
        ctx = self.ctx
        clock = ctx.clock
        N, T_ns = ctx.n_steps, ctx.T_ns
        while not ctx.stop.is_set():
            with self._cond:
                k = self.next_k
                if k >= N:
                    break
                rem = k * T_ns + self.loss_ns - clock.now()
                if rem > 0:
                    self._cond.wait(min(rem / 1e9, 0.05))
                    continue
                self.lost_deadline += 1
                self._decide(k, None, CT.DEADLINE, msg.NO_TIME, msg.NO_TIME)
        self.wait_end()

    def summary(self) -> dict:
        return {"received": self.received, "lost_deadline": self.lost_deadline, "invalid": self.invalid,
                "late": self.late, "superseded": self.superseded, "malformed": self.malformed,
                "overflows": self.dec.overflows, "decided": self.next_k, "loss_deadline_us": self.loss_ns / 1e3,
                "decode_us": percentiles(self.decode_time), "uplink_us": percentiles(self.net_latency)}

