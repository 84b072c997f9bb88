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

import dataclasses
import json
import os
import secrets
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from .. import scenario
from ..errors import BadInput
from ..nodes.options import NodeConfig, RunConfig, load_scenario
from ..nodes.process import parse_cpus, peak_rss_mb
from ..wire import messages as msg
from ..wire import transport
from . import external, netns, status
from .credentials import RunCredentials, choose_topology
from .devicefaults import DEVICE_FAULTS, DeviceWatch
from .recorder import RecorderControl, exit_code
from .spawn import Forked, _forked_node
from .stalls import Stalls, check_fault_times


def recording_default_path(name: str, run_id: str) -> Path:
    from ..record.recording import default_path

    return default_path(name, run_id=run_id)


class Launcher(RunCredentials, Stalls, RecorderControl):
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
            cfg = self.cfg = dataclasses.replace(cfg, **self.netns.endpoints(cfg))
        self.topology, self.topology_why = choose_topology(cfg)  # --topology auto: peer on one host
        self.secure = not cfg.insecure
        # mutual TLS links (``TlsCredentials``): the peer topology, or the router topology given --tls-dir
        self.tls = self.secure and (self.topology == "peer" or (bool(cfg.tls_dir) and not cfg.secret_file))
        self.listen = cfg.listen or f"{'tls' if self.tls else 'tcp'}/127.0.0.1:{transport.free_port()}"
        self.node_connect = cfg.node_connect or self.listen
        self.node_listen = cfg.node_listen
        self.node_prefix = cfg.node_prefix
        self.kills = cfg.kill
        self.crashes = cfg.crash
        self.colocated = self.opts.colocate           # roles run inside another node's process
        self.init_stalls(cfg.stall)                   # --stall, and the watch for stalled nodes (``stalls``)
        self.t0_mono: int | None = None               # sample 0's time, CLOCK_MONOTONIC ns
        self.fork_ok = cfg.spawn == "fork"            # --spawn fork (``forks``)
        self.processes = self.opts.processes          # the node processes
        self.cpus = cfg.cpu
        for who, spec in self.cpus.items():
            parse_cpus(spec)  # one clear line now if unusable
            if who in self.colocated:
                raise BadInput(f"--cpu {who}=...: the {who} runs in the {self.opts.process_of(who)}'s process "
                               f"(--colocate {who}); pin that one")
        self.procs: dict[str, subprocess.Popen] = {}
        self.exits: dict[str, dict] = {}
        self.faults: list[dict] = []
        self.kill_sent: dict[str, int] = {}
        self.signal: int | None = None
        self.stopping = False
        self.record_path = None if cfg.no_record else Path(cfg.out or recording_default_path(self.sc.name,
                                                                                              self.run_id))
        if self.record_path is not None and self.record_path.exists() and not cfg.force:
            raise BadInput(f"{self.record_path} exists: a recording is never overwritten (remove it, choose "
                           "another --out, or pass --force)")
        if self.tls:
            if cfg.secret_file:
                raise BadInput("--secret-file: the peer topology's credentials are TLS certificates (--tls-dir DIR, "
                               "made with 'testbed secret --tls DIR'; by default made for the run)")
            transport.require_tls((self.listen, self.node_connect, *self.node_listen.values()))
        elif cfg.tls_dir:
            raise BadInput("--tls-dir with --secret-file: the router topology authenticates by one of them")
        self.secret_dir = None
        self.secret_path: Path | None = None
        self.tls_dir: Path | None = None              # the peer topology's TLS folder (``make_secrets``)
        self.recorder: subprocess.Popen | None = None
        self.recorder_exit: dict | None = None
        self._faults_published = 0
        self._method_fault: str | None = None       # the outcome once a node reported a method fault
        self.device_watch: DeviceWatch | None = None  # what the plant (a device) does wrong (``devicefaults``)
        self._events_seen = 0
        self._collector_ready = False
        self._router_rt = False                       # SCHED_FIFO now (``router_realtime``)
        self.router_fifo = False                      # ... at some point of the run (the summary's ``launcher``)
        self._tokens: list = []
        self.status = None                            # the live status line (``status``): a terminal or --progress
        self.rerun = None                                              # testbed run --rerun / --rrd
        if cfg.rerun or cfg.rrd:
            from ..view.rerun import LiveRerun

            self.rerun = LiveRerun.from_options(cfg.rerun, cfg.rrd, cfg.roa, self.sc, self.run_id)
        self.foxglove = None                                           # testbed run --foxglove PORT
        if cfg.foxglove is not None:
            from .foxglove_tap import FoxgloveLive

            self.foxglove = FoxgloveLive(self.sc, self.run_id, cfg.foxglove)
        self.external = external.check(self)           # --external ROLE: a node from outside (join file)
        # the run folder last: a run refused above (bad input) leaves nothing behind
        self.own_dir = cfg.run_dir is None
        self.run_dir = Path(cfg.run_dir or tempfile.mkdtemp(prefix="testbed-run-"))
        self.run_dir.mkdir(parents=True, exist_ok=True)

    def phase(self, name: str) -> None:
        """A milestone on stderr with ``-v`` (``benchmarks/bench_startup.py`` reads them)."""
        if self.cfg.verbose:
            from ..nodes.process import process_age

            print(f"testbed run: phase {name} t={time.time():.6f} age={process_age():.3f} cpu={time.process_time():.3f}",
                  file=sys.stderr, flush=True)

    # ---- processes
    def node_config(self, role: str) -> NodeConfig:
        """What the node process ``role`` runs: the run's options, its session and its own settings."""
        c = self.cfg
        guest_crash = {f"{g}_crash_at": self.crashes[g] for g in self.colocated
                       if self.opts.process_of(g) == role and g in self.crashes}  # --encoder-crash-at
        here = role not in self.node_prefix or self.node_prefix[role].startswith("ip netns exec")
        rerun = {} if self.rerun is None else {"recording_id": self.rerun.recording_id, **(
            {"rerun_save": self.rerun.part(role)} if self.rerun.mode == "save" else {"rerun_url": self.rerun.url})}
        return NodeConfig(
            role=role, scenario=self.scenario_ref, opts=self.opts, session=self.session_options(role),
            ready_timeout=c.startup_timeout, launched=True, **({"rx": c.rx} if c.rx else {}), rx_spin_us=c.rx_spin_us,
            cpus=self.cpus.get(role), parent_pid=os.getpid() if here else None, realtime=c.realtime,
            verbose=c.verbose, crash_at=self.crashes.get(role), **guest_crash, **rerun,
            spin_us=c.spin_us if role == "plant" else None,
            ack_grace=c.ack_grace if role == "encoder" or self.opts.process_of("encoder") == role else None,
            corrupt=c.corrupt if role == "attacker" else None)

    def command(self, role: str) -> list[str]:
        """The node's command line: ``testbed node`` with its ``NodeConfig`` as flags, under its ``--node-prefix``."""
        return [*shlex.split(self.node_prefix.get(role, "")), sys.executable, "-P", "-m", "testbed.cli",
                *self.node_config(role).argv()]

    def declare_collector_ready(self, session) -> None:
        """The plant starts the run once the collector is ready (with a recorder: once it is ready too)."""
        if not self._collector_ready:
            self._collector_ready = True
            self._tokens.append(session.liveliness().declare_token(self.keys.ready(transport.COLLECTOR)))

    def wait_summaries(self, col, timeout: float = 0.3) -> None:
        """Until every node that exited cleanly has its summary in (they publish it before they exit)."""
        want = {r for r, e in self.exits.items() if e.get("exit_code") == 0 and r in self.procs}
        want |= {g for g in self.colocated if self.opts.process_of(g) in want and g not in self.exits}
        end = time.monotonic() + timeout
        while time.monotonic() < end and not want <= set(col.snapshot_summaries()):
            time.sleep(0.01)

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

    def publish_faults(self, session) -> None:
        """Each new fault as an ``Event`` of node ``launcher`` (so the recording has it)."""
        while self._faults_published < len(self.faults):
            f = self.faults[self._faults_published]
            self._faults_published += 1
            k = f.get("at_sample")
            e = msg.Event(node="launcher", kind=f"{f.get('node') or 'run'}_{f['kind']}",
                          k=-1 if k is None else int(k), detail=json.dumps(f, default=str))
            try:
                session.put(self.keys.events("launcher"), e.encode())
            except Exception:  # noqa: BLE001 - the session may be closing
                pass

    def _popen(self, cmd: list[str], name: str) -> subprocess.Popen:
        """A child in its own session and process group, its output in ``<run dir>/<name>.log``."""
        env = dict(os.environ)
        env.setdefault("PYTHONUNBUFFERED", "1")
        with open(self.run_dir / f"{name}.log", "wb") as log:
            return subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                    start_new_session=True, env=env)

    def forks(self, role: str) -> bool:
        """Whether ``role`` is forked from the launcher (``--spawn fork``, and no ``--node-prefix`` for it).

        Only while the launcher has started no threads of a library (Zenoh's session, rerun's
        streams: a fork copies none of them, and a lock one of them held stays held in the child);
        ``run`` forks before it opens its session, and nothing imports rerun before that."""
        return self.fork_ok and role not in self.node_prefix

    def spawn(self, *, forked: bool) -> None:
        """Start the node processes that are forked (before the launcher has any Zenoh thread) or exec'd."""
        for role in self.processes:
            if self.forks(role) == forked and role not in self.procs and role != self.external:
                self.procs[role] = self._fork(role) if forked else self._popen(self.command(role), role)

    def _fork(self, role: str) -> Forked:
        import gc

        cmd = self.command(role)
        argv = cmd[cmd.index("testbed.cli") + 1:]
        gc.freeze()  # the launcher's objects: the child's collector never walks them (nor copies their pages)
        log_fd = os.open(self.run_dir / f"{role}.log", os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            _forked_node(argv, log_fd)  # never returns
        os.close(log_fd)
        return Forked(pid)

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

    def _signal_group(self, role: str, sig: int) -> None:
        p = self.procs[role]
        if p.poll() is None:
            try:
                os.killpg(p.pid, sig)
            except ProcessLookupError:
                pass

    def stop_all(self, session, reason: str, grace: float = 3.0) -> None:
        self.stopping = True
        alive = [r for r, p in self.procs.items() if p.poll() is None]
        if not alive:
            return
        try:
            session.put(self.keys.stop, msg.Stop(reason=reason, origin="launcher").encode())
        except Exception:  # noqa: BLE001 - the stop is best effort; the processes are stopped below
            pass
        end = time.monotonic() + grace
        while time.monotonic() < end and any(self.procs[r].poll() is None for r in alive):
            time.sleep(0.02)
        for r in alive:
            self._signal_group(r, signal.SIGINT)
        end = time.monotonic() + grace
        while time.monotonic() < end and any(self.procs[r].poll() is None for r in alive):
            time.sleep(0.02)
        for r in alive:
            self._signal_group(r, signal.SIGKILL)
        for r in alive:
            try:
                self.procs[r].wait(5)
            except subprocess.TimeoutExpired:
                pass

    def log_tail(self, role: str, lines: int = 6) -> str:
        try:
            text = (self.run_dir / f"{role}.log").read_text(errors="replace")
        except OSError:
            return ""
        return "\n".join(text.rstrip().splitlines()[-lines:])

    # ---- watching
    def record_exit(self, role: str, rc: int, col, t0_mono: int | None) -> None:
        now = time.monotonic_ns()
        info = {"exit_code": rc, "signal": signal.Signals(-rc).name if rc < 0 else None,
                "at_sample": col.last_k(role),
                "t_s": None if t0_mono is None else round((now - t0_mono) / 1e9, 4)}
        self.exits[role] = info
        plant_done = col.plant_done()
        injected = role in self.kill_sent
        asked = self.signal is not None or self.stopping or plant_done
        abnormal = rc != 0 and not (asked and rc in (130, 143, -2, -15))
        if abnormal:
            why = f"killed by {info['signal']}" if rc < 0 else f"exit code {rc}"
            tail = self.log_tail(role)
            last = tail.splitlines()[-1] if tail else ""
            fault = {"node": role, "kind": "killed" if rc < 0 else "crashed", "why": why,
                     "last_log_line": last, "exit_code": rc, "signal": info["signal"],
                     "at_sample": info["at_sample"], "t_s": info["t_s"], "injected": injected}
            self.faults.append(fault)
            print(f"testbed run: node {role} died ({why}) at sample {info['at_sample']}"
                  + (f": {last}" if last else ""), file=sys.stderr)

    #: a colocated role's liveliness loss without a crash counts as its death only this long after:
    #: its host also closes it at the run's end, and that loss can arrive before the plant's Stop
    GUEST_GRACE_NS = 500_000_000

    def check_guest(self, role: str, col, t0_mono: int | None, *, final: bool = False) -> None:
        """A colocated role whose liveliness went while its host runs on: it died alone (killed or crashed).

        At the run's end its host closes it as well, after its summary and the plant's Stop, which
        may still be on their way when the liveliness loss arrives: a loss without a crash event
        counts once ``GUEST_GRACE_NS`` has passed with neither in, or (``final``, after the
        summaries were waited for) when the host exited cleanly and published its summary but the
        role's, which the host publishes first, never came.
        """
        host = self.opts.process_of(role)
        lost = col.lost_at(role)
        if lost is None or t0_mono is None:
            return
        crash = col.event_of(role, "crash")
        if final:
            if self.exits.get(host, {}).get("exit_code") != 0:
                return  # the host itself died or was stopped: its fault says it
            got = col.snapshot_summaries()
            if crash is None and (role in got or host not in got):
                return  # closed by its host at the end (its account is published before the host's)
        else:
            if host in self.exits or col.plant_done():
                return
            if crash is None and (time.monotonic_ns() - lost < self.GUEST_GRACE_NS
                                  or role in col.snapshot_summaries()):
                return
        injected = role in self.kill_sent
        why = (f"exception: {crash.detail}" if crash is not None else
               f"killed (colocated in the {host}: the {role} alone stopped)")
        info = {"exit_code": None, "signal": None if crash is not None else "SIGKILL",
                "at_sample": col.last_k(role), "t_s": round((lost - t0_mono) / 1e9, 4), "colocated_in": host}
        self.exits[role] = info
        self.faults.append({"node": role, "kind": "crashed" if crash is not None else "killed", "why": why,
                            "last_log_line": (self.log_tail(host).splitlines() or [""])[-1],
                            "exit_code": None, "signal": info["signal"], "at_sample": info["at_sample"],
                            "t_s": info["t_s"], "injected": injected, "colocated_in": host})
        print(f"testbed run: node {role} died ({why}) at sample {info['at_sample']}", file=sys.stderr)

    def router_realtime(self, on: bool) -> None:
        """With ``--realtime``, the launcher's threads (the run's router) run under SCHED_FIFO during the
        loop as the nodes' do: a router thread at normal priority waits behind every other process for
        each message it forwards."""
        from ..nodes.process import set_realtime

        if not self.cfg.realtime or on == self._router_rt:
            return
        if on:
            self._router_rt = set_realtime(True)
            self.router_fifo = self.router_fifo or self._router_rt
        else:
            set_realtime(False)
            self._router_rt = False

    def _plant_ok(self, col) -> bool:
        return col.plant_done() or self.exits.get("plant", {}).get("exit_code") == 0

    def add_liveliness(self, col) -> None:
        """When each dead node's liveliness token went away (it may trail the process exit)."""
        for f in self.faults:
            role = f.get("node")
            if role is None or f["kind"] in ("stalled", *DEVICE_FAULTS):  # it went on; its token goes at the end
                continue
            if f["kind"] == "link_cut":  # the session ended only if the token went during the cut
                f["liveliness_lost"] = self.lost_during(col, role, f["down_s"], f["up_s"])
                continue
            lost = col.lost_at(role)
            f["liveliness_lost"] = lost is not None
            if lost is not None and role in self.kill_sent:
                f["liveliness_detect_ms"] = round((lost - self.kill_sent[role]) / 1e6, 3)

    def method_fault(self, col) -> str | None:
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
            self.faults.append({"node": e.node, "kind": "method_fault", "why": e.detail, "at_sample": int(e.k)})
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
        f = {"node": None, "kind": "lockstep_break", "why": line, "at_sample": int(br[0])}
        self.faults.append(f)
        summary["faults"] = self.faults
        print(f"testbed run: {line}", file=sys.stderr)

    def device_faults(self, col, now: int, t0_mono: int, *, final: bool = False) -> str | None:
        """The plant's device faults (``DeviceWatch``; its loss: ``lost``): the outcome if one ends the run."""
        if self.device_watch is None:
            self.device_watch = DeviceWatch(col.start, self.sc.run.deadline, self.external == "plant")
        self.faults.extend(self.device_watch.tick(col, now - t0_mono, final=final))
        f = self.device_watch.ends_run() or (self._lost.get("plant") if self.external == "plant" else None)
        return None if f is None else f"plant {f['kind']} at sample {f['at_sample']}"

    def watch(self, session, col) -> str:
        a = self.cfg
        t_launch = time.monotonic()
        t0_mono = None
        end_mono = None
        stopping_since = None
        while True:
            if self.signal is not None:
                return f"interrupted by {signal.Signals(self.signal).name}"
            if self.method_fault(col):
                return self._method_fault
            if t0_mono is None and col.start is not None:
                st = col.start
                self.phase("start")
                if st.T_ns >= 10_000_000:  # a slow loop leaves the CPU idle: load the summary's kernels now
                    threading.Thread(target=self._warm_summary, daemon=True, name="warm-summary").start()
                t0_mono = st.t0_ns - (time.time_ns() - time.monotonic_ns())
                self.t0_mono = t0_mono
                self.router_realtime(True)
                end_mono = t0_mono + st.n_steps * st.T_ns + int(10e9)
            for role, p in self.procs.items():
                rc = p.poll()
                if rc is not None and role not in self.exits:
                    self.record_exit(role, rc, col, t0_mono)
            if t0_mono is not None:
                for guest in self.colocated:
                    if guest not in self.exits:
                        self.check_guest(guest, col, t0_mono)
            if t0_mono is None and not self.recorder_started(session, col):
                return "recorder did not start"
            self.check_recorder(col, t0_mono)
            self.publish_faults(session)
            if a.on_record_error == "stop" and any(f["kind"] == "record_error"
                                                                           for f in self.faults):
                return "stopped: the recording failed"
            if all(r in self.exits for r in self.procs):
                return "done" if self._plant_ok(col) else "all nodes exited"
            now = time.monotonic_ns()
            if t0_mono is None:
                if time.monotonic() - t_launch > a.startup_timeout:
                    self.faults.append({"node": None, "kind": "startup_timeout",
                                        "why": f"no start after {a.startup_timeout:g} s",
                                        "alive": sorted(col.alive)})
                    return "startup timeout"
                if "plant" in self.exits:
                    return "plant exited before the start"
            else:
                for role, sec in self.kills.items():
                    if role not in self.kill_sent and now >= t0_mono + int(sec * 1e9):
                        self.kill_sent[role] = time.monotonic_ns()
                        if role == transport.RECORDER:
                            if self.recorder is not None and self.recorder.poll() is None:
                                os.killpg(self.recorder.pid, signal.SIGKILL)
                        elif role in self.colocated:  # its host process kills it alone (SIGUSR2)
                            self._signal_group(self.opts.process_of(role), signal.SIGUSR2)
                        else:
                            self._signal_group(role, signal.SIGKILL)
                if self.netns is not None:
                    self.netns.tick(self.faults, now, t0_mono)  # --cut
                self.stalls_tick(col, now, t0_mono)
                if self.status is not None:
                    self.status.tick(col)
                if (ended := self.device_faults(col, now, t0_mono)) is not None:
                    return ended
                if now > end_mono:
                    self.faults.append({"node": None, "kind": "timeout",
                                        "why": "nodes still running 10 s after the end of the run"})
                    return "timeout"
            if "plant" in self.exits or col.plant_done():
                # the plant has finished or died: the others stop on its Stop or its liveliness
                if stopping_since is None:
                    stopping_since = time.monotonic()
                    if "plant" in self.exits and not col.plant_done():
                        session.put(self.keys.stop, msg.Stop(reason="plant died", origin="launcher").encode())
                elif time.monotonic() - stopping_since > 5.0:
                    return "done" if self._plant_ok(col) else "plant died"
            time.sleep(0.01)

    def run(self) -> tuple[int, dict]:
        import zenoh

        from .collect import Collector

        def on_signal(signum, _frame):
            self.signal = signum

        old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        if transport.LAUNCHER in self.cpus:  # before Zenoh starts its threads: the router's CPUs
            os.sched_setaffinity(0, parse_cpus(self.cpus[transport.LAUNCHER]))
        self.make_secrets()  # the certificates of a TLS run are made meanwhile (``secrets_ready``)
        if self.external is not None:
            self.secrets_ready()  # the join file names them
        join_path = external.write_join(self)
        if not self.secure:
            print(f"testbed run: INSECURE: no authentication and no access control; any local process can join, "
                  f"stop or steer run {self.run_id}", file=sys.stderr)
        outcome = "?"
        try:
            if self.netns is not None:  # before Zenoh starts a thread: the launcher moves into the hub
                self.netns.up()
            self.fork_ok = self.fork_ok and "rerun" not in sys.modules  # its import starts threads
            if any(self.forks(r) for r in self.processes):  # before Zenoh starts any thread here
                if self.rerun is not None:
                    self.rerun.prepare()  # the part files the nodes' flags name
                self.prewarm()
                self.secrets_ready()
                self.spawn(forked=True)
            try:
                self.secrets_ready()
                session_cm = zenoh.open(self.session_config())
            except BaseException:
                for r in self.procs:
                    self._signal_group(r, signal.SIGKILL)
                raise
            with session_cm as session:
                self.phase("router")
                col = Collector(session, self.keys, self.sc.n_steps, spill=self.run_dir / "telemetry.bin")
                self.status = status.start(self.cfg.progress, self.sc.n_steps, self.sc.T, self.sc.network)  # the live status line
                tokens = [session.liveliness().declare_token(self.keys.alive(transport.COLLECTOR))]
                self._tokens = tokens
                try:
                    # the recorder and the nodes start together; the plant starts the run once the
                    # collector is ready, which it declares once the recorder is (``watch``)
                    if self.record_path is not None:
                        self.recorder = self._popen(self.recorder_command(), transport.RECORDER)
                    if self.rerun is not None:
                        self.rerun.start()
                    if self.foxglove is not None:
                        self.foxglove.start(session, self.keys)
                    if self.record_path is None:  # forked nodes are ready at once: the taps listen first
                        self.declare_collector_ready(session)
                    self.spawn(forked=False)
                    self.phase("spawned")
                    outcome = self.watch(session, col)
                    self.phase("watched")
                finally:
                    self.router_realtime(False)
                    self.stall_inject.release(self.procs)  # a node still frozen by --stall
                    self.stop_all(session, outcome)
                    for r, p in self.procs.items():
                        if r not in self.exits and p.poll() is not None:
                            self.record_exit(r, p.returncode, col, None)
                    self.phase("stopped")
                    self.wait_summaries(col)  # late telemetry and summaries
                    status.stop(self.status, col)  # the status line's last state, the run's losses
                    for guest in self.colocated:  # one that died alone just before the end
                        if guest not in self.exits:
                            self.check_guest(guest, col, self.t0_mono, final=True)
                    self.stalls_end(col)
                    if self.t0_mono is not None:  # what arrived as the run ended
                        outcome = self.device_faults(col, time.monotonic_ns(), self.t0_mono, final=True) or outcome
                    self.add_liveliness(col)
                    self.check_recorder(col, None)
                    if self.netns is not None:
                        self.netns.tick(self.faults, None, self.t0_mono)  # a cut still open: restored, recorded
                    self.publish_faults(session)
                if self.signal is None:  # every node's own account of its telemetry against what arrived
                    self.faults.extend(col.telemetry_check())
                    self.publish_faults(session)
                outcome = self.method_fault(col) or outcome  # one that arrived as the run ended
                from ..record.summary import LIVE_FIELDS, build_summary  # loaded meanwhile by ``_warm_summary``

                plant = self.sc.make_model()
                cb = self.sc.make_method().codebook(plant.n, self.sc.quantizer)
                nodes = {r: dict(self.exits.get(r, {}), log=str(self.run_dir / f"{r}.log")) for r in self.processes}
                for r in self.colocated:  # a role inside another process: that process's exit, unless it died alone
                    host = self.opts.process_of(r)
                    nodes[r] = dict(self.exits.get(r) or self.exits.get(host, {}), colocated_in=host,
                                    log=str(self.run_dir / f"{host}.log"))
                nodes = {r: nodes[r] for r in transport.ROLES}
                # the spill read back a chunk at a time into the report's columns; the per-sample values stay
                # numpy arrays (``testbed run --json`` streams them out: ``record.summary.write_json``)
                summary = build_summary(self.sc, col.snapshot(self.sc, fields=LIVE_FIELDS), run_id=self.run_id,
                                        ack_via_attacker=self.opts.ack_via_attacker, nodes=nodes,
                                        faults=self.faults, codebook=cb, arrays=True)
                if summary.get("plant_fault"):  # the true plant (an FMU) failed: say so, not "crashed"
                    outcome = f"plant fault at sample {summary.get('plant_fault_at')}"
                    for f in (*self.faults, *summary["faults"]):
                        if f.get("node") == "plant" and f.get("kind") == "crashed":
                            f.update(kind="plant_fault", why=summary["plant_fault"])
                self.lockstep_fault(summary)
                self.publish_faults(session)
                summary["outcome"] = outcome
                summary["security"] = self.security()
                external.annotate(summary, self.external)
                summary["launcher"] = {"pid": os.getpid(), "sched_fifo": self.router_fifo,
                                       "spawn": "fork" if any(self.forks(r) for r in self.processes) else "exec"}
                try:  # the launcher's own view (exits, faults, outcome) goes into the recording too
                    launcher_view = {k: summary.get(k) for k in ("outcome", "faults", "nodes", "complete", "samples")}
                    session.put(self.keys.summary("launcher"),
                                msg.NodeSummary(node="launcher", data=launcher_view).encode())
                    if self.recorder is not None and self.recorder.poll() is None:
                        time.sleep(0.1)
                except Exception:  # noqa: BLE001 - best effort at the end; the recorder is stopped below
                    pass
                self.stop_recorder()
                self.check_recorder(col, None)
                for t in tokens:
                    t.undeclare()
                summary["recording"] = self.recording_info()
                self.phase("summary")
                if self.rerun is not None:
                    self.rerun.finish()
                    summary["rerun"] = self.rerun.info()
                if self.foxglove is not None:
                    self.foxglove.finish(self.cfg.foxglove_linger)
                    summary["foxglove"] = self.foxglove.info()
        finally:
            if self.recorder is not None and self.recorder.poll() is None:  # an exception above
                self.stop_recorder()
            if self.netns is not None:
                self.netns.down()
            self.remove_secrets()
            external.remove_join(join_path)
            for s, h in old.items():
                signal.signal(s, h)
        summary["run_dir"] = str(self.run_dir)
        summary["launcher"]["peak_rss_mb"] = peak_rss_mb()  # the end of run included (benchmarks/bench_soak.py)
        summary["recording_complete"] = None if summary["recording"] is None else summary["recording"]["complete"]
        code = exit_code(self.signal, self.faults, summary, ridden=netns.RIDDEN_THROUGH)
        if code == 0 and self.own_dir:
            shutil.rmtree(self.run_dir, ignore_errors=True)
            summary["run_dir"] = None
        return code, summary
