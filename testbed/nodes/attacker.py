"""Attacker node: a DoS proxy on the encoder-to-controller channel.

Forwards each symbol unchanged (payload and header) or drops it.  The decision
is the core's ``attackers.Gate``: the scenario's offline schedule at t_k = k T
(every generator) or the online greedy attacker, which needs a score per sample:
``||x_k||_inf`` read from the plant's sensor messages (it eavesdrops on that
link) or ``E_k`` from the encoder's telemetry.  Decisions are taken once per
sample, in order, so the greedy budget evolves as in the simulator.

With ``--ack-via-attacker`` the acks pass through too; the ack of sample k is
dropped iff sample k was (the jammer is on for the whole exchange of that slot).

Fault injection for tests and demos: ``--corrupt K[:range|:length],...`` replaces
the payload of sample K by an out-of-range code or a payload of the wrong length.
"""

from __future__ import annotations

import math
import threading

import numpy as np

from attackers.gate import Gate

from ..loop.params import corrupt_payload
from ..wire import messages as msg
from .base import Node
from .context import warm_publisher
from .options import attack_horizon


def parse_corrupt(spec: str | None) -> dict[int, str]:
    out: dict[int, str] = {}
    if not spec:
        return out
    for part in spec.split(","):
        part = part.strip()
        if not part:
            continue
        k, _, kind = part.partition(":")
        kind = kind or "range"
        if kind not in ("range", "length"):
            raise ValueError(f"--corrupt: kind must be 'range' or 'length', got {kind!r}")
        try:
            out[int(k)] = kind
        except ValueError:
            raise ValueError(f"--corrupt: {k!r} is not a sample index") from None
    return out


