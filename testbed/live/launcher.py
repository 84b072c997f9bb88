"""``testbed run SCENARIO [--duration S]``: start the four nodes of a live run, watch them, stop them.

The launcher listens on one Zenoh endpoint (``tcp/127.0.0.1:<free port>`` by
default, a fresh port per run), starts plant, encoder, attacker and controller as
``testbed node ...`` processes, each in its own session and process group, and
collects their telemetry (``testbed.live.collect``).  It stops them all on
SIGINT, SIGTERM, Ctrl-C, the end of the run or a timeout: ``Stop`` message, then
SIGINT to each group, then SIGKILL.  Nodes also die with the launcher
(PR_SET_PDEATHSIG) and stop when its liveliness token goes away, so no node is
left behind.  A node that dies is reported with its exit status, the last lines
of its log and when its liveliness token went away; the run goes on without it
(unless it was the plant).  With ``--colocate encoder`` there are three node
processes; the plant's runs the encoder, whose death alone (``--kill encoder@S``:
SIGUSR2 to the plant) the launcher reports from its liveliness token.

Exit codes: 0 clean run, 1 a node died or the run did not complete,
2 bad scenario, 3 the recording is incomplete, 128 + signal when interrupted.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import secrets
import shlex
import shutil
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .. import scenario
from ..common.errors import BadInput
from ..nodes.options import NodeConfig, RecorderConfig, RunConfig, load_scenario
from ..nodes.process import parse_cpus, peak_rss_mb
from ..record.faults import Fault
from ..wire import messages as msg
from ..wire import transport
from . import external, netns, status
from .credentials import RunCredentials
from .devicefaults import DEVICE_FAULTS, DeviceWatch
from .faultlog import FaultLog
from .processes import NodeProcesses
from .recorder import RecorderProcess, exit_code
from .stalls import StallControl, check_fault_times, lost_during, parse_stalls

if TYPE_CHECKING:
    import zenoh

    from .collect import Collector

#: a launched node waits this much longer than ``--startup-timeout`` for its peers: the launcher's clock, which
#: starts after the forked nodes' (it opens its session and the recorder first), decides a start-up timeout and
#: stops them, so a slow machine does not turn it into a node's exit code 3 ("crashed") first
STARTUP_GRACE_S = 10.0


def recording_default_path(name: str, run_id: str) -> Path:
    from ..record.recording import default_path

    return default_path(name, run_id=run_id)


def declare_summaries_held(session: zenoh.Session, keys: transport.Keys, col: Collector) -> zenoh.Queryable:
    """The queryable ``collector/summaries``: the roles whose summaries ``col`` holds, as a JSON list (a node
    closes its session once its own is among them: ``NodeContext.summary_received``)."""
    def reply(query: zenoh.Query) -> None:
        try:
            query.reply(query.key_expr, json.dumps(sorted(col.snapshot_summaries())).encode())
        except Exception:  # noqa: BLE001 - the querier gave up or the session is closing
            pass

    return session.declare_queryable(keys.summaries_held, reply)


class RouterPriority:
    """With SCHED_FIFO asked for (``RunConfig.sched_fifo``), the launcher's threads (the run's router) run under
    SCHED_FIFO during the loop as the nodes' do: a router thread at normal priority waits behind every other
    process for each message it forwards.  ``fifo``: whether it did at some point of the run (the summary's
    ``launcher.sched_fifo``)."""

    def __init__(self, realtime: bool):
        self.realtime = realtime
        self.on = False
        self.fifo = False

    def set(self, on: bool) -> None:
        from ..nodes.process import set_realtime

        if not self.realtime or on == self.on:
            return
        if on:
            self.on = set_realtime(True)
            self.fifo = self.fifo or self.on
        else:
            set_realtime(False)
            self.on = False


class Launcher:
    """A live run: the scenario and the run's options, and the collaborators that run it: its sessions and
    credentials (``creds``), the node processes (``nodes``), the recorder (``recorder``), the stall and loss
    watch (``stalls``), the namespaces and link cuts (``netns``), an external node (``external``), and the
    faults they find (``faults``).  ``run`` goes through the run's phases."""

    def __init__(self, cfg: RunConfig):
        self.cfg = cfg
        self.phase("up")
        self.opts = cfg.opts
        self.sc = load_scenario(cfg.scenario, self.opts)
        if self.sc.method_note:
            print(f"testbed run: {self.sc.method_note}", file=sys.stderr)
        self.phase("scenario")
        self.sc, over = scenario.with_seed(self.sc, self.opts.overrides())
        if over.get("seed") != self.opts.seed:
            self.opts = dataclasses.replace(self.opts, seed=over["seed"])
            print(f"testbed run: the random attack has no seed; drew seed = {self.opts.seed} (recorded; "
                  f"--seed {self.opts.seed} repeats it)", file=sys.stderr)
        check_fault_times(cfg, self.sc.n_steps, self.sc.T)  # a fault past the run's end: refused
        ref = cfg.scenario
        self.scenario_ref = str(Path(ref).resolve()) if (Path(ref).suffix == ".toml" or Path(ref).exists()) else ref
        self.run_id = cfg.run_id or f"{self.sc.name}-{os.getpid()}-{secrets.token_hex(3)}"
        self.keys = transport.Keys.for_run(self.run_id)
        self.netns = netns.plan(cfg, self.run_id, self.opts)  # testbed run --netns: its namespaces and endpoints
        if self.netns is not None:
            eps = self.netns.endpoints(cfg)  # the launcher's listener is its session's; the nodes' are by role
            cfg = self.cfg = dataclasses.replace(cfg, session=dataclasses.replace(cfg.session, listen=(eps.pop("listen"),)),
                                                 **eps)
        self.colocated = self.opts.colocate           # roles run inside another node's process
        self.creds = RunCredentials(cfg, self.run_id, self.keys, self.colocated)  # topology, endpoints, secrets
        self.processes = self.opts.processes          # the node processes
        self.cpus = cfg.cpu
        for who, spec in self.cpus.items():
            parse_cpus(spec)  # one clear line now if unusable
            if who in self.colocated:
                raise BadInput(f"--cpu {who}=...: the {who} runs in the {self.opts.process_of(who)}'s process "
                               f"(--colocate {who}); pin that one")
        stalls = parse_stalls(cfg.stall, self.colocated)  # --stall (``stalls``)
        self.record_path = None if cfg.no_record else Path(cfg.out or recording_default_path(self.sc.name,
                                                                                              self.run_id))
        if self.record_path is not None and self.record_path.exists() and not cfg.force:
            raise BadInput(f"{self.record_path} exists: a recording is never overwritten (remove it, choose "
                           "another --out, or pass --force)")
        self.creds.check()
        self.rerun = None                                              # testbed run --rerun / --rrd
        if cfg.rerun or cfg.rrd:
            from ..view.rerun import LiveRerun

            self.rerun = LiveRerun.from_options(cfg.rerun, cfg.rrd, cfg.roa, self.sc, self.run_id)
        self.foxglove = None                                           # testbed run --foxglove PORT
        if cfg.foxglove is not None:
            from .foxglove_tap import FoxgloveLive

            self.foxglove = FoxgloveLive(self.sc, self.run_id, cfg.foxglove)
        self.external = external.check(cfg, self.colocated)  # --external ROLE: a node from outside (join file)
        # the run folder last: a run refused above (bad input) leaves nothing behind
        self.own_dir = cfg.run_dir is None
        self.run_dir = Path(cfg.run_dir or tempfile.mkdtemp(prefix="testbed-run-"))
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.faults = FaultLog()
        self.nodes = NodeProcesses(run_dir=self.run_dir, processes=self.processes, colocated=self.colocated,
                                   process_of=self.opts.process_of, node_prefix=cfg.node_prefix,
                                   fork=cfg.spawn == "fork", external=self.external, command=self.command,
                                   faults=self.faults)
        self.stalls = StallControl(stalls, self.colocated, self.external, self.nodes, self.faults)
        self.recorder = None if self.record_path is None else \
            RecorderProcess(self.record_path, self.run_dir, self.faults, cfg.on_record_error)
        self.fifo = cfg.sched_fifo(self.sc.T)  # --realtime, read once: the nodes' loops and the router
        self.router = RouterPriority(self.fifo)
        self.signal: int | None = None
        self.t0_mono: int | None = None               # sample 0's time, CLOCK_MONOTONIC ns
        self.status: status.LiveStatus | None = None  # the live status line (``status``): a terminal or --progress
        self.device_watch: DeviceWatch | None = None  # what the plant (a device) does wrong (``devicefaults``)
        self._method_fault: str | None = None         # the outcome once a node reported a method fault
        self._events_seen = 0
        self._collector_ready = False
        self._tokens: list = []

    def phase(self, name: str) -> None:
        """A milestone on stderr with ``-v`` (``benchmarks/bench_startup.py`` reads them): when, the CPU used, the
        peak memory (MB) of this process and of the largest child it reaped so far."""
        if self.cfg.verbose:
            import resource

            from ..nodes.process import process_age

            children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024  # the largest reaped child's
            print(f"testbed run: phase {name} t={time.time():.6f} age={process_age():.3f} cpu={time.process_time():.3f}"
                  f" hwm={peak_rss_mb() or 0:.1f} children_hwm={children:.1f}", file=sys.stderr, flush=True)

    # ---- what each process runs
    def node_config(self, role: str) -> NodeConfig:
        """What the node process ``role`` runs: the run's options, its session and its own settings."""
        c = self.cfg
        guest_crash: dict[str, Any] = {f"{g}_crash_at": c.crash[g] for g in self.colocated
                       if self.opts.process_of(g) == role and g in c.crash}  # --encoder-crash-at
        here = role not in c.node_prefix or c.node_prefix[role].startswith("ip netns exec")
        rx: dict[str, Any] = {"rx": c.rx} if c.rx else {}
        rerun: dict[str, Any] = {} if self.rerun is None else {"recording_id": self.rerun.recording_id, **(
            {"rerun_save": self.rerun.part(role)} if self.rerun.mode == "save" else {"rerun_url": self.rerun.url})}
        return NodeConfig(
            role=role, scenario=self.scenario_ref, opts=self.opts, session=self.creds.session_options(role),
            ready_timeout=c.startup_timeout + STARTUP_GRACE_S, launched=True, **rx, rx_spin_us=c.rx_spin_us,
            cpus=self.cpus.get(role), parent_pid=os.getpid() if here else None, realtime=self.fifo,
            verbose=c.verbose, crash_at=c.crash.get(role), **guest_crash, **rerun,
            spin_us=c.spin_us if role == "plant" else None,
            ack_grace=c.ack_grace if role == "encoder" or self.opts.process_of("encoder") == role else None,
            corrupt=c.corrupt if role == "attacker" else None)

    def command(self, role: str) -> list[str]:
        """The node's command line: ``testbed node`` with its ``NodeConfig`` as flags, under its ``--node-prefix``."""
        return [*shlex.split(self.cfg.node_prefix.get(role, "")), sys.executable, "-P", "-m", "testbed.cli",
                *self.node_config(role).argv()]

    def recorder_config(self) -> RecorderConfig:
        """What the recorder process runs: the run's options, its session, the file."""
        c = self.cfg
        return RecorderConfig(scenario=self.scenario_ref, opts=self.opts,
                              session=self.creds.session_options(transport.RECORDER),
                              out=str(self.record_path), loop=c.record_loop, launched=True, parent_pid=os.getpid(),
                              scenario_ref=c.scenario, force=c.force, cpus=self.cpus.get(transport.RECORDER),
                              verbose=c.verbose)

    # ---- the run's phases
    def run(self) -> tuple[int, dict]:
        """The run: prepare, open the session (the run's router), start, loop, stop, summarize, close; the
        cleanup (recorder, namespaces, credentials, join file, signal handlers) in reverse order whatever
        happens.  Returns the exit code and the summary."""
        import zenoh  # noqa: F401 - loaded before the signal handlers and the forks, as ever

        with contextlib.ExitStack() as cleanup:
            self.prepare(cleanup)
            session = self.open_session(cleanup)
            col = self.collect(session)
            outcome = "?"
            try:
                self.start(session)
                outcome = self.loop(session, col)
                self.phase("watched")
            finally:
                outcome = self.stop(session, col, outcome)
            summary = self.summarize(session, col, outcome)
            self.close(session, summary)
        return self.finish(summary)

    def prepare(self, cleanup: contextlib.ExitStack) -> None:
        """Signal handlers, CPUs, credentials, the join file, the namespaces, and the forked nodes (all before
        Zenoh starts a thread in this process)."""
        def on_signal(signum: int, _frame: object) -> None:
            self.signal = signum

        old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        cleanup.callback(lambda: [signal.signal(s, h) for s, h in old.items()])
        if transport.LAUNCHER in self.cpus:  # before Zenoh starts its threads: the router's CPUs
            os.sched_setaffinity(0, parse_cpus(self.cpus[transport.LAUNCHER]))
        cleanup.callback(self.creds.remove_secrets)
        self.creds.make_secrets(self.run_dir)  # the certificates of a TLS run are made meanwhile (``secrets_ready``)
        if self.external is not None:
            self.creds.secrets_ready()  # the join file names them
        join_path = external.write_join(self.external, self.run_dir, self.creds, self.sc, self.opts, self.cfg)
        cleanup.callback(external.remove_join, join_path)
        if not self.creds.secure:
            print(f"testbed run: INSECURE: no authentication and no access control; any local process can join, "
                  f"stop or steer run {self.run_id}", file=sys.stderr)
        if self.netns is not None:  # before Zenoh starts a thread: the launcher moves into the hub
            cleanup.callback(self.netns.down)
            self.netns.up()
        if self.recorder is not None:  # an exception below: the recorder still closes its file
            cleanup.callback(self.recorder.stop)
        self.nodes.fork_ok = self.nodes.fork_ok and "rerun" not in sys.modules  # its import starts threads
        if self.nodes.any_forked():  # before Zenoh starts any thread here
            if self.rerun is not None:
                self.rerun.prepare()  # the part files the nodes' flags name
            self.prewarm()
            self.creds.secrets_ready()
            self.nodes.spawn(forked=True)

    def open_session(self, cleanup: contextlib.ExitStack) -> zenoh.Session:
        """The launcher's session, the run's router (closed first at the end); a forked node is killed if it
        cannot open."""
        import zenoh

        try:
            self.creds.secrets_ready()
            session_cm = zenoh.open(self.creds.session_config())
        except BaseException:
            self.nodes.kill_all()
            raise
        session = cleanup.enter_context(session_cm)
        self.phase("router")
        return session

    def collect(self, session: zenoh.Session) -> Collector:
        """The collector of the nodes' telemetry, the live status line and the collector's liveliness."""
        from .collect import Collector

        col = Collector(session, self.keys, self.sc.n_steps, spill=self.run_dir / "telemetry.bin")
        self.status = status.start(self.cfg.progress, self.sc.n_steps, self.sc.T, self.sc.network)  # the live status line
        self._tokens = [session.liveliness().declare_token(self.keys.alive(transport.COLLECTOR)),
                        declare_summaries_held(session, self.keys, col)]
        return col

    def start(self, session: zenoh.Session) -> None:
        """The recorder and the nodes start together; the plant starts the run once the collector is ready,
        which it declares once the recorder is (``loop``)."""
        if self.recorder is not None:
            self.recorder.start(self.recorder_config())
        if self.rerun is not None:
            self.rerun.start()
        if self.foxglove is not None:
            self.foxglove.start(session, self.keys)
        if self.recorder is None:  # forked nodes are ready at once: the taps listen first
            self.declare_collector_ready(session)
        self.nodes.spawn(forked=False)
        self.phase("spawned")

    def loop(self, session: zenoh.Session, col: Collector) -> str:
        """Watch the run until it ends; its outcome."""
        a = self.cfg
        t_launch = time.monotonic()
        end_mono = None
        stopping_since = None
        while True:
            if self.signal is not None:
                return f"interrupted by {signal.Signals(self.signal).name}"
            if (fault := self.method_fault(col)) is not None:
                return fault
            if self.t0_mono is None and col.start is not None:
                end_mono = self.started(col.start)
            t0_mono = self.t0_mono
            self.nodes.poll(col, t0_mono, interrupted=self.signal is not None)
            if t0_mono is not None:
                self.nodes.check_guests(col, t0_mono)
            if t0_mono is None and not self.recorder_started(session, col):
                return "recorder did not start"
            self.check_recorder(t0_mono)
            self.publish_faults(session)
            if a.on_record_error == "stop" and self.faults.any("record_error"):
                return "stopped: the recording failed"
            if self.nodes.all_exited():
                return "done" if self.nodes.plant_ok(col) else "all nodes exited"
            now = time.monotonic_ns()
            if t0_mono is None:
                if time.monotonic() - t_launch > a.startup_timeout:
                    self.faults.append(Fault(role=None, kind="startup_timeout",
                                             detail=f"no start after {a.startup_timeout:g} s", alive=sorted(col.alive)))
                    return "startup timeout"
                if "plant" in self.nodes.exits:
                    return "plant exited before the start"
            else:
                if (ended := self.tick(col, now, t0_mono)) is not None:
                    return ended
                assert end_mono is not None  # set with t0 (started)
                if now > end_mono:
                    self.faults.append(Fault(role=None, kind="timeout",
                                             detail="nodes still running 10 s after the end of the run"))
                    return "timeout"
            if "plant" in self.nodes.exits or col.plant_done():
                # the plant has finished or died: the others stop on its Stop or its liveliness
                if stopping_since is None:
                    stopping_since = time.monotonic()
                    if "plant" in self.nodes.exits and not col.plant_done():
                        session.put(self.keys.stop, msg.Stop(reason="plant died", origin="launcher").encode())
                elif time.monotonic() - stopping_since > 5.0:
                    return "done" if self.nodes.plant_ok(col) else "plant died"
            time.sleep(0.01)

    def started(self, st: msg.Start) -> int:
        """The run started (the plant's ``Start``): t0 on this host's monotonic clock; the loop's deadline."""
        self.phase("start")
        if st.T_ns >= 10_000_000:  # a slow loop leaves the CPU idle: load the summary's kernels now
            threading.Thread(target=self._warm_summary, daemon=True, name="warm-summary").start()
        self.t0_mono = st.t0_ns - (time.time_ns() - time.monotonic_ns())
        self.router.set(True)
        return self.t0_mono + st.n_steps * st.T_ns + int(10e9)

    def tick(self, col: Collector, now: int, t0_mono: int) -> str | None:
        """One look during the loop: the faults to inject (``--kill``, ``--cut``, ``--stall``), the stalls and
        losses, the status line, the device's faults (the outcome if one ends the run)."""
        for role, sec in self.cfg.kill.items():
            if role not in self.nodes.kill_sent and now >= t0_mono + int(sec * 1e9):
                if role == transport.RECORDER:
                    self.nodes.kill_sent[role] = time.monotonic_ns()
                    if self.recorder is not None:
                        self.recorder.kill()
                else:
                    self.nodes.kill(role)
        if self.netns is not None:
            self.netns.tick(self.faults, now, t0_mono)  # --cut
        self.stalls.tick(col, now, t0_mono)
        if self.status is not None:
            self.status.tick(col)
        return self.device_faults(col, now, t0_mono)

    def stop(self, session: zenoh.Session, col: Collector, outcome: str) -> str:
        """Stop every node, then gather what the run's end shows: late exits and summaries, stalls, losses,
        device faults, liveliness, the recorder, an open cut; the outcome (a device fault may change it)."""
        self.router.set(False)
        self.stalls.release()  # a node still frozen by --stall
        self.nodes.stop_all(session, self.keys.stop, outcome)
        for r, p in self.nodes.procs.items():
            if r not in self.nodes.exits and (rc := p.poll()) is not None:
                self.nodes.record_exit(r, rc, col, None, interrupted=self.signal is not None)
        self.phase("stopped")
        self.nodes.wait_summaries(col)  # late telemetry and summaries
        status.stop(self.status, col)  # the status line's last state, the run's losses
        self.nodes.check_guests(col, self.t0_mono, final=True)  # one that died alone just before the end
        self.nodes.check_summaries(col)  # after the guests: one that died alone owes none
        self.stalls.end(col, self.t0_mono)
        if self.t0_mono is not None:  # what arrived as the run ended
            outcome = self.device_faults(col, time.monotonic_ns(), self.t0_mono, final=True) or outcome
        self.add_liveliness(col)
        self.check_recorder(None)
        if self.netns is not None:
            self.netns.tick(self.faults, None, self.t0_mono)  # a cut still open: restored, recorded
        self.publish_faults(session)
        return outcome

    def summarize(self, session: zenoh.Session, col: Collector, outcome: str) -> dict:
        """The run's summary (``record.summary.build_summary``) with the launcher's view: faults, nodes,
        outcome, security, the external node, the launcher itself."""
        if self.signal is None:  # every node's own account of its telemetry against what arrived
            self.faults.extend(col.telemetry_check())
            self.publish_faults(session)
        outcome = self.method_fault(col) or outcome  # one that arrived as the run ended
        from ..record.summary import LIVE_FIELDS, build_summary  # loaded meanwhile by ``_warm_summary``

        plant = self.sc.make_model()
        cb = self.sc.make_method().codebook(plant.n, self.sc.quantizer)
        nodes = self.nodes.nodes(transport.ROLES)
        # the spill read back a chunk of rows at a time (``collect.SpillRows``): every reduction made chunk by
        # chunk and the per-sample values kept in files of the run folder (``stats.Stack``), so that the end of
        # the run takes the same memory however long the run; ``testbed run --json`` streams them out
        # (``record.summary.write_json``)
        with col.lock:
            rows = col.rows(self.sc, fields=LIVE_FIELDS)
            summary = build_summary(self.sc, rows, run_id=self.run_id, ack_via_attacker=self.opts.ack_via_attacker,
                                    nodes=nodes, faults=self.faults.dicts(), codebook=cb, arrays=True,
                                    store=self.run_dir)
        if summary.get("plant_fault"):  # the true plant (an FMU) failed: say so, not "crashed"
            outcome = f"plant fault at sample {summary.get('plant_fault_at')}"
            for f in self.faults:
                if f.role == "plant" and f.kind == "crashed":
                    f.kind, f.detail = "plant_fault", summary["plant_fault"]
        self.lockstep_fault(summary)
        self.publish_faults(session)
        summary["outcome"] = outcome
        summary["security"] = self.creds.security()
        external.annotate(summary, self.external, self.faults)
        summary["faults"] = self.faults.dicts()
        summary["launcher"] = {"pid": os.getpid(), "realtime": self.cfg.realtime, "sched_fifo": self.router.fifo,
                               "spawn": "fork" if self.nodes.any_forked() else "exec",
                               # how far the records came out of the order of k (the end of run's windows)
                               "telemetry_lag": col.lag, "telemetry_lag_of": dict(col.lag_of)}
        return summary

    def close(self, session: zenoh.Session, summary: dict) -> None:
        """The launcher's own view into the recording, the recorder stopped, the live taps finished."""
        try:  # the launcher's own view (exits, faults, outcome) goes into the recording too
            launcher_view = {k: summary.get(k) for k in ("outcome", "faults", "nodes", "complete", "samples")}
            session.put(self.keys.summary("launcher"),
                        msg.NodeSummary(node="launcher", data=launcher_view).encode())
            if self.recorder is not None and self.recorder.running():
                time.sleep(0.1)
        except Exception:  # noqa: BLE001 - best effort at the end; the recorder is stopped below
            pass
        if self.recorder is not None:
            self.recorder.stop()
        self.check_recorder(None)
        summary["faults"] = self.faults.dicts()  # a write error the recorder said as it stopped
        for t in self._tokens:
            t.undeclare()
        summary["recording"] = None if self.recorder is None else self.recorder.info()
        self.phase("summary")
        if self.rerun is not None:
            self.rerun.finish()
            summary["rerun"] = self.rerun.info()
        if self.foxglove is not None:
            self.foxglove.finish(self.cfg.foxglove_linger)
            summary["foxglove"] = self.foxglove.info()

    def finish(self, summary: dict) -> tuple[int, dict]:
        """The exit code; the run folder goes after a clean run (unless given)."""
        summary["run_dir"] = str(self.run_dir)
        summary["launcher"]["peak_rss_mb"] = peak_rss_mb()  # the end of run included (benchmarks/bench_soak.py)
        summary["recording_complete"] = None if summary["recording"] is None else summary["recording"]["complete"]
        code = exit_code(self.signal, self.faults, summary, ridden=netns.RIDDEN_THROUGH)
        if code == 0 and self.own_dir:
            shutil.rmtree(self.run_dir, ignore_errors=True)
            summary["run_dir"] = None
        return code, summary

    # ---- helpers of the phases
    def declare_collector_ready(self, session: zenoh.Session) -> None:
        """The plant starts the run once the collector is ready (with a recorder: once it is ready too)."""
        if not self._collector_ready:
            self._collector_ready = True
            self._tokens.append(session.liveliness().declare_token(self.keys.ready(transport.COLLECTOR)))

    def recorder_started(self, session: zenoh.Session, col: Collector) -> bool:
        """During start-up: declare the collector ready once the recorder is (False: it died first)."""
        if self._collector_ready or self.recorder is None:
            return True
        st = self.recorder.startup(col)
        if st == "ready":
            self.declare_collector_ready(session)
        return st != "failed"

    def check_recorder(self, t0_mono: int | None) -> None:
        if self.recorder is not None:
            self.recorder.check(t0_mono, stopping=self.nodes.stopping,
                                injected=transport.RECORDER in self.nodes.kill_sent)

    def publish_faults(self, session: zenoh.Session) -> None:
        """Each new fault as an ``Event`` of node ``launcher`` (so the recording has it)."""
        self.faults.publish(session, self.keys.events("launcher"))

    def _warm_summary(self) -> None:
        """Load the summary's kernels (the region-of-attraction check) while a slow loop runs, at low
        priority, so that the summary is quick once the run is over (a fast loop is left alone)."""
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
        except (OSError, AttributeError):
            pass
        try:
            import numpy as np

            from ..record import summary  # noqa: F401 - loaded early, in this idle thread, not at the end of the run
            from ..sim.batch import in_nominal_roa

            model = self.sc.make_model()
            in_nominal_roa(model, self.sc.K, self.sc.T, np.zeros((1, model.n)), horizon=2 * self.sc.T,
                           flow=self.sc.flow)
        except Exception:  # noqa: BLE001 - only a warm-up: the summary computes it anyway
            pass

    def prewarm(self) -> None:
        """Before forking the nodes: load numba and the loop's compiled kernels once, here, so that
        no forked node loads them again (about 0.3 s of import and 0.6 s of kernel loading each)."""
        try:
            self._prewarm()
        except Exception:  # noqa: BLE001 - only a warm-up: each node loads what it needs anyway, and says why not
            pass
        self.phase("prewarmed")

    def _prewarm(self) -> None:
        from ..nodes import controller, encoder, plant  # imported once, for every forked node

        sc = self.sc
        model = sc.make_model()
        encoder.warm_kernels(sc, model)
        controller.warm_kernels(sc, model)
        if sc.plant.fmu is None:  # an FMU is opened by the plant node alone
            plant.warm_process(sc)

    def add_liveliness(self, col: Collector) -> None:
        """When each dead node's liveliness token went away (it may trail the process exit)."""
        kill_sent = self.nodes.kill_sent
        for f in self.faults:
            role = f.role
            if role is None or f.kind in ("stalled", *DEVICE_FAULTS):  # it went on; its token goes at the end
                continue
            if f.kind == "link_cut":  # the session ended only if the token went during the cut
                f.liveliness_lost = lost_during(col, role, f.down_s, f.up_s, self.t0_mono)
                continue
            lost = col.lost_at(role)
            f.liveliness_lost = lost is not None
            if lost is not None and role in kill_sent:
                f.liveliness_detect_ms = round((lost - kill_sent[role]) / 1e6, 3)

    def method_fault(self, col: Collector) -> str | None:
        """A node's ``method_fault`` event (its method's end raised at sample k): one fault, one stderr line
        (the line ``testbed simulate`` prints), and the outcome that ends the run; None without one."""
        if self._method_fault is None:
            evs = col.events
            n = len(evs)
            e = next((evs[i] for i in range(self._events_seen, n) if evs[i].kind == "method_fault"), None)
            self._events_seen = n
            if e is None:
                return None
            self._method_fault = f"method fault at sample {e.k}"
            self.faults.append(Fault(role=e.node, kind="method_fault", detail=e.detail, sample=int(e.k)))
            print(f"testbed run: {e.detail}", file=sys.stderr)
        return self._method_fault

    def lockstep_fault(self, summary: dict) -> None:
        """The method's ends held different shared state (``lockstep_breaks``, from the recorded xi_k, E_k):
        a fault at its first sample and the stderr line of ``testbed simulate``."""
        br = summary.get("lockstep_breaks") or []
        if not br:
            return
        line = (f"method {self.sc.method.name!r} broke lockstep: its encoder and decoder disagree from sample "
                f"{br[0]} ({len(br)} samples)")
        self.faults.append(Fault(role=None, kind="lockstep_break", detail=line, sample=int(br[0])))
        print(f"testbed run: {line}", file=sys.stderr)

    def device_faults(self, col: Collector, now: int, t0_mono: int, *, final: bool = False) -> str | None:
        """The plant's device faults (``DeviceWatch``; its loss: ``lost``): the outcome if one ends the run."""
        if self.device_watch is None:
            assert col.start is not None  # called from the start on (t0_mono)
            self.device_watch = DeviceWatch(col.start, self.sc.run.deadline, self.external == "plant")
        self.faults.extend(self.device_watch.tick(col, now - t0_mono, final=final))
        f = self.device_watch.ends_run() or (self.stalls.lost.get("plant") if self.external == "plant" else None)
        return None if f is None else f"plant {f.kind} at sample {f.sample}"
