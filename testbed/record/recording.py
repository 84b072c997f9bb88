"""MCAP recordings of runs (live or simulated): the writer, the reference reader, one set of topics.

``read`` decodes every message into a dataclass (simple, slow: the reference
the tests hold the fast reader to); the commands and ``testbed.open`` use the
streaming columnar reader, ``testbed.record.columns``.

Topics are the run's Zenoh keys without the ``testbed/<run_id>`` prefix; every
channel is protobuf (``testbed.record.schema``):

=========================  ==========================  ===============================================
topic                      schema                      content
=========================  ==========================  ===============================================
``/telemetry/plant``       ``testbed.PlantSample``     x_k, u_k, theta_k as received, timing, flags;
                                                       the final state x_N has flag bit 3
``/telemetry/encoder``     ``testbed.EncoderSample``   symbol, xi_k, E_k, q_k, saturation (Algorithm 1)
``/telemetry/controller``  ``testbed.ControllerSample``  xi_k, E_k, theta_k, q_k, u_k (Algorithm 2)
``/telemetry/attacker``    ``testbed.AttackerSample``  dropped / forwarded, attack on, totals
``/loop/sensor``           ``testbed.Sensor``          control path as it crossed the network
``/loop/symbol/tx|rx``     ``testbed.Symbol``          (live runs; at T >= 10 ms by default,
``/loop/actuation``        ``testbed.Actuation``       see ``testbed run --record-loop``)
``/loop/ack/tx|rx``        ``testbed.Ack``
``/attacker/status``       ``testbed.AttackerStatus``  every switch of the attack
``/events/<node>``         ``testbed.Event``           saturations, faults, peers lost, node deaths
``/summary/<node>``        ``testbed.NodeSummary``     a node's counters and timing at exit
``/control/start|stop``    ``testbed.RunStart|RunStop``  t0 and the run's identity; stops
``/liveliness``            ``testbed.Liveliness``      nodes appearing and going away
``/recorder/malformed``    ``testbed.Malformed``       anything that did not decode, as received
``/log``                   ``foxglove.Log``            start, end, attacks on and off, saturations,
                                                       faults, every node event (Foxglove's Log panel)
``/phase``                 ``foxglove.SceneUpdate``    one a sample: the phase plane (trajectory so far,
                                                       x_k, xi_k, the box Q(xi_k, E_k)), Foxglove's 3D panel
                                                       (a simulation at T < 10 ms: one every 10 ms of the
                                                       run, ``phase_every`` samples)
``/phase/roa``             ``foxglove.SceneUpdate``    once: the nominal region of attraction (n = 2,
                                                       T >= 10 ms)
=========================  ==========================  ===============================================

Metadata records: ``testbed.scenario`` (name, TOML text, reference, folder, plant module source),
``testbed.software`` (versions), ``testbed.run`` (source live|simulate, run id,
host, command line, options; a simulation's ``simulator``, ``writer`` and ``phase_every``),
and at a clean close ``testbed.recorder`` (message counts).  ``log_time`` is when the recorder got a message
(CLOCK_REALTIME ns; t0 + k T in a simulation), ``publish_time`` t0 plus the
message's own time stamp when it has one.

Crash safety: the writer closes its chunk and flushes the file at least every
``flush_interval`` (0.5 s), so a recorder killed with SIGKILL leaves a file whose
every complete chunk ``read`` recovers (``Recording.truncated`` is then True)."""

from __future__ import annotations

import json
import os
import platform
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..loop.channel import ATTACKER, CHANNEL
from ..wire import messages as msg
from . import schema
from .recorded import resolved_metadata, scenario_metadata, software_versions
from .topics import _U64_MAX, FORMAT_VERSION, PROFILE, schema_for_topic

if TYPE_CHECKING:
    from ..scenario import Scenario
    from ..sim.loop import SimResult


def default_path(scenario_name: str, when: float | None = None, directory: str | Path | None = None,
                 run_id: str | None = None) -> Path:
    """``recordings/<scenario>-<UTC start, YYYYmmdd-HHMMSS>-<run id>.mcap`` (a suffix avoids an existing file).

    The directory is ``$TESTBED_RECORDINGS_DIR`` if set, else ``recordings/`` under the current directory.
    The run id makes the name unique to the run; the writer also creates the file exclusively.
    """
    if directory is None:
        directory = os.environ.get("TESTBED_RECORDINGS_DIR") or "recordings"
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime(time.time() if when is None else when))
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in (run_id or ""))[:80]
    base = Path(directory) / (f"{scenario_name}-{stamp}-{safe}" if safe else f"{scenario_name}-{stamp}")
    p = base.with_suffix(".mcap")
    i = 1
    while p.exists():
        p = Path(f"{base}-{i}.mcap")
        i += 1
    return p


