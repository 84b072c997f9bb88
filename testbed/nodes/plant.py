"""Plant node: samples x_k at t_k = k T on absolute deadlines, holds u, integrates the true plant.

It is also the run's time master: once every node is ready it picks t0 and
publishes ``Start``; when the last sample is done it publishes ``Stop``.

What acts on the plant is ``testbed.loop.protocol.PlantProtocol`` (the simulator runs
the same object) on the scenario's true plant (``[plant]``, ``sc.make_process()``).
Timing modes (``[run] timing``), with d = ``[run] deadline``:

* ``ideal``:    u_k acts on [t_k, t_k+1) as in the paper: the plant holds t_k until
  u_k arrives or d T has passed (then u_k = 0, a deadline miss) and computes
  x_k+1 = phi_T(x_k, u_k).  A live run reproduces ``testbed simulate`` bit for bit.
* ``physical``: u_k acts from its arrival t_k + delta_k (u_k-1 is held until then;
  after d T without u_k the actuator falls back to 0):
  x_k+1 = phi_{T - delta}(phi_delta(x_k, u_k-1), u_k).  The delays are recorded, so
  ``testbed resimulate`` reproduces the run.

Input checks: a u_k with a non-finite entry is rejected (u_k = 0, as if it never came)
and |u_k| is clamped to ``[controller] u_max``; an actuation whose header names a
sample whose instant has not come yet is rejected.  Each is counted and logged as
an event.  If the controller's liveliness token disappears the plant stops waiting
and runs on with u = 0; the run is marked (``controller_lost_at``).

A plant that is a device (``[plant.sensor]``, ``[plant.actuator]``, ``[plant.disturbance]``,
``testbed.loop.device``, applied by ``PlantProtocol`` as in the simulator): the sensor message carries
x_meas,k, the telemetry both x_k and x_meas,k, and u is the input that acted after the actuator.

Colocated encoder (``--colocate encoder``, a smart sensor): the plant's process also
runs the encoder (``testbed.nodes.encoder.EncoderNode``, ``embedded``) on x_k as it is
sampled: no sensor message (x_k is still published for a greedy attacker that scores
by the state), and the ack of the actuation message handed over in the process.

Plant faults: a true plant that raises ``plants.PlantFault`` (an FMU step that failed)
ends the run at that sample, as ``testbed simulate`` does: sample k's telemetry, an
event ``plant_fault`` with the plant's line, the final record (x at the fault) and a
``Stop`` naming the fault; the node then exits with status 1.  A plant that fails
already in its start-up reset is a startup failure (one line in the log, exit 1).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING

import numpy as np

from plants.base import PlantFault

from ..loop.flow import FLOW_OK, STATUS_NAMES
from ..loop.protocol import PlantProtocol
from ..record.timingstats import Timings, percentiles
from ..wire import messages as msg
from ..wire import transport
from .base import Node
from .context import RoleView

if TYPE_CHECKING:
    from ..scenario import Scenario

PT = msg.PlantTelemetry


def warm_process(sc: Scenario) -> None:
    """Load the true plant's compiled flow map (or start an FMU) on a throw-away copy of the plant:
    the node's warm-up, and the launcher's before it forks (for an ODE plant only)."""
    p = sc.make_process()
    try:
        p.reset(sc.x0)
        p.advance(np.zeros(p.m), sc.T)
        p.advance(np.zeros(p.m), 0.5 * sc.T)
    finally:
        p.close()


class PlantNode(Node):
    role = "plant"

    def setup(self) -> None:
        ctx, keys = self.ctx, self.ctx.keys
        sc = self.sc
        self.encoder = None
        if "encoder" in ctx.opts.colocate:
            self.encoder = self._embedded_encoder()
        # x_k on the wire: for the encoder, or (colocated) only for an attacker that scores by the state
        wanted = sc.attack.online and sc.attack.score == "state"
        self.pub_sensor = self.publisher(keys.sensor) if self.encoder is None or wanted else None
        self.pub_start = ctx.session.declare_publisher(keys.start)
        self.pub_stop = ctx.session.declare_publisher(keys.stop)
        self._ack_to_encoder = self.encoder is not None and ctx.opts.ack_on_actuation
        self._guest_links: dict = {}  # [network] sensor/ack losses of the colocated encoder (``channelstage``)
        if self.encoder is not None and sc.network is not None:
            from .channelstage import in_process_links

            self._guest_links = in_process_links(self.encoder)
        self._sub_act = self.subscribe(keys.actuation, self._on_actuation, primary=True, thread=False,
                                       link="actuation")
        self._lock = threading.Lock()
        self._got = threading.Event()
        self._waiting_k = 0                  # the sample whose u_k the loop needs next
        self._acts: dict[int, tuple[msg.Actuation, int]] = {}  # u_k that arrived, by k
        self.controller_dead = False
        self.controller_lost_at = -1
        self.late_u = 0
        self.future_u = 0
        self.misses = 0
        self.no_u = 0
        self.overruns = 0
        self.jitter = Timings()  # fixed memory however long the run
        self.latency = Timings()  # fixed memory however long the run
        self.k_done = 0
        self.flow_status = FLOW_OK
        self.diverged_at = -1
        self.plant_fault: str | None = None
        self.plant_fault_at = -1
        self.timing = self.sc.run.timing
        self.spin_ns = int(self.cfg.spin_us * 1e3) if self.cfg.spin_us is not None \
            else min(200_000, self.ctx.T_ns // 20)
        self.process = self.sc.make_process()
        ctx.on_peer(self._on_peer)

    def _embedded_encoder(self):
        import dataclasses

        from .encoder import EncoderNode

        enc = EncoderNode(RoleView(self.ctx, "encoder"), dataclasses.replace(self.cfg, crash_at=self.cfg.encoder_crash_at))
        enc.embedded = True
        enc.setup()
        return enc

    def declare_alive(self) -> None:
        super().declare_alive()
        if self.encoder is not None:
            self.encoder.ctx.declare_alive()

    def declare_ready(self) -> None:
        if self.encoder is not None and not self.encoder.dead:
            self.encoder.ctx.declare_ready()
        super().declare_ready()

    def kill_encoder(self) -> None:
        """``--kill encoder@S`` when colocated (SIGUSR2 from the launcher): the encoder alone dies."""
        if self.encoder is not None:
            self.encoder.kill()

    def warmup(self) -> None:
        if self.encoder is not None:
            self.encoder.warmup()
        try:
            warm_process(self.sc)
        except PlantFault as e:  # the true plant cannot start (an FMU that fails to initialize): one line
            self.process.close()
            raise SystemExit(f"testbed node plant: startup failed: plant fault: {e}") from None

    def warm_publishers(self) -> None:
        from .context import warm_publisher

        if self.pub_sensor is not None:
            warm_publisher(self.pub_sensor, msg.Sensor(0, 0, tuple(self.sc.x0)).encode()[0])
        if self.encoder is not None:
            self.encoder.warm_publishers()

    # ---- callbacks
    def _on_peer(self, node: str, alive: bool) -> None:
        if node == "controller" and not alive and self.ctx.start_msg is not None \
                and not self.controller_dead and not self.ctx.stop.is_set():
            self.controller_dead = True
            self.controller_lost_at = self.k_done
            self.ctx.event("controller_lost", k=self.k_done,
                           detail="controller liveliness lost: running on with u = 0")
            self._got.set()

    def _on_actuation(self, sample):
        rx = time.monotonic_ns()
        try:
            a = msg.Actuation.decode(sample.payload, sample.attachment)
        except msg.MessageError as e:
            self.bad_message("actuation", e)
            return None
        if a.k == msg.WARMUP_K:
            return None
        if self._ack_to_encoder and not ("ack" in self._guest_links and self._guest_links["ack"].drops(a.k)):
            self.encoder.ack_in(a.k, a.theta, a.last_rx, rx)  # the colocated encoder's ack rides on this message
        if len(a.u) != self.process.m:
            self.bad_message("actuation", msg.MessageError(f"u has {len(a.u)} entries, plant has m = {self.process.m}"))
            return None
        ctx = self.ctx
        if ctx.clock is not None and a.k > ctx.newest_k(rx - ctx.clock.t0_mono_ns):
            self.future_u += 1
            ctx.event("future_actuation", k=a.k, detail=f"u for sample {a.k} before its instant: rejected")
            return None
        with self._lock:
            if a.k < self._waiting_k or a.k in self._acts or a.k >= ctx.n_steps:
                self.late_u += 1
                return None
            self._acts[a.k] = (a, rx)  # may come before the loop reaches k when the plant runs late
            if a.k == self._waiting_k:
                self._got.set()
        return a.k

    # ---- the time master
    def start_run(self, lead_s: float, timeout: float) -> msg.Start | None:
        ctx = self.ctx
        need = set(transport.ROLES) | ({transport.COLLECTOR} if self.cfg.wait_collector else set())
        if not ctx.wait_for("ready", need, timeout):
            if not ctx.stop.is_set():
                ctx.event("startup_timeout", detail=f"not ready after {timeout:g} s: "
                                                    f"{', '.join(ctx.missing('ready', need))}")
                ctx.request_stop("startup timeout")
            return None
        st = msg.Start(run_id=ctx.keys.run_id, t0_ns=time.time_ns() + int(lead_s * 1e9), T_ns=ctx.T_ns,
                       n_steps=ctx.n_steps, digest=ctx.digest, timing=self.timing,
                       ack_via_attacker=ctx.opts.ack_via_attacker)
        ctx.adopt_start(st)
        payload = st.encode()

        def announce():  # repeated until t0: a node that missed one copy gets the next
            while not ctx.stop.is_set() and ctx.now() < -20_000_000:
                self.pub_start.put(payload)
                time.sleep(0.05)

        self.pub_start.put(payload)
        threading.Thread(target=announce, daemon=True, name="start-announce").start()
        return st

    # ---- the loop
    def run(self) -> None:
        ctx, sc, clock = self.ctx, self.sc, self.ctx.clock
        assert clock is not None  # set by the Start before any sample is handled
        T_ns, N = ctx.T_ns, ctx.n_steps
        d_ns = int(sc.run.deadline * T_ns)
        physical = self.timing == "physical"
        proc = self.process
        fault = None
        try:
            proc.reset(np.array(sc.x0, dtype=np.float64))
        except PlantFault as e:
            fault = e
            self._on_plant_fault(e, 0)
        pp = PlantProtocol.for_scenario(sc, proc)
        tel = ctx.telemetry
        for k in range(N if fault is None else 0):
            if ctx.stop.is_set():
                break
            t_act = clock.sleep_until(k * T_ns, self.spin_ns, ctx.stop)
            if ctx.stop.is_set():
                break
            self.maybe_crash(k)
            with self._lock:
                self._waiting_k = k
                if k in self._acts:
                    self._got.set()
                else:
                    self._got.clear()
            x = proc.x
            xm = pp.measure(k, x)  # x_meas,k: what the sensor reads ([plant.sensor]; x_k itself without one)
            if self.pub_sensor is not None:
                payload, att = msg.Sensor(k, t_act, tuple(xm.tolist())).encode()
                self.pub_sensor.put(payload, attachment=att)
            sensor_tx = clock.now()
            if self.encoder is not None and not (self._guest_links and "sensor" in self._guest_links
                                                 and self._guest_links["sensor"].drops(k)):
                enc = self.encoder  # the colocated encoder: x_k handed over in the process
                try:
                    enc.sensor_in(k, t_act, xm, clock.now())
                except Exception as e:  # noqa: BLE001 - the encoder fails alone
                    enc.fail(e)
            # -- hold t_k until u_k or the deadline t_k + d T (ideal), or until u_k acts (physical).
            # The deadline is nominal: a plant that runs late waits less and catches up.
            deadline = k * T_ns + d_ns
            inlet = self.inlet
            while not self.controller_dead:
                now = clock.now()
                rem = deadline - now
                if rem <= 0 or self._got.is_set():
                    break
                w = inlet.window(now) if inlet is not None else None
                if w is not None and w[0] <= now < w[1]:  # rx "spin": u_k is due, poll for it
                    assert inlet is not None  # a window comes from the inlet
                    if not inlet.spin(min(w[1], deadline)) and clock.now() >= w[1]:
                        inlet.last_k = max(inlet.last_k, k)  # not this window: wait as usual
                    continue
                if w is not None and w[0] > now:
                    rem = min(rem, w[0] - now)
                if self._got.wait(rem / 1e9):
                    break
            with self._lock:
                a, rx_mono = self._acts.pop(k, (None, msg.NO_TIME))
                self._waiting_k = k + 1
                for old in [j for j in self._acts if j <= k]:
                    del self._acts[old]
                    self.late_u += 1
            flags = 0
            u = None
            if a is not None:
                u, refused = pp.check_input(a.u)
                if refused == "nonfinite":
                    ctx.event("input_rejected", k=k, detail="u_k has a non-finite entry: u_k = 0 applied")
                elif refused == "clamped":
                    ctx.event("input_clamped", k=k, detail=f"|u_k| above u_max = {sc.controller.u_max:g}: clamped")
            if u is not None:
                assert a is not None  # u is the checked a.u
                theta = a.theta
                u_rx = rx_mono - clock.t0_mono_ns
                self.latency.append(u_rx - t_act)
            else:
                theta = msg.THETA_NONE if a is None else a.theta
                u_rx = msg.NO_TIME
                flags |= PT.FLAG_NO_U
                self.no_u += 1
                if self.controller_dead:
                    flags |= PT.FLAG_CTRL_DEAD
                elif a is None:
                    flags |= PT.FLAG_MISS
                    self.misses += 1
            jit = t_act - k * T_ns
            self.jitter.append(jit)
            if jit > d_ns:
                self.overruns += 1
            # -- integrate over [t_k, t_k+1)
            if not physical:
                delay = 0
            elif u is not None:
                delay = pp.delay_ns(u_rx - t_act, theta)
            else:  # u_{k-1} held until the (nominal) deadline, then 0
                delay = min(max(deadline - t_act, 0), T_ns)
            try:
                st = pp.step(u, delay)
            except PlantFault as e:  # the run ends at this sample, as in testbed simulate
                fault, st = e, FLOW_OK
            applied = pp.u_applied
            u_applied = (np.zeros(proc.m) if u is None else u) if pp.device is None or applied is None else applied
            tel.put(PT(k=k, t_ns=t_act, sensor_tx_ns=sensor_tx, u_rx_ns=u_rx, delay_ns=delay, theta=theta,
                       flags=flags, flow_status=st, x=tuple(x.tolist()), u=tuple(u_applied.tolist()),
                       x_meas=() if xm is x else tuple(xm.tolist())).encode())
            self.k_done = k + 1
            if fault is not None:
                self._on_plant_fault(fault, k)
                break
            if st != FLOW_OK:
                self.flow_status, self.diverged_at = st, k
                ctx.event("flow_diverged", k=k, detail=f"phi_T status {STATUS_NAMES.get(st, st)}: run ends")
                break
        x = proc.x
        self.x_final = x
        self.rejected_nonfinite, self.clamped = pp.rejected_nonfinite, pp.clamped
        self.device_counters = {} if pp.device is None else pp.device.counters()
        final_k = self.k_done
        tel.put(PT(k=final_k, t_ns=clock.now(), sensor_tx_ns=msg.NO_TIME, u_rx_ns=msg.NO_TIME, delay_ns=0,
                   theta=msg.THETA_NONE, flags=PT.FLAG_FINAL, flow_status=self.flow_status,
                   x=tuple(x.tolist()), u=()).encode())
        reason = "done" if final_k == N else (f"flow diverged at sample {self.diverged_at}"
                                               if self.diverged_at >= 0 else ctx.stop_reason or "stopped")
        if fault is not None:
            reason = f"plant fault at sample {self.plant_fault_at}: {fault}"
        tel.flush()
        self.pub_stop.put(msg.Stop(reason=reason, origin="plant").encode())
        if not ctx.stop.is_set():
            ctx.request_stop(reason)
        proc.close()
        if fault is not None:
            self.error = fault  # exit status 1, without a traceback: the fault's line is in the event and the log

    def _on_plant_fault(self, e: PlantFault, k: int) -> None:
        self.plant_fault, self.plant_fault_at = str(e), k
        self.ctx.event("plant_fault", k=k, detail=str(e), level=logging.ERROR)

    def summary(self) -> dict:
        return {"samples": self.k_done, "deadline_misses": self.misses, "u_missing": self.no_u,
                "late_u": self.late_u, "future_u": self.future_u,
                "inputs_rejected": getattr(self, "rejected_nonfinite", 0), "inputs_clamped": getattr(self, "clamped", 0),
                "overruns": self.overruns, "malformed": self.malformed,
                "controller_lost_at": self.controller_lost_at, "timing": self.timing,
                "plant_fault": self.plant_fault, "plant_fault_at": self.plant_fault_at,
                "jitter_us": percentiles(self.jitter), "latency_us": percentiles(self.latency),
                **getattr(self, "device_counters", {}),
                "spin_us": self.spin_ns / 1e3, "colocated": ["encoder"] if self.encoder is not None else [],
                **self.rx_summary()}
