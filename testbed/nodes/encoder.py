"""Encoder node: Algorithm 1 on x_k from the plant; symbol out, theta_k back on the ack channel.

Lockstep with the decoder rests only on symbols and acks.  The encoder applies
the update rules (xi), (E) for sample k when it learns theta_k.  If x_k+1 arrives
and theta_k is still unknown (a lost or late ack: the ack is routed through the
attacker, or the controller is slow or dead), it waits ``ack_grace`` and then
sends *nothing* for k+1 and for every later sample until theta_k is known: the
decoder, receiving nothing, sets theta = 1 for those samples, which the encoder
can then replay without asking.  theta_k itself is recovered from any later ack
(``Ack.last_rx``).  So a missing ack costs samples, never lockstep.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from ..io import messages as msg
from ..quantizer import Encoder
from ..runsummary import percentiles
from .common import Node, warm_publisher


def skip_sample(enc: Encoder) -> None:
    """theta_k = 1 for a sample whose symbol was never sent (the decoder cannot have it).

    Rules (xi), (E) with theta_k = 1 depend on neither x_k nor the symbol.
    """
    enc.encode(enc.xi)
    enc.ack(1)


class EncoderNode(Node):
    role = "encoder"

    def setup(self) -> None:
        ctx, keys = self.ctx, self.ctx.keys
        sc = self.sc
        self.enc = Encoder(self.plant, sc.K, sc.quantizer, sc.flow)
        self.codebook = self.enc.codebook
        self.pub_symbol = self.publisher(keys.symbol_tx)
        self._cond = threading.Condition()
        self.next_k = 0            # next sample index expected from the plant
        self.pending: int | None = None   # sample sent whose theta is unknown
        self.pending_tx = 0
        self.silent: list[int] = []       # samples withheld while ``pending`` is unresolved
        self.n_silent = 0
        self.n_sent = 0
        self.stale_sensor = 0
        self.stale_acks = 0
        self.ack_latency: list[int] = []
        self.encode_time: list[int] = []
        self.desync_episodes = 0
        self.inconsistent_acks = 0
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
        e = Encoder(self.plant, self.sc.K, self.sc.quantizer, self.sc.flow)
        e.encode(self.sc.x0)
        e.ack(0)
        skip_sample(e)
        self.codebook.pack(0)

    def warm_publishers(self) -> None:
        warm_publisher(self.pub_symbol, self.codebook.pack(0))

    # ---- helpers (hold self._cond)
    def _mark_silent(self, j: int) -> None:
        if self.pending is None:
            skip_sample(self.enc)
        else:
            self.silent.append(j)

    def _resolve(self, theta: int) -> None:
        self.enc.ack(theta)
        self.pending = None
        for _ in self.silent:
            skip_sample(self.enc)
        self.silent.clear()
        self._cond.notify_all()

    # ---- callbacks
    def _on_sensor(self, sample) -> None:
        ctx = self.ctx
        clock = ctx.clock
        if clock is None:
            return
        rx = clock.now()
        try:
            s = msg.Sensor.decode(sample.payload, sample.attachment)
            if len(s.x) != self.plant.n:
                raise msg.MessageError(f"x has {len(s.x)} entries, plant has n = {self.plant.n}")
        except msg.MessageError as e:
            self.bad_message("sensor", e)
            return
        if s.k == msg.WARMUP_K:
            return
        k = s.k
        self.maybe_crash(k)
        with self._cond:
            if k < self.next_k or k >= ctx.n_steps:
                self.stale_sensor += 1
                return
            for j in range(self.next_k, k):  # sensor samples that never came: nothing was sent
                self._mark_silent(j)
                self.n_silent += 1
            self.next_k = k
            if self.pending is not None:
                until = rx + self.ack_grace_ns
                while self.pending is not None:
                    rem = until - clock.now()
                    if rem <= 0:
                        break
                    self._cond.wait(rem / 1e9)
            if self.pending is not None:
                if not self.silent:
                    self.desync_episodes += 1
                    ctx.event("ack_missing", k=self.pending,
                              detail=f"theta_{self.pending} unknown at sample {k}: withholding symbols "
                                     "until an ack resolves it", level=20)
                self.silent.append(k)
                self.n_silent += 1
                self.next_k = k + 1
                tel = msg.EncoderTelemetry(k=k, sensor_tx_ns=s.stamp_ns, rx_ns=rx, tx_ns=msg.NO_TIME,
                                           symbol=-1, saturated=0, silent=1, E=float("nan"), xi=(), q=())
                silent = True
            else:
                enc = self.enc
                if enc.k != k:  # cannot happen by construction; say so loudly if it does
                    ctx.event("internal_desync", k=k, detail=f"encoder at sample {enc.k}, x for sample {k}")
                xi, E = enc.xi, enc.E
                i, sat = enc.encode(np.asarray(s.x))
                data = self.codebook.pack(i)
                tx = clock.now()
                self.pub_symbol.put(data, attachment=msg.Header(k, tx).encode())
                self.pending, self.pending_tx = k, tx
                self.next_k = k + 1
                self.n_sent += 1
                self.encode_time.append(tx - rx)
                tel = msg.EncoderTelemetry(k=k, sensor_tx_ns=s.stamp_ns, rx_ns=rx, tx_ns=tx, symbol=i,
                                           saturated=int(sat), silent=0, E=E, xi=tuple(xi.tolist()),
                                           q=tuple(enc.q.tolist()))
                silent = False
        ctx.telemetry.put(tel.encode())
        if not silent and tel.saturated:
            ctx.event("saturation", k=k, detail=f"x_k outside Q(xi_k, E_k), E_k = {tel.E:.3e}"
                      + (" (OVERFLOW sent)" if tel.symbol == self.codebook.overflow else " (clipped)"),
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
        with self._cond:
            p = self.pending
            if p is None:
                if a.k >= self.next_k and a.k < self.ctx.n_steps:
                    # theta for samples whose x never reached us: the decoder lost them too
                    if a.theta != 1:
                        self.inconsistent_acks += 1
                    for j in range(self.next_k, a.k + 1):
                        skip_sample(self.enc)
                        self.n_silent += 1
                    self.next_k = a.k + 1
                else:
                    self.stale_acks += 1
                return
            if a.k == p:
                theta = a.theta
                if self.ctx.clock is not None:
                    self.ack_latency.append(rx - self.ctx.clock.t0_mono_ns - self.pending_tx)
            elif a.k > p:
                theta = 0 if a.last_rx == p else 1
                self.ctx.event("ack_resync", k=p, detail=f"theta_{p} = {theta} recovered from the ack of "
                                                         f"sample {a.k}; {len(self.silent)} samples withheld",
                               level=20)
            else:
                self.stale_acks += 1
                return
            self._resolve(theta)

    def run(self) -> None:
        self.wait_end()

    def summary(self) -> dict:
        return {"sent": self.n_sent, "withheld": self.n_silent, "saturations": self.enc.saturations,
                "desync_episodes": self.desync_episodes, "stale_sensor": self.stale_sensor,
                "stale_acks": self.stale_acks, "inconsistent_acks": self.inconsistent_acks,
                "malformed": self.malformed, "ack_grace_us": self.ack_grace_ns / 1e3,
                "encode_us": percentiles(self.encode_time), "ack_rtt_us": percentiles(self.ack_latency)}
