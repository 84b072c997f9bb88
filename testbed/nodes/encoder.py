"""Encoder node: Algorithm 1 on x_k from the plant; symbol out, theta_k back with the actuation (or an ack).

The logic is ``testbed.loop.protocol.EncoderProtocol`` (the simulator runs the same
object); this shell adds the clock, the grace for a late ack, publishing and
telemetry.  If x_k+1 arrives and theta_k is still unknown (a lost or late ack:
the ack is routed through the attacker, or the controller is slow or dead), it
waits ``ack_grace`` and then withholds the symbol; theta_k is recovered from any
later ack (``last_rx``).  So a missing ack costs samples, never lockstep.

Where theta_k comes from: with the paper's ideal ack it rides on the controller's
actuation message, which the encoder reads beside the plant (``loop/actuation``);
with ``--separate-ack`` it is a message of its own (``loop/ack/tx``); with
``--ack-via-attacker`` the attacker's forward (``loop/ack/rx``).

Colocated (``--colocate encoder``): the plant's process runs this shell as a part of
itself (``embedded``): x_k comes from the plant's loop (``sensor_in``), no sensor
message, and the acks from the plant's actuation handler (``ack_in``); telemetry,
events, summary and liveliness are still the encoder's own.  Its failure (an
exception, or ``kill``: the launcher's ``--kill encoder@S``) ends the encoder, not
the plant.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING

from ..loop.protocol import EncoderProtocol, MethodFault, Send, skip_sample
from ..methods.base import symbol_code
from ..record.timingstats import Timings, percentiles
from ..wire import messages as msg
from .base import Node
from .context import warm_publisher

if TYPE_CHECKING:
    import numpy as np

    from plants.base import Plant

    from ..scenario import Scenario

log = logging.getLogger("testbed.nodes")


def warm_kernels(sc: Scenario, model: Plant) -> None:
    """Load the encoder's compiled kernels (quantizer, flow map, the plant's right-hand side): the
    node's warm-up, and the launcher's before it forks its nodes."""
    e = sc.make_method().make_encoder(model, sc.K, sc.quantizer, sc.flow)
    e.encode(sc.x0)
    e.ack(0)
    skip_sample(e)


class EncoderNode(Node):
    role = "encoder"
    embedded = False   # run inside the plant's process (``--colocate encoder``)

    def setup(self) -> None:
        ctx, keys = self.ctx, self.ctx.keys
        sc = self.sc
        self.enc = sc.make_method().make_encoder(self.model, sc.K, sc.quantizer, sc.flow)
        self.proto = EncoderProtocol(self.enc, ctx.n_steps)
        self.codebook = self.enc.codebook
        self.pub_symbol = self.publisher(keys.symbol_tx)
        self._cond = threading.Condition()
        self.pending_tx = 0
        self.ack_latency = Timings()  # fixed memory however long the run
        self.encode_time = Timings()  # fixed memory however long the run
        self.future_sensor = 0
        self.state_faults = 0  # x_k with a wrong length or a non-finite entry (``msg.state_fault``)
        self.dead = False
        self.killed = False
        self.ack_grace_ns = int(self.cfg.ack_grace * ctx.T_ns) if self.cfg.ack_grace is not None \
            else max(int(0.2 * sc.run.deadline * ctx.T_ns), 50_000)
        if sc.attack.online and sc.attack.score == "E":
            ctx.telemetry.n = 1  # the greedy attacker reads E_k from it before deciding sample k
            ctx.telemetry.immediate = True
        opts = ctx.opts
        self._subs = []
        if not self.embedded:
            self._subs.append(self.subscribe(keys.sensor, self._on_sensor, blocking=True, primary=True,
                                                             link="sensor"))
        if opts.ack_on_actuation:
            if not self.embedded:  # embedded: the plant's actuation handler hands the ack over (``ack_in``)
                self._subs.append(self.subscribe(keys.actuation, self._on_actuation, link="ack"))
        else:
            self._subs.append(self.subscribe(keys.ack_for_encoder(opts.ack_via_attacker), self._on_ack, link="ack"))

    def warmup(self) -> None:
        warm_kernels(self.sc, self.model)

    def warm_publishers(self) -> None:
        warm_publisher(self.pub_symbol, b"\0" * self.codebook.nbytes)

    # ---- x_k
    def _on_sensor(self, sample):
        try:
            s = msg.Sensor.decode(sample.payload, sample.attachment)
        except msg.MessageError as e:
            self.bad_message("sensor", e)
            return None
        if s.k == msg.WARMUP_K:
            return None
        bad = msg.state_fault(s.x, self.model.n)
        if bad is not None:  # a plant (a device) that sent a wrong x_k: never encoded; the launcher ends the run
            kind, why = bad
            if kind == msg.STATE_WRONG_LENGTH:
                self.bad_message("sensor", msg.MessageError(why), k=s.k)
            self.state_faults += 1
            if self.state_faults <= 20:
                self.ctx.event(kind, k=s.k, detail=f"x_{s.k} from the plant: {why}", level=logging.ERROR)
            return None
        clock = self.ctx.wait_clock()
        if clock is None:
            return None
        self.sensor_in(s.k, s.stamp_ns, s.x, clock.now())
        return s.k

    def sensor_in(self, k: int, stamp_ns: int, x: Sequence[float] | np.ndarray, rx: int) -> None:
        """x_k (sampled at ``stamp_ns``) reached the encoder at ``rx`` (run clock): encode, send."""
        if self.dead or self.method_fault is not None:
            return
        ctx = self.ctx
        clock = ctx.clock
        assert clock is not None  # set by the Start before any sample is handled
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
            try:
                act = self.method_call(k, proto.sensor, k, x)
            except MethodFault as e:  # (embedded: the plant's loop called us) the run ends at this sample
                self.fail(e)
                return
            if act is None:
                return
            if isinstance(act, Send):
                data = self.codebook.pack(act.symbol)
                tx = clock.now()
                self.pub_symbol.put(data, attachment=msg.Header(k, tx).encode())
                self.pending_tx = tx
                self.encode_time.append(tx - rx)
                tel = msg.EncoderTelemetry(k=k, sensor_tx_ns=stamp_ns, rx_ns=rx, tx_ns=tx, symbol=symbol_code(act.symbol),
                                           saturated=int(act.saturated), silent=0, E=act.E,
                                           xi=tuple(act.xi.tolist()), q=tuple(act.q.tolist()))
            else:
                if act.first:
                    ctx.event("ack_missing", k=act.pending,
                              detail=f"theta_{act.pending} unknown at sample {k}: withholding symbols "
                                     "until an ack resolves it", level=20)
                tel = msg.EncoderTelemetry(k=k, sensor_tx_ns=stamp_ns, rx_ns=rx, tx_ns=msg.NO_TIME,
                                           symbol=-1, saturated=0, silent=1, E=float("nan"), xi=(), q=())
        ctx.telemetry.put(tel.encode())
        if isinstance(act, Send) and act.saturated:
            ctx.event("saturation", k=k, detail=f"x_k outside Q(xi_k, E_k), E_k = {act.E:.3e}"
                      + (" (OVERFLOW sent)" if act.symbol == self.codebook.overflow else " (clipped)"),
                      level=20)

    # ---- theta_k
    def _on_actuation(self, sample):
        return self._ack_from(sample, msg.Actuation, "actuation (the ack it carries)")

    def _on_ack(self, sample):
        return self._ack_from(sample, msg.Ack, "ack")

    def _ack_from(self, sample, cls, what: str):
        """theta_k and last_rx from an Ack or an Actuation message: the sample index, or None."""
        rx = time.monotonic_ns()
        try:
            a = cls.decode(sample.payload, sample.attachment)
        except msg.MessageError as e:
            self.bad_message(what, e)
            return None
        if a.k == msg.WARMUP_K:
            return None
        self.ack_in(a.k, a.theta, a.last_rx, rx)
        return a.k

    def ack_in(self, k: int, theta: int, last_rx: int, rx_mono: int) -> None:
        """The ack of sample k (theta_k, last_rx) arrived at ``rx_mono`` (CLOCK_MONOTONIC ns)."""
        if self.dead or self.method_fault is not None:
            return
        proto = self.proto
        with self._cond:
            p, silent = proto.pending, len(proto.silent)
            try:
                what = self.method_call(lambda: proto.next_k, proto.ack, k, theta, last_rx)
            except MethodFault as e:
                self.fail(e)
                return
            if what == "resolved" and self.ctx.clock is not None:
                self.ack_latency.append(rx_mono - self.ctx.clock.t0_mono_ns - self.pending_tx)
            elif what == "resync" and p is not None:
                self.ctx.event("ack_resync", k=p, detail=f"theta_{p} recovered from the ack of sample {k}; "
                                                         f"{silent} samples withheld", level=20)
            self._cond.notify_all()

    # ---- colocated: the encoder alone dies
    def fail(self, e: BaseException) -> None:
        if not self.embedded or isinstance(e, MethodFault):
            return super().fail(e)
        if self.error is None:
            self.error = e
            import traceback

            log.error("encoder (colocated in the plant) crashed:\n%s",
                      "".join(traceback.format_exception(e)).rstrip())
            self.ctx.event("crash", detail=f"{type(e).__name__}: {e}", level=logging.ERROR)
            self.die()

    def kill(self) -> None:
        """Fault injection (``--kill encoder@S`` when colocated): the encoder stops at once, as if
        SIGKILLed: nothing more sent, its unpublished telemetry lost, its liveliness tokens gone."""
        if not self.dead:
            self.killed = True
            log.warning("encoder (colocated in the plant): killed")
            self.ctx.telemetry.discard()
            self.die()

    def die(self) -> None:
        with self._cond:
            self.dead = True
            self._cond.notify_all()
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:  # noqa: BLE001 - the session may be closing
                pass
        self.ctx.close()  # its alive/ready tokens: the peers see it go

    def run(self) -> None:
        self.wait_end()

    def summary(self) -> dict:
        d = self.proto.counters()
        d.update({"malformed": self.malformed, "future_sensor": self.future_sensor, "ack_grace_us": self.ack_grace_ns / 1e3,
                  "encode_us": percentiles(self.encode_time), "ack_rtt_us": percentiles(self.ack_latency)})
        d.update(self.rx_summary())
        if self.embedded:
            d["colocated_in"] = "plant"
        return d
