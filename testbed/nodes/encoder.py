"""Encoder node: Algorithm 1 on x_k from the plant; symbol out, theta_k back on the ack channel.

The logic is ``testbed.protocol.EncoderProtocol`` (the simulator runs the same
object); this shell adds the clock, the grace for a late ack, publishing and
telemetry.  If x_k+1 arrives and theta_k is still unknown (a lost or late ack:
the ack is routed through the attacker, or the controller is slow or dead), it
waits ``ack_grace`` and then withholds the symbol; theta_k is recovered from any
later ack (``Ack.last_rx``).  So a missing ack costs samples, never lockstep.
"""

from __future__ import annotations

import threading
import time

from ..io import messages as msg
from ..protocol import EncoderProtocol, Send, skip_sample
from ..quantizer import Encoder
from ..runsummary import percentiles
from .common import Node, warm_publisher


class EncoderNode(Node):
    role = "encoder"

    def setup(self) -> None:
        ctx, keys = self.ctx, self.ctx.keys
        sc = self.sc
        self.enc = Encoder(self.model, sc.K, sc.quantizer, sc.flow)
        self.proto = EncoderProtocol(self.enc, ctx.n_steps)
        self.codebook = self.enc.codebook
        self.pub_symbol = self.publisher(keys.symbol_tx)
        self._cond = threading.Condition()
        self.pending_tx = 0
        self.ack_latency: list[int] = []
        self.encode_time: list[int] = []
        self.future_sensor = 0
        self.ack_grace_ns = int(self.args.ack_grace * ctx.T_ns) if self.args.ack_grace is not None \
            else max(int(0.2 * sc.run.deadline * ctx.T_ns), 50_000)
        if sc.attack.online and sc.attack.score == "E":
            ctx.telemetry.n = 1  # the greedy attacker reads E_k from it before deciding sample k
        self._subs = [
            ctx.session.declare_subscriber(keys.sensor, self.guard(self._on_sensor)),
            ctx.session.declare_subscriber(keys.ack_for_encoder(ctx.opts.ack_via_attacker),
                                           self.guard(self._on_ack)),
        ]

    def warmup(self) -> None:
        e = Encoder(self.model, self.sc.K, self.sc.quantizer, self.sc.flow)
        e.encode(self.sc.x0)
        e.ack(0)
        skip_sample(e)
        self.codebook.pack(0)

    def warm_publishers(self) -> None:
        warm_publisher(self.pub_symbol, self.codebook.pack(0))

    # ---- callbacks
    def _on_sensor(self, sample) -> None:
        ctx = self.ctx
        clock = ctx.clock
        if clock is None:
            return
        rx = clock.now()
        try:
            s = msg.Sensor.decode(sample.payload, sample.attachment)
            if len(s.x) != self.model.n:
                raise msg.MessageError(f"x has {len(s.x)} entries, plant has n = {self.model.n}")
        except msg.MessageError as e:
            self.bad_message("sensor", e)
            return
        if s.k == msg.WARMUP_K:
            return
        k = s.k
        if k > ctx.newest_k(rx):
            self.future_sensor += 1
            ctx.event("future_sensor", k=k, detail=f"x for sample {k} before its instant: rejected")
            return
        self.maybe_crash(k)
        proto = self.proto
        with self._cond:
            if proto.pending is not None and proto.next_k <= k < ctx.n_steps:
                until = rx + self.ack_grace_ns   # a late ack still resolves it
                while proto.pending is not None:
                    rem = until - clock.now()
                    if rem <= 0:
                        break
                    self._cond.wait(rem / 1e9)
            act = proto.sensor(k, s.x)
            if act is None:
                return
            if isinstance(act, Send):
                data = self.codebook.pack(act.symbol)
                tx = clock.now()
                self.pub_symbol.put(data, attachment=msg.Header(k, tx).encode())
                self.pending_tx = tx
                self.encode_time.append(tx - rx)
                tel = msg.EncoderTelemetry(k=k, sensor_tx_ns=s.stamp_ns, rx_ns=rx, tx_ns=tx, symbol=act.symbol,
                                           saturated=int(act.saturated), silent=0, E=act.E,
                                           xi=tuple(act.xi.tolist()), q=tuple(act.q.tolist()))
            else:
                if act.first:
                    ctx.event("ack_missing", k=act.pending,
                              detail=f"theta_{act.pending} unknown at sample {k}: withholding symbols "
                                     "until an ack resolves it", level=20)
                tel = msg.EncoderTelemetry(k=k, sensor_tx_ns=s.stamp_ns, rx_ns=rx, tx_ns=msg.NO_TIME,
                                           symbol=-1, saturated=0, silent=1, E=float("nan"), xi=(), q=())
        ctx.telemetry.put(tel.encode())
        if isinstance(act, Send) and act.saturated:
            ctx.event("saturation", k=k, detail=f"x_k outside Q(xi_k, E_k), E_k = {act.E:.3e}"
                      + (" (OVERFLOW sent)" if act.symbol == self.codebook.overflow else " (clipped)"),
                      level=20)

    def _on_ack(self, sample) -> None:
        rx = time.monotonic_ns()
        try:
            a = msg.Ack.decode(sample.payload, sample.attachment)
        except msg.MessageError as e:
            self.bad_message("ack", e)
            return
        if a.k == msg.WARMUP_K:
            return
        proto = self.proto
        with self._cond:
            p, silent = proto.pending, len(proto.silent)
            what = proto.ack(a.k, a.theta, a.last_rx)
            if what == "resolved" and self.ctx.clock is not None:
                self.ack_latency.append(rx - self.ctx.clock.t0_mono_ns - self.pending_tx)
            elif what == "resync":
                self.ctx.event("ack_resync", k=p, detail=f"theta_{p} recovered from the ack of sample {a.k}; "
                                                         f"{silent} samples withheld", level=20)
            self._cond.notify_all()

    def run(self) -> None:
        self.wait_end()

    def summary(self) -> dict:
        d = self.proto.counters()
        d.update({"malformed": self.malformed, "future_sensor": self.future_sensor, "ack_grace_us": self.ack_grace_ns / 1e3,
                  "encode_us": percentiles(self.encode_time), "ack_rtt_us": percentiles(self.ack_latency)})
        return d
