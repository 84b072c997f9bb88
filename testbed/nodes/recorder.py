"""``testbed record SCENARIO --run-id ID --out RUN.mcap``: the recorder node of a live run.

The recorder is a Zenoh peer like the four loop nodes: it subscribes to the
run's keys and writes what crossed the network to one MCAP file
(``testbed.record.recording``).  ``testbed run`` starts it before the loop nodes
and lets the plant start only once it is ready, so a recording holds a run
from its first sample; a recorder started by hand records whatever it sees.

Off the loop's path: a Zenoh callback only appends the raw bytes and the
arrival time to a queue; a writer thread decodes, converts to protobuf and
writes.  The queue holds at most ``Recorder.IN_MEMORY`` messages in memory and
the rest in an unnamed temporary file beside the recording
(``testbed.nodes.backlog``): a writer behind the run (niced, on a loaded
machine) holds no memory per message however long the run.  The control path (``loop/*``: five messages a sample) is recorded by
default only when T >= 10 ms (``--loop auto``); telemetry carries every value
of it anyway.  The file is flushed at least every ``--flush`` seconds, so a
recorder killed with SIGKILL loses at most that much.

It stops on SIGINT / SIGTERM, when the launcher goes away (``--launched``),
or by itself ``--linger`` seconds after the plant's ``Stop``.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import struct
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..record import recording, topics
from ..wire import messages as msg
from ..wire import transport
from ..wire.session import security_info, zenoh_config
from .backlog import Backlog
from .options import RECORD_FAILED, RecorderConfig, T_ns, load_scenario
from .process import on_stop_signals, parse_cpus, tune_process

if TYPE_CHECKING:
    from ..scenario import Scenario

log = logging.getLogger("testbed.recorder")
ROLE = "recorder"
RECORDER_STOP_GRACE_S = 60.0  # time to drain the queue and close the file after a signal

_LOOP_TYPES: dict[str, Any] = {"loop/sensor": msg.Sensor, "loop/symbol/tx": msg.Symbol, "loop/symbol/rx": msg.Symbol,
               "loop/actuation": msg.Actuation, "loop/ack/tx": msg.Ack, "loop/ack/rx": msg.Ack}
_JSON_TYPES: dict[str, Any] = {"attacker/status": msg.AttackerStatus, "control/start": msg.Start, "control/stop": msg.Stop}


def _stamp(t) -> int:
    """The record's own time (ns since t0) for ``publish_time``."""
    for f in ("t_ns", "tx_ns", "rx_ns"):
        v = getattr(t, f, msg.NO_TIME)
        if v != msg.NO_TIME:
            return v
    return msg.NO_TIME


def stats_key(keys: transport.Keys) -> str:
    """Queryable of a running recorder's counters (JSON): received, written, queue, ..."""
    return f"{keys.prefix}/recorder/stats"