class AttackerNode(Node):
    role = "attacker"

    def setup(self) -> None:
        ctx, keys, sc = self.ctx, self.ctx.keys, self.sc
        a = sc.attack
        if a.online:
            from attackers.greedy import (
                GreedyAttacker,  # numba: only for the online attacker
            )

            gp = a.greedy_params()
            self.gate = Gate(GreedyAttacker(gp[0], gp[1], gp[2], gp[3], sc.T, threshold=gp[4]))
            self.score_kind = a.score
        else:
            self.gate = Gate(a.schedule(sc.T, attack_horizon(sc)), sc.T)
            self.score_kind = None
        self.codebook = sc.make_method().codebook(self.model.n, sc.quantizer)
        self.corrupt = parse_corrupt(self.cfg.corrupt)
        self._lock = threading.Lock()
        self._score_cond = threading.Condition()
        self.scores: dict[int, float] = {}
        self.decisions = bytearray(sc.n_steps)  # 1 = drop sample k: one byte a sample, allocated once
        self.next_decide = 0
        self.dropped = 0
        self.forwarded = 0
        self.corrupted = 0
        self.acks_dropped = 0
        self.acks_forwarded = 0
        self.missing_scores = 0
        self.future_symbols = 0
        self.score_wait_ns = max(int(0.25 * sc.run.deadline * ctx.T_ns), 100_000)
        self.pub_fwd = self.publisher(keys.symbol_rx)
        self.pub_status = ctx.session.declare_publisher(keys.attacker_status)
        # the online (greedy) gate may wait for a score while it holds its lock: those handlers must not
        # run on Zenoh's own receive thread, which delivers the score
        online = self.gate.is_online
        self._subs = [self.subscribe(keys.symbol_tx, self.stamped(self._on_symbol, "symbol header (dropped)"),
                                     blocking=online, primary=True)]
        if ctx.opts.ack_via_attacker:
            self.pub_ack = self.publisher(keys.ack_rx)
            self._subs.append(self.subscribe(keys.ack_tx, self._on_ack, blocking=online))
        if self.score_kind == "state":
            self._subs.append(self.subscribe(keys.sensor, self._on_sensor))
        elif self.score_kind == "E":
            self._subs.append(self.subscribe(keys.telemetry("encoder"), self._on_enc_telemetry))
        self._last_on = False

    def warmup(self) -> None:
        if self.gate.is_online:
            from attackers.greedy import GreedyAttacker

            GreedyAttacker(1.0, 0.0, 0.0, 0.0, self.sc.T).decide(0, 0.0)

    def warm_publishers(self) -> None:
        warm_publisher(self.pub_fwd, b"\0" * self.codebook.nbytes)
        if self.ctx.opts.ack_via_attacker:
            warm_publisher(self.pub_ack, msg.Ack(0, 0, 0, -1).encode()[0])

    # ---- scores for the greedy attacker
    def _put_score(self, k: int, s: float) -> None:
        with self._score_cond:
            self.scores[k] = s
            self._score_cond.notify_all()

    def _on_sensor(self, sample) -> None:
        try:
            s = msg.Sensor.decode(sample.payload, sample.attachment)
        except msg.MessageError:
            return
        if s.k != msg.WARMUP_K:
            self._put_score(s.k, float(np.max(np.abs(s.x))))

    def _on_enc_telemetry(self, sample) -> None:
        try:
            recs = [msg.EncoderTelemetry.decode(r) for r in msg.unpack_batch(sample.payload)]
        except msg.MessageError:
            return
        for t in recs:
            if not t.silent:
                self._put_score(t.k, t.E)

    def _score(self, k: int, wait: bool) -> float:
        clock = self.ctx.clock
        with self._score_cond:
            if k not in self.scores and wait and clock is not None:
                until = clock.now() + self.score_wait_ns
                while k not in self.scores:
                    rem = until - clock.now()
                    if rem <= 0:
                        break
                    self._score_cond.wait(rem / 1e9)
            s = self.scores.pop(k, math.nan)
            for old in [j for j in self.scores if j < k]:
                del self.scores[old]
        if s != s:
            self.missing_scores += 1
        return s

    # ---- decisions, once per sample and in order
    def decide(self, k: int, wait_score: bool = True) -> int:
        T = self.sc.T
        with self._lock:
            while self.next_decide <= k:
                j = self.next_decide
                score = self._score(j, wait_score and j == k) if self.gate.is_online else 0.0
                d = int(self.gate.decide(j, j * T, score))
                if 0 <= j < len(self.decisions):
                    self.decisions[j] = d
                self.next_decide = j + 1
            return self.decisions[k] if 0 <= k < len(self.decisions) else 0

    def _publish_status(self, k: int) -> None:
        on = bool(self.gate.attack_on)
        if on != self._last_on:
            self._last_on = on
            self.pub_status.put(msg.AttackerStatus(k=k, attack_on=on, dropped=self.dropped,
                                                   forwarded=self.forwarded,
                                                   acks_dropped=self.acks_dropped).encode())

    # ---- callbacks
    def _on_symbol(self, sample, h, rx: int):
        ctx = self.ctx
        k = h.k
        if k >= ctx.n_steps:
            return None
        if k > ctx.newest_k(rx):
            self.future_symbols += 1
            ctx.event("future_symbol", k=k, detail=f"symbol for sample {k} before its instant: dropped")
            return None
        self.maybe_crash(k)
        drop = self.decide(k)
        corrupted = 0
        tx = msg.NO_TIME
        if drop:
            self.dropped += 1
        else:
            payload = sample.payload.to_bytes()
            kind = self.corrupt.get(k)
            if kind is not None:
                payload = self._corrupt(payload, kind)
                corrupted = 1
                self.corrupted += 1
            tx = ctx.now()
            self.pub_fwd.put(payload, attachment=sample.attachment)
            self.forwarded += 1
        ctx.telemetry.put(msg.AttackerTelemetry(k=k, rx_ns=rx, tx_ns=tx, dropped=int(drop), corrupted=corrupted,
                                                attack_on=int(self.gate.attack_on), dropped_total=self.dropped,
                                                forwarded_total=self.forwarded).encode())
        self._publish_status(k)
        if corrupted:
            ctx.event("corrupted", k=k, detail=f"payload replaced ({self.corrupt[k]})", level=20)
        return k

    def _corrupt(self, payload: bytes, kind: str) -> bytes:
        return corrupt_payload(self.codebook, payload, kind)

    def _on_ack(self, sample) -> None:
        h = self.rx_header(sample, "ack header (dropped)")
        if h is None:
            return
        if h.k < self.ctx.n_steps and self.decide(h.k, wait_score=False):
            self.acks_dropped += 1
            return
        self.pub_ack.put(sample.payload, attachment=sample.attachment)
        self.acks_forwarded += 1

    def run(self) -> None:
        self.wait_end()

    def summary(self) -> dict:
        return {"mode": self.gate.mode, "dropped": self.dropped, "forwarded": self.forwarded,
                "corrupted": self.corrupted, "acks_dropped": self.acks_dropped,
                "acks_forwarded": self.acks_forwarded, "missing_scores": self.missing_scores,
                "attacks_started": self.gate.attacks_started, "malformed": self.malformed,
                "future_symbols": self.future_symbols,
                "score": self.score_kind, **self.rx_summary()}