class RecordingFailed(OSError):
    """The recording file cannot be written (a full disk, an I/O error, the file removed under the writer)."""


#: bytes a recorder keeps allocated beside its file (``PATH.reserve``), freed to say why it failed (``PATH.error``)
RESERVE_BYTES = 16 * 1024


def error_path(path: str | Path) -> Path:
    """Where a recorder that could not write says why: ``PATH.error`` (one JSON object), beside the file."""
    return Path(f"{path}.error")


class RecordingWriter:
    """Thread-safe MCAP writer of protobuf messages, flushed at least every ``flush_interval`` seconds.

    A write that fails (ENOSPC, EIO, or the file found removed at a flush: its link count is 0) raises
    ``RecordingFailed`` once; ``failed`` then says why, later writes are dropped, and ``close`` leaves
    the part already written as it is (readable up to its last complete chunk).  With ``reserve`` a
    small file is kept allocated beside it and freed on failure, so that ``PATH.error`` can say why
    even on a full disk.
    """

    def __init__(self, path: str | Path, *, flush_interval: float = 0.5, chunk_size: int = 1 << 20,
                 compression: str = "zstd", exclusive: bool = True, reserve: bool = False):
        from mcap.writer import CompressionType, Writer

        from ..common.errors import BadInput

        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            # exclusive create: two runs can never write into one file
            self._f = open(self.path, "xb" if exclusive else "wb")
        except FileExistsError:
            raise BadInput(f"{self.path} exists: a recording is never overwritten (remove it, choose another "
                           "path, or pass --force)") from None
        except OSError as e:
            raise BadInput(f"cannot write the recording {self.path}: {e.strerror or e}") from None
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[compression]
        self._w = Writer(self._f, chunk_size=chunk_size, compression=comp, enable_data_crcs=True)
        self._w.start(profile=PROFILE, library=f"testbed-recorder/{FORMAT_VERSION}")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._lock = threading.Lock()
        self.flush_interval = float(flush_interval)
        self._last_flush = time.monotonic()
        self.counts: Counter = Counter()
        self.closed = False
        self.failed: str | None = None
        self._reserve = None
        if reserve:
            try:
                self._reserve = Path(f"{self.path}.reserve")
                fd = os.open(self._reserve, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
                try:
                    os.posix_fallocate(fd, 0, RESERVE_BYTES)
                finally:
                    os.close(fd)
            except OSError:
                self._drop_reserve()

    def _drop_reserve(self) -> None:
        if self._reserve is not None:
            try:
                self._reserve.unlink()
            except OSError:
                pass
            self._reserve = None

    def _fail(self, e: BaseException) -> RecordingFailed:
        """Mark the file failed (once), say why in ``PATH.error``; the exception to raise."""
        if self.failed is None:
            self.failed = (e.strerror or str(e)) if isinstance(e, OSError) and e.strerror else str(e)
            self._drop_reserve()
            try:
                error_path(self.path).write_text(json.dumps({
                    "error": self.failed, "errno": getattr(e, "errno", None), "messages_written": sum(self.counts.values()),
                    "at_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}) + "\n")
            except OSError:
                pass
        return RecordingFailed(f"cannot write {self.path}: {self.failed}")

    def _channel(self, topic: str, name: str) -> int:
        ch = self._channels.get(topic)
        if ch is None:
            sid = self._schemas.get(name)
            if sid is None:
                if "." in name:  # a Foxglove schema, as foxglove-sdk publishes it
                    from ..view.foxglove import descriptor_set

                    full, data = name, descriptor_set(name)
                else:
                    full, data = schema.full_name(name), schema.file_descriptor_set()
                sid = self._w.register_schema(name=full, encoding="protobuf", data=data)
                self._schemas[name] = sid
            ch = self._w.register_channel(topic=topic, message_encoding="protobuf", schema_id=sid)
            self._channels[topic] = ch
        return ch

    def channel(self, topic: str, name: str) -> int:
        """The channel id of ``topic`` (schema ``name``), registered on first use (for :meth:`adder`)."""
        with self._lock:
            return self._channel(topic, name)

    def adder(self) -> Callable[[int, int, bytes, int], None]:
        """``add(channel_id, log_time, data, publish_time)`` of mcap's writer (``simrecord.fast_adder``), for one
        thread writing many messages in a row in order of log time (``record_simulation``): no lock, no counts
        (the caller adds them), no flush (the caller calls :meth:`maybe_flush`)."""
        from .simrecord import fast_adder

        return fast_adder(self._w)

    def metadata(self, name: str, data: dict) -> None:
        clean = {str(k): v if isinstance(v, str) else json.dumps(v, default=str) for k, v in data.items()}
        with self._lock:
            if not self.closed and self.failed is None:
                try:
                    self._w.add_metadata(name, clean)
                    self._f.flush()
                except OSError as e:
                    raise self._fail(e) from None

    def write(self, topic: str, obj: Any, log_time: int, publish_time: int | None = None,
              name: str | None = None, extra: dict | None = None) -> None:
        """``obj``: a ``testbed.wire.messages`` dataclass, a dict with the schema's fields, or a protobuf message.

        ``extra``: fields beside the dataclass's (``view.foxglove.telemetry_extra``).
        """
        if name is None:
            name = schema_for_topic(topic)
            if name is None:
                raise ValueError(f"{topic!r} is not a topic of a recording")
        data = obj.SerializeToString() if hasattr(obj, "SerializeToString") else \
            schema.to_pb(obj, name, extra).SerializeToString()
        self.write_bytes(topic, name, data, log_time, publish_time)

    def write_bytes(self, topic: str, name: str, data: bytes, log_time: int, publish_time: int | None = None) -> None:
        log_time = int(log_time)
        with self._lock:
            if self.closed or self.failed is not None:
                return
            pub = int(log_time if publish_time is None else publish_time)
            try:
                ch = self._channel(topic, name)
                self._w.add_message(channel_id=ch, log_time=min(max(log_time, 0), _U64_MAX),
                                    data=data, publish_time=min(max(pub, 0), _U64_MAX))
            except OSError as e:
                raise self._fail(e) from None
            self.counts[topic] += 1
            if time.monotonic() - self._last_flush >= self.flush_interval:
                self._flush_locked()

    def maybe_flush(self) -> None:
        with self._lock:
            if not self.closed and self.failed is None and time.monotonic() - self._last_flush >= self.flush_interval:
                self._flush_locked()

    def flush(self) -> None:
        with self._lock:
            if not self.closed and self.failed is None:
                self._flush_locked()

    def _flush_locked(self) -> None:
        try:
            self._w.flush()   # closes the chunk in progress and flushes the stream (no fsync: a killed
            if os.fstat(self._f.fileno()).st_nlink == 0:  # process's written data survives in the page cache)
                raise OSError("the file was removed while it was being written (its link count is 0)")
        except OSError as e:
            raise self._fail(e) from None
        self._last_flush = time.monotonic()

    def close(self, recorder_stats: dict | None = None) -> None:
        with self._lock:
            if self.closed:
                return
            if self.failed is None:
                try:
                    self._close_locked(recorder_stats)
                    return
                except OSError as e:
                    self._fail(e)
            self.closed = True  # failed: what was written stays as it is, readable up to its last complete chunk
            try:
                self._f.close()
            except OSError:
                pass

    def _close_locked(self, recorder_stats: dict | None) -> None:
        stats = {"messages": sum(self.counts.values()), "per_topic": dict(self.counts)}
        if recorder_stats:
            stats.update(recorder_stats)
        self._w.add_metadata("testbed.recorder", {k: json.dumps(v) for k, v in stats.items()})
        self._w.finish()
        self._f.close()
        self.closed = True
        self._drop_reserve()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def write_text_metadata(w: RecordingWriter, sc: Scenario, *, source: str, run_id: str, ref: str | None = None,
                        extra: dict | None = None) -> None:
    """The metadata every recording starts with."""
    w.metadata("testbed.scenario", scenario_metadata(sc, ref))
    w.metadata("testbed.resolved", resolved_metadata(sc))
    w.metadata("testbed.software", software_versions())
    run = {"source": source, "run_id": run_id, "host": platform.node(), "pid": str(os.getpid()),
           "command": " ".join(sys.argv), "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    if extra:
        run.update({k: v if isinstance(v, str) else json.dumps(v, default=str) for k, v in extra.items()})
    w.metadata("testbed.run", run)


#: ``record_simulation``: the phase plane's SceneUpdate every sample at T >= PHASE_PERIOD_S, else every
#: round(PHASE_PERIOD_S / T) samples (one scene per 10 ms of the run: 60,000 a minute at 1 kHz cost more
#: than the telemetry; Foxglove's 3D panel needs no more)
PHASE_PERIOD_S = 0.01


def phase_every(T: float) -> int:
    """Samples between two phase-plane scenes of a simulation's recording (1: every sample)."""
    return 1 if T >= PHASE_PERIOD_S else max(1, int(round(PHASE_PERIOD_S / T)))


def record_simulation(path: str | Path, sc: Scenario, res: SimResult, *, overrides: dict | None = None,
                      ref: str | None = None, t0_ns: int | None = None, flush_interval: float = 5.0,
                      exclusive: bool = True,
                      roa: bool = True, bulk: bool = True) -> dict:
    """Write a simulated run (``testbed.sim.loop.SimResult``) with the topics and schemas of a live run.

    Times are nominal and latencies zero (t_k = k T, every message at its sample
    instant); t0 is the wall-clock time of the call.  The Foxglove topics
    (``view.foxglove``) come from the same tap as a live recorder's; ``roa``:
    draw the nominal region of attraction there.  Returns the writer's counts.

    ``bulk`` (default): the telemetry of every sample is encoded from the arrays at once
    (``testbed.record.simrecord``; the same bytes) and ``/phase`` holds a scene every
    :func:`phase_every` samples (every sample at T >= 10 ms; ``testbed.run`` metadata
    ``phase_every``).  ``bulk=False``: one message object at a time, a scene every sample (the
    reference the tests hold the bulk path to).
    """
    import numpy as np

    from ..sim.batch import attack_on_samples
    from ..view.foxglove import FoxgloveTopics, telemetry_extra

    t0 = time.time_ns() if t0_ns is None else int(t0_ns)
    Tn = int(round(sc.T * 1e9))
    N = len(res.t)
    plant = sc.make_model()
    cb = sc.make_method().codebook(plant.n, sc.quantizer)
    run_id = f"sim-{sc.name}-{t0}"
    w = RecordingWriter(path, flush_interval=flush_interval, exclusive=exclusive)
    fox = FoxgloveTopics(sc, roa=roa)

    def tap(items):
        for topic, name, data, lt in items:
            w.write_bytes(topic, name, data, lt)

    def tele(topic, name, t, lt):
        w.write(topic, t, lt, name=name, extra=telemetry_extra(name, t, t0, Tn))

    every = phase_every(sc.T) if bulk else 1
    try:
        write_text_metadata(w, sc, source="simulate", run_id=run_id, ref=ref,
                            extra={"scenario_overrides": overrides or {}, "bits": cb.bits,
                                   "simulator": getattr(res, "simulator", "per-sample"), "phase_every": every,
                                   "writer": "bulk" if bulk else "per-message"})
        start = msg.Start(run_id=run_id, t0_ns=t0, T_ns=Tn, n_steps=sc.n_steps, digest="", timing="ideal",
                          ack_via_attacker=False)
        w.write("/control/start", start, t0)
        tap(fox.start(start, t0))
        theta = np.asarray(res.theta, dtype=np.int64)
        attack_on = attack_on_samples(sc, res)  # an online attacker (greedy) is on when it drops
        # the attacker's own drops (a loss the channel caused, or a withheld sample, it forwarded or never saw)
        drop = theta if res.loss_cause is None else (np.asarray(res.loss_cause) == ATTACKER).astype(np.int64)
        dropped_total = np.cumsum(drop)
        withheld = res.withheld if res.withheld is not None else np.zeros(N, dtype=bool)
        # x_k never reached the encoder (a [network] sensor link lost it): no encoder record, as live
        unsensed = np.zeros(N, dtype=bool) if res.loss_cause is None else \
            (np.asarray(res.loss_cause) == CHANNEL) & (np.asarray(res.symbols) == -1) & ~np.asarray(withheld, dtype=bool)
        prev_on = False
        delays = res.delays
        u_missing = res.u_missing if res.u_missing is not None else np.zeros(N, dtype=bool)
        reasons = res.reason
        fault = getattr(res, "plant_fault", None)   # the true plant failed (an FMU step) at plant_fault_at
        x_meas = getattr(res, "x_meas", None)       # what the sensor read ([plant.sensor])
        u_plant = getattr(res, "u_plant", None)     # what acted after the actuator ([plant.actuator])
        if bulk:
            _bulk_samples(w, fox, sc, res, t0, Tn, every, theta, attack_on, dropped_total, drop, unsensed)
        for k in range(0 if bulk else N):  # the per-message path
            tk = k * Tn
            lt = t0 + tk
            th = int(theta[k])
            dk = 0 if delays is None else int(delays[k])
            miss = bool(u_missing[k])
            p = msg.PlantTelemetry(
                k=k, t_ns=tk, sensor_tx_ns=tk, u_rx_ns=msg.NO_TIME if miss else tk + dk, delay_ns=dk,
                theta=msg.THETA_NONE if miss else th,
                flags=(msg.PlantTelemetry.FLAG_NO_U | msg.PlantTelemetry.FLAG_MISS) if miss else 0,
                flow_status=int(res.flow_status) if k == res.diverged_at else 0,
                x=tuple(res.x[k]), u=tuple(u_plant[k]) if u_plant is not None else
                (0.0,) * res.u.shape[1] if miss else tuple(res.u[k]),
                x_meas=() if x_meas is None else tuple(x_meas[k]))
            tele("/telemetry/plant", "PlantSample", p, lt)
            tap(fox.plant(p, lt))
            if fault is not None and k == res.plant_fault_at:  # the event a live plant node publishes
                ev = msg.Event(node="plant", kind="plant_fault", k=k, t_ns=tk, detail=fault)
                w.write("/events/plant", ev, lt)
                tap(fox.event(ev, lt))
            sym = int(res.symbols[k])
            if withheld[k]:
                e = msg.EncoderTelemetry(k=k, sensor_tx_ns=tk, rx_ns=tk, tx_ns=msg.NO_TIME, symbol=-1, saturated=0,
                                         silent=1, E=float("nan"), xi=(), q=())
            else:
                e = msg.EncoderTelemetry(k=k, sensor_tx_ns=tk, rx_ns=tk, tx_ns=tk, symbol=sym,
                                         saturated=int(res.saturated[k]), silent=0, E=float(res.E_enc[k]),
                                         xi=tuple(res.xi_enc[k]), q=tuple(res.q_enc[k]))
            if not unsensed[k]:
                tele("/telemetry/encoder", "EncoderSample", e, lt)
                tap(fox.encoder(e, lt))
            if res.saturated[k]:
                ev = msg.Event(node="encoder", kind="saturation", k=k, t_ns=tk,
                               detail=f"x_k outside Q(xi_k, E_k), E_k = {res.E_enc[k]:.3e}")
                w.write("/events/encoder", ev, lt)
                tap(fox.event(ev, lt))
            on = bool(attack_on[k])
            tele("/telemetry/attacker", "AttackerSample", msg.AttackerTelemetry(
                k=k, rx_ns=tk, tx_ns=msg.NO_TIME if drop[k] else tk, dropped=int(drop[k]), corrupted=0, attack_on=int(on),
                dropped_total=int(dropped_total[k]), forwarded_total=int(k + 1 - dropped_total[k])), lt)
            if on != prev_on:
                st = msg.AttackerStatus(k=k, attack_on=on, dropped=int(dropped_total[k]),
                                        forwarded=int(k + 1 - dropped_total[k]))
                w.write("/attacker/status", st, lt)
                tap(fox.status(st, lt))
                prev_on = on
            reason = (msg.ControllerTelemetry.DEADLINE if th else msg.ControllerTelemetry.RECEIVED) \
                if reasons is None else int(reasons[k])
            received = reason == msg.ControllerTelemetry.RECEIVED
            tele("/telemetry/controller", "ControllerSample", msg.ControllerTelemetry(
                k=k, sym_stamp_ns=tk if received else msg.NO_TIME, rx_ns=tk if received else msg.NO_TIME, tx_ns=tk,
                symbol=sym if received else -1, theta=th, reason=reason,
                E=float(res.E_dec[k]), xi=tuple(res.xi_dec[k]), q=tuple(res.q[k]), u=tuple(res.u[k])), lt)
        tN = N * Tn
        tele("/telemetry/plant", "PlantSample", msg.PlantTelemetry(
            k=N, t_ns=tN, sensor_tx_ns=msg.NO_TIME, u_rx_ns=msg.NO_TIME, delay_ns=0, theta=msg.THETA_NONE,
            flags=msg.PlantTelemetry.FLAG_FINAL, flow_status=int(res.flow_status),
            x=tuple(np.asarray(res.x_final, dtype=float)), u=()), t0 + tN)
        if fault is not None and N == 0:  # the true plant failed to start
            w.write("/events/plant", msg.Event(node="plant", kind="plant_fault", k=0, t_ns=0, detail=fault), t0)
        mfault = getattr(res, "method_fault", None)
        if mfault is not None:  # the event a live node publishes when its method's end raises at sample k
            role = getattr(res, "method_fault_role", None) or "controller"
            ev = msg.Event(node=role, kind="method_fault", k=int(res.method_fault_at), t_ns=tN, detail=mfault)
            w.write(f"/events/{role}", ev, t0 + tN)
            tap(fox.event(ev, t0 + tN))
        stop = msg.Stop(reason="end of run" if fault is None and mfault is None else
                        f"plant fault at sample {res.plant_fault_at}: {fault}" if fault is not None else
                        f"method fault at sample {res.method_fault_at}: {mfault}", origin="simulator")
        if sc.network is not None:  # the controller's counters: its late symbols (the summary's losses.late)
            w.write("/summary/controller", {"node": "controller", "json": json.dumps(res.counters.get("controller", {}))},
                    t0 + tN, name="NodeSummary")
        w.write("/control/stop", stop, t0 + tN)
        tap(fox.stop(stop, t0 + tN))
    finally:
        w.close()
    return dict(w.counts)


def _bulk_samples(w: RecordingWriter, fox, sc, res, t0: int, Tn: int, every: int, theta, attack_on,
                  dropped_total, drop, unsensed, block: int = 1 << 15) -> None:
    """Every sample's messages, in the order of the per-message path: the telemetry encoded from the
    arrays (``simrecord``), blocks of ``block`` samples at a time; events, attack switches and the
    decimated phase plane between them as that path writes them."""
    import numpy as np

    from ..view.foxglove import REFRESH_S, TOPIC_PHASE, PhaseScene, window_of
    from .simrecord import encode, telemetry_columns

    N = len(res.t)
    if every > 1:  # the trajectory of the scenes is the scenes' samples: refreshed every REFRESH_S of the run
        fox.scene = PhaseScene(window_of(sc, None), refresh=max(1, round(REFRESH_S / (sc.T * every))))
    scene = fox.scene
    reason = theta if res.reason is None else np.asarray(res.reason, dtype=np.int64)
    withheld = np.zeros(N, bool) if res.withheld is None else np.asarray(res.withheld, dtype=bool)
    fault_at = res.plant_fault_at if getattr(res, "plant_fault", None) is not None else -1
    on = np.asarray(attack_on, dtype=bool)
    switch = set((np.flatnonzero(on != np.concatenate([[False], on[:-1]])) if N else np.zeros(0, np.int64)).tolist())
    sat = np.flatnonzero(res.saturated)
    special = set(range(0, N, every)) | switch | set(sat.tolist()) | ({fault_at} - {-1})
    add = w.adder()
    topics = ("/telemetry/plant", "/telemetry/encoder", "/telemetry/attacker", "/telemetry/controller")
    names = ("PlantSample", "EncoderSample", "AttackerSample", "ControllerSample")
    cp, ce, ca, cc = (w.channel(t, nm) for t, nm in zip(topics, names, strict=True))

    def tap(items):
        for topic, name, data, lt in items:
            w.write_bytes(topic, name, data, lt)

    for k0 in range(0, N, block):
        k1 = min(N, k0 + block)
        cols = telemetry_columns(res, k0, k1, t0, Tn, attack_on, dropped_total, reason, drop)
        P, E, A, C = (encode(nm, k1 - k0, cols[nm]) for nm in names)
        for k in range(k0, k1):
            i = k - k0
            lt = t0 + k * Tn
            if k not in special:
                add(cp, lt, P[i], lt)
                if not unsensed[k]:
                    add(ce, lt, E[i], lt)
                add(ca, lt, A[i], lt)
                add(cc, lt, C[i], lt)
                continue
            tk = k * Tn
            add(cp, lt, P[i], lt)
            if k == fault_at:
                ev = msg.Event(node="plant", kind="plant_fault", k=k, t_ns=tk, detail=res.plant_fault)
                w.write("/events/plant", ev, lt)
                tap(fox.event(ev, lt))
            if not unsensed[k]:
                add(ce, lt, E[i], lt)
            if k % every == 0:
                held = bool(withheld[k] or unsensed[k])
                w.write_bytes(TOPIC_PHASE, "foxglove.SceneUpdate",
                              scene.sample(lt, res.x[k], None if held else res.xi_enc[k],
                                           None if held else float(res.E_enc[k])), lt)
            if res.saturated[k]:
                ev = msg.Event(node="encoder", kind="saturation", k=k, t_ns=tk,
                               detail=f"x_k outside Q(xi_k, E_k), E_k = {res.E_enc[k]:.3e}")
                w.write("/events/encoder", ev, lt)
                tap(fox.event(ev, lt))
            add(ca, lt, A[i], lt)
            if k in switch:
                d = int(dropped_total[k])
                st = msg.AttackerStatus(k=k, attack_on=bool(on[k]), dropped=d, forwarded=int(k + 1 - d))
                w.write("/attacker/status", st, lt)
                tap(fox.status(st, lt))
            add(cc, lt, C[i], lt)
        for t in topics:
            w.counts[t] += k1 - k0 - (int(unsensed[k0:k1].sum()) if t == "/telemetry/encoder" else 0)
        w.maybe_flush()


def markdown() -> str:
    """docs/recording-format.md: every topic, metadata record and field (``python -m testbed.record.recording``)."""
    doc = __doc__
    table = doc[doc.index("========================="):doc.index("Metadata records")].strip()
    return f"""# Recording format (MCAP + protobuf)

Generated by `python -m testbed.record.recording > docs/recording-format.md` from `testbed/record/recording.py` and
`testbed/record/schema.py`; a test checks that it is current.

Every live run (`testbed run`) and every `testbed simulate --out` writes one MCAP file.
Topics are the run's Zenoh keys without the `testbed/<run_id>` prefix. Every channel is
protobuf (schema encoding `protobuf`, a `FileDescriptorSet` of package `testbed`), so
Foxglove opens the file as it is and Rerun decodes it natively.

## Topics

```
{table}
```

## Metadata records

- `testbed.scenario`: `name`, `toml` (the scenario file's text), `ref` (as given on the command line),
  `base_dir` (the scenario file's folder, empty for a bundled scenario), `plant_ref` (`[plant] name`),
  `plant_module`, `plant_class`, `plant_file` (where the plant class came from), `plant_source` (that module's
  text; empty for the bundled plants, which ship with the testbed) and `plant_sha256` (its sha256; for an FMU
  plant `plant_ref` is empty, `plant_file` the FMU and `plant_sha256` the file's); the same `model_*` keys for a
  `[model]` of another class than the plant's.
  `testbed report` loads `plant_source` only when the module cannot be imported (see docs/own-plant.md).
- `testbed.software`: versions of Python, the platform, dos-testbed (and its git commit when run from a
  checkout), numpy, scipy, numba, eclipse-zenoh, mcap, protobuf, rerun-sdk; `format` (this format's version).
- `testbed.run`: `source` (`live` or `simulate`), `run_id`, `host`, `pid`, `command`, `started_utc`,
  `scenario_overrides` (JSON: `--duration`, `--T`, `--mode`, ... applied on top of the TOML), and for live
  runs `T_ns`, `ack_via_attacker`; for a simulation `bits`, `simulator` (`batch` or `per-sample`: which
  simulator ran), `writer` (`bulk`: the telemetry encoded from the arrays at once; `per-message`) and
  `phase_every` (`/phase` holds the scene of every `phase_every`-th sample: 1 at T >= 10 ms, else one
  every 10 ms of the run).
- `testbed.recorder` (written at a clean close only): message counts per topic and the recorder's counters.

## Times

`*_ns` fields are nanoseconds since the run's t0 (`/control/start`: `t0_ns`, CLOCK_REALTIME). A time that
never happened is an absent field (proto3 `optional`). A message's MCAP `log_time` is when the recorder
received it (CLOCK_REALTIME ns); its `publish_time` is t0 plus the message's own time stamp. In a
simulation both are t0 + k T and every latency is zero.

## Messages and fields

{schema.describe()}"""


__all__ = ["RecordingWriter", "default_path", "record_simulation", "write_text_metadata"]


if __name__ == "__main__":
    sys.stdout.write(markdown())