class Recorder:
    """Subscribes to one run and writes it to ``writer``; ``close()`` drains and finishes the file."""

    #: malformed messages written as such (the rest only counted): a flood cannot fill the disk
    MAX_MALFORMED = 1000

    def __init__(self, session, keys: transport.Keys, writer: recording.RecordingWriter, *, loop: bool,
                 n_steps: int = 2**31, foxglove=None):
        import zenoh

        self.n_steps = int(n_steps)
        self.rejected = 0
        self.overflow = 0

        self._zenoh = zenoh
        self.keys = keys
        self.w = writer
        self.loop = loop
        # raw messages waiting for the writer: in memory up to a bound, the rest in a temporary file beside
        # the recording (a writer behind for the whole of a long run holds no memory per message)
        self.q = Backlog(self.IN_MEMORY, writer.path.parent)
        self.t0: int | None = None
        self.received = 0
        self.written = 0
        self.warmup = 0
        self.malformed = 0
        self.write_errors = 0
        self.failed: str | None = None  # why the file cannot be written (``RecordingFailed``)
        self.fox = foxglove   # testbed.view.foxglove.FoxgloveTopics, or None
        self.T_ns = 0 if foxglove is None else foxglove.T_ns
        self.stop_seen: msg.Stop | None = None
        self.stop_seen_mono = 0.0
        self.lost: dict[str, float] = {}
        self._done = threading.Event()
        self._wake = threading.Event()
        self._thread = threading.Thread(target=self._writer, name="recorder-writer", daemon=True)
        self._thread.start()
        p = keys.prefix
        self._plen = len(p) + 1
        if loop:
            keyexprs = [f"{p}/**"]
        else:
            keyexprs = [f"{p}/telemetry/*", f"{p}/events/*", f"{p}/summary/*", keys.attacker_status,
                        f"{p}/control/*"]
        self._subs = [session.declare_subscriber(k, self._on_sample) for k in keyexprs]
        self._subs += [session.liveliness().declare_subscriber(keys.alive("*"), self._on_alive, history=True),
                       session.liveliness().declare_subscriber(keys.ready("*"), self._on_ready, history=True)]
        # ``testbed/<run>/recorder/stats``: its counters on request (is it keeping up?)
        self._stats_q = session.declare_queryable(stats_key(keys), self._on_stats)

    def _on_stats(self, query) -> None:
        d = self.stats()
        d["queue"] = len(self.q)
        d["messages_in_file"] = sum(self.w.counts.values())
        query.reply(query.key_expr, json.dumps(d).encode())

    # ---- Zenoh threads: just enqueue
    #: messages waiting for the writer; beyond that they are counted, not kept (a flood cannot fill the disk)
    MAX_QUEUE = 500_000
    #: of those, the ones held in memory (about 460 bytes each for a telemetry batch); the rest wait on disk
    IN_MEMORY = 4096

    def _on_sample(self, sample) -> None:
        if self.failed is not None:
            return
        if len(self.q) >= self.MAX_QUEUE:
            self.overflow += 1
            return
        att = sample.attachment
        if not self.q.append((str(sample.key_expr), sample.payload.to_bytes(), None if att is None else att.to_bytes(),
                              time.time_ns())):
            self.overflow += 1  # the backlog's file could not be written
            return
        self.received += 1
        self._wake.set()

    def _liveliness(self, sample, token: str) -> None:
        node = transport.Keys.node_of(sample.key_expr)
        present = sample.kind != self._zenoh.SampleKind.DELETE
        if not self.q.append(("", None, (node, token, present), time.time_ns())):
            self.overflow += 1  # the backlog's file could not be written
        if not present and token == "alive":
            self.lost[node] = time.monotonic()
        self._wake.set()

    def _on_alive(self, sample) -> None:
        self._liveliness(sample, "alive")

    def _on_ready(self, sample) -> None:
        self._liveliness(sample, "ready")

    # ---- writer thread
    def _writer(self) -> None:
        while True:
            self._wake.wait(0.1)
            self._wake.clear()
            try:
                while self.q:
                    try:
                        item = self.q.popleft()
                    except OSError as e:  # the backlog's file cannot be read back: what waits in it is lost, counted
                        self.write_errors += len(self.q)
                        self.q.clear()
                        print(f"testbed record: the queue's file beside the recording cannot be read ({e}); "
                              "the messages waiting in it are lost (counted in write_errors)", file=sys.stderr,
                              flush=True)
                        break
                    try:
                        self._write(*item)
                    except recording.RecordingFailed:
                        raise
                    except Exception:
                        self.write_errors += 1
                        log.exception("recorder: could not write a message")
                self.w.maybe_flush()
            except recording.RecordingFailed as e:  # the file cannot take more: say so once, write no more
                self.failed = str(e)
                self.q.clear()
                print(f"testbed record: {e}; the recording ends here (what was written before stays readable)",
                      file=sys.stderr, flush=True)
                return
            if self._done.is_set() and not self.q:
                return

    def _pub(self, stamp: int, log_time: int) -> int:
        return log_time if self.t0 is None or stamp == msg.NO_TIME else self.t0 + stamp

    def _malformed(self, key: str, payload: bytes, attachment: bytes | None, error: str, log_time: int) -> None:
        self.malformed += 1
        if self.malformed > self.MAX_MALFORMED:
            return
        self.w.write("/recorder/malformed", {"key": key, "payload": payload, "attachment": attachment or b"",
                                             "error": error}, log_time)

    def _write(self, key: str, payload, attachment, log_time: int) -> None:
        if not key:  # liveliness
            node, token, present = attachment
            self.w.write("/liveliness", {"node": node, "token": token, "present": present}, log_time)
            return
        rel = key[self._plen:]
        topic = "/" + rel
        try:
            if rel.startswith("telemetry/"):
                role = rel[len("telemetry/"):]
                typ = msg.TELEMETRY_TYPES.get(role)
                if typ is None:
                    raise msg.MessageError(f"no telemetry type for node {role!r}")
                recs = [typ.decode(r) for r in msg.unpack_batch(payload)]
                name = topics.TELEMETRY_SCHEMA[role]
                N = self.n_steps
                for t in recs:
                    final = role == "plant" and t.flags & msg.PlantTelemetry.FLAG_FINAL
                    if not (0 <= t.k <= N if final else 0 <= t.k < N):
                        self.rejected += 1  # a sample outside the run: never recorded as one
                        continue
                    self.w.write(topic, t, log_time, self._pub(_stamp(t), log_time), name=name,
                                 extra=self._foxglove_extra(name, t))
                    self._foxglove(role, t, log_time)
                    self.written += 1
                return
            if rel in _LOOP_TYPES:
                m = _LOOP_TYPES[rel].decode(payload, attachment)
                if m.k == msg.WARMUP_K:
                    self.warmup += 1
                    return
                self.w.write(topic, m, log_time, self._pub(m.stamp_ns, log_time))
            elif rel.startswith("events/"):
                e = msg.Event.decode(payload)
                self.w.write(topic, e, log_time, self._pub(e.t_ns, log_time))
                self._foxglove("event", e, log_time)
            elif rel.startswith("summary/"):
                s = msg.NodeSummary.decode(payload)
                self.w.write(topic, {"node": s.node, "json": json.dumps(s.data, default=str)}, log_time)
            elif rel in _JSON_TYPES:
                m = _JSON_TYPES[rel].decode(payload)
                if isinstance(m, msg.Start) and self.t0 is None:
                    self.t0 = m.t0_ns
                if isinstance(m, msg.Stop) and self.stop_seen is None and m.origin == "plant":
                    self.stop_seen, self.stop_seen_mono = m, time.monotonic()
                self.w.write(topic, m, log_time)
                self._foxglove({msg.Start: "start", msg.Stop: "stop", msg.AttackerStatus: "status"}[type(m)], m,
                               log_time)
            else:
                raise msg.MessageError(f"not a key of a run: {rel}")
            self.written += 1
        except (msg.MessageError, ValueError, OverflowError, TypeError, struct.error) as e:
            # not a message of a run, or one whose numbers no schema can hold: counted and kept as bytes
            self._malformed(key, payload, attachment, f"{type(e).__name__}: {e}", log_time)

    # ---- Foxglove topics (testbed.view.foxglove): derived from what was just written
    def _foxglove_extra(self, name: str, t) -> dict | None:
        """The telemetry's derived fields (header stamp t0 + k T, log10 E_k) once t0 is known."""
        if self.fox is None:
            return None
        from ..view.foxglove import telemetry_extra

        return telemetry_extra(name, t, self.t0, self.T_ns)

    def _foxglove(self, kind: str, m, log_time: int) -> None:
        """Write the /log, /phase, /phase/roa messages that ``m`` makes (a failure never costs the recording)."""
        if self.fox is None:
            return
        try:
            handler = getattr(self.fox, kind, None)
            for topic, name, data, lt in (handler(m, log_time) if handler is not None else ()):
                self.w.write_bytes(topic, name, data, lt)
        except Exception:
            self.write_errors += 1
            log.exception("recorder: could not write a Foxglove message")

    def _foxglove_flush(self) -> None:
        """The phase-plane samples still waiting for their partner (the end of the run)."""
        if self.fox is not None:
            try:
                for topic, name, data, lt in self.fox.flush(time.time_ns()):
                    self.w.write_bytes(topic, name, data, lt)
            except Exception:  # noqa: BLE001 - counted: the recording goes on without the Foxglove scene
                self.write_errors += 1

    # ---- end
    def stats(self) -> dict:
        return {"received": self.received, "written": self.written, "warmup_skipped": self.warmup,
                "malformed": self.malformed, "rejected_k": self.rejected, "queue_overflow": self.overflow,
                "max_queue": self.q.max_len, "write_errors": self.write_errors,
                "loop_recorded": self.loop}

    def close(self, timeout: float = 30.0) -> dict:
        for s in (*self._subs, self._stats_q):
            try:
                s.undeclare()
            except Exception:  # noqa: BLE001 - the session may be closing
                pass
        self._done.set()
        self._wake.set()
        self._thread.join(timeout)
        if not self._thread.is_alive():
            self.q.close()
        self._foxglove_flush()
        st = self.stats()
        self.w.close(st)
        return st


# ============================================================================ command line


def loop_default(sc: Scenario, choice: str) -> bool:
    return choice == "on" or (choice == "auto" and sc.T >= 0.01)


def run_recorder(cfg: RecorderConfig) -> int:
    """Record the run of configuration ``cfg`` until it ends; the exit code."""
    import zenoh

    logging.basicConfig(level=logging.INFO if cfg.verbose else logging.WARNING, stream=sys.stderr,
                        format="%(asctime)s recorder   %(levelname)s %(message)s")
    opts = cfg.opts
    if cfg.cpus:
        os.sched_setaffinity(0, parse_cpus(cfg.cpus))
    sc = load_scenario(cfg.scenario, opts, check_design=not cfg.launched)
    tune_process(cfg.parent_pid)
    if cfg.nice:
        try:  # recording is off the loop's path: under CPU contention the loop nodes go first
            os.nice(cfg.nice)
        except OSError:
            pass
    stop = threading.Event()
    why = {"reason": ""}

    def on_signal(signum):  # on the signal thread (see on_stop_signals)
        why["reason"] = why["reason"] or f"signal {signal.Signals(signum).name}"
        stop.set()

    on_stop_signals(on_signal, grace=RECORDER_STOP_GRACE_S)
    assert cfg.session.run_id is not None  # a process's session has one (only the launcher's makes one)
    out = Path(cfg.out) if cfg.out else recording.default_path(sc.name, run_id=cfg.session.run_id)
    keys = transport.Keys.for_run(cfg.session.run_id)
    conf = zenoh_config(cfg.session, ROLE, keys, colocate=opts.colocate)
    if cfg.session.insecure and not cfg.launched:
        print(f"testbed record: INSECURE: no authentication, any local process can join run {cfg.session.run_id}",
              file=sys.stderr)
    w = recording.RecordingWriter(out, flush_interval=cfg.flush, exclusive=not cfg.force, reserve=True)
    try:
        recording.write_text_metadata(w, sc, source="live", run_id=cfg.session.run_id, ref=cfg.scenario_ref or cfg.scenario,
                                      extra={"scenario_overrides": opts.overrides(), "T_ns": T_ns(sc),
                                             "ack_via_attacker": opts.ack_via_attacker,
                                             "ack_on_actuation": opts.ack_on_actuation,
                                             "colocate": list(opts.colocate),
                                             "security": security_info(cfg.session)})
    except recording.RecordingFailed as e:
        w.close()
        print(f"testbed record: {e}; nothing recorded", file=sys.stderr, flush=True)
        return RECORD_FAILED
    loop = loop_default(sc, cfg.loop)
    print(f"testbed record: run {cfg.session.run_id} -> {out}", file=sys.stderr, flush=True)
    try:
        session_cm = zenoh.open(conf)
    except zenoh.ZError as e:
        w.close()
        print(f"testbed record: no Zenoh session (the router is not there, or it refused the credentials): "
              f"{str(e).split(' at /')[0]}", file=sys.stderr)
        return 3
    with session_cm as session:
        from ..view.foxglove import FoxgloveTopics

        rec = Recorder(session, keys, w, loop=loop, n_steps=sc.n_steps, foxglove=FoxgloveTopics(sc, background=True))
        tokens = [session.liveliness().declare_token(keys.alive(ROLE)),
                  session.liveliness().declare_token(keys.ready(ROLE))]
        try:
            while not stop.wait(0.05):
                if rec.failed is not None:
                    why["reason"] = "the file cannot be written"
                    break
                if cfg.launched and transport.COLLECTOR in rec.lost:
                    why["reason"] = "launcher gone"
                    break
                if not cfg.launched and rec.stop_seen is not None \
                        and time.monotonic() - rec.stop_seen_mono > cfg.linger:
                    why["reason"] = "run ended"
                    break
        finally:
            for t in tokens:
                try:
                    t.undeclare()
                except Exception:  # noqa: BLE001 - leaving: a token the session already dropped
                    pass
            st = rec.close()
    log.info("recorder stopped (%s): %s", why["reason"], st)
    print(f"testbed record: {st['written']} messages written to {out} ({why['reason'] or 'stopped'})",
          file=sys.stderr, flush=True)
    if rec.failed is None and w.failed is not None:  # it failed as it closed the file
        print(f"testbed record: cannot write {out}: {w.failed}; the recording has no footer (readable up to its "
              "last complete chunk)", file=sys.stderr, flush=True)
    code = RECORD_FAILED if rec.failed is not None or w.failed is not None else 0
    if rec.fox is not None and rec.fox.busy():
        # The phase-plane outline's daemon thread is still in numba's compiler (a short run of a plant
        # whose kernels were not cached): finalizing the interpreter under it can abort in LLVM
        # (SIGABRT) after the file is complete.  The file is closed and the lines above flushed: leave now.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


__all__ = ["RECORD_FAILED", "Recorder", "stats_key", "run_recorder", "loop_default"]
