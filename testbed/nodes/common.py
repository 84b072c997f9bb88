"""What every node of a live run shares: options, the run clock, the Zenoh context.

Clock.  Every node agrees on the run's start instant t0, chosen by the plant (the
time master) and published in ``Start.t0_ns`` on CLOCK_REALTIME, the only clock
two hosts can share (keep them in sync with NTP/PTP; the offset between hosts
shifts the controller's loss deadline and the cross-host latency figures).  Each
node converts t0 once into its own CLOCK_MONOTONIC and paces and stamps on that
clock from then on, so a step of the wall clock during a run changes nothing.
On one host (or in network namespaces of one host) the conversion error is a few
microseconds.  All stamps are integer ns since t0; sample k is due at t_k = k T_ns.
"""

from __future__ import annotations

import argparse
import collections
import ctypes
import dataclasses
import faulthandler
import hashlib
import json
import logging
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass


from ..wire import messages as msg
from ..wire import transport

log = logging.getLogger("testbed.nodes")

#: how far ahead of a node's run clock a message's sample instant may be (clock offsets across
#: hosts, a plant that samples a little early); a message for a later sample is rejected
CLOCK_TOLERANCE_NS = 2_000_000


# ============================================================================ run options
@dataclass(frozen=True)
class RunOptions:
    """Options of a live run that every node must share (they enter the start digest).

    Any field left None keeps the scenario's value.
    """

    duration: float | None = None
    T: float | None = None
    timing: str | None = None
    deadline: float | None = None
    mode: str | None = None
    loss_fraction: float | None = None
    actuation: str | None = None
    rule: str | None = None
    seed: int | None = None
    ack_via_attacker: bool = False
    separate_ack: bool = False
    colocate: tuple[str, ...] = ()

    _OVERRIDES = (("duration", "--duration"), ("T", "--T"), ("timing", "--timing"), ("deadline", "--deadline"),
                  ("mode", "--mode"), ("loss_fraction", "--loss-fraction"), ("actuation", "--actuation"),
                  ("rule", "--rule"), ("seed", "--seed"))

    @classmethod
    def from_args(cls, args) -> "RunOptions":
        co = getattr(args, "colocate", None) or ()
        return cls(**{k: getattr(args, k, None) for k, _ in cls._OVERRIDES},
                   ack_via_attacker=bool(getattr(args, "ack_via_attacker", False)),
                   separate_ack=bool(getattr(args, "separate_ack", False)),
                   colocate=tuple(sorted({co} if isinstance(co, str) else set(co))))

    @property
    def ack_on_actuation(self) -> bool:
        """The ideal ack rides on the actuation message (one put, read by the plant and the encoder)."""
        return not (self.ack_via_attacker or self.separate_ack)

    def process_of(self, role: str) -> str:
        """The process that runs ``role`` (its own, or the plant's for a colocated encoder)."""
        return transport.host_of(role, self.colocate)

    @property
    def processes(self) -> tuple[str, ...]:
        """The node processes of the run (the four roles, less the colocated ones)."""
        return tuple(r for r in transport.ROLES if r not in self.colocate)

    def overrides(self) -> dict:
        """The scenario overrides (``testbed.scenario.with_overrides``), None fields left out."""
        return {k: getattr(self, k) for k, _ in self._OVERRIDES if getattr(self, k) is not None}

    def cli(self) -> list[str]:
        """The same options as command-line flags (for the launcher)."""
        out = []
        for name, flag in self._OVERRIDES:
            v = getattr(self, name)
            if v is not None:
                out += [flag, repr(v) if isinstance(v, float) else str(v)]
        if self.ack_via_attacker:
            out.append("--ack-via-attacker")
        if self.separate_ack:
            out.append("--separate-ack")
        for r in self.colocate:
            out += ["--colocate", r]
        return out


def add_run_option_arguments(p: argparse.ArgumentParser,
                             title: str = "run options (must be the same for every node of a run)") -> None:
    g = p.add_argument_group(title)
    g.add_argument("--duration", type=float, help="override [run] duration (seconds)")
    g.add_argument("--T", type=float, metavar="SECONDS",
                   help="override [quantizer] T, the sample period (re-validates the scenario)")
    g.add_argument("--timing", choices=["ideal", "physical"], help="override [run] timing")
    g.add_argument("--deadline", type=float, metavar="FRACTION",
                   help="override [run] deadline (fraction of T the plant waits for u_k)")
    g.add_argument("--mode", choices=["ideal", "resilient"], help="override [quantizer] mode")
    g.add_argument("--loss-fraction", type=float, metavar="C",
                   help="override [run] loss_fraction: the controller declares sample k lost at t_k + C d T")
    g.add_argument("--actuation", choices=["scheduled", "arrival"],
                   help="override [run] actuation (physical timing: u_k acts at its scheduled instant or on arrival)")
    g.add_argument("--rule", choices=["paper", "delay-aware"], help="override [quantizer] rule (the prediction rule)")
    g.add_argument("--seed", type=int, metavar="S",
                   help="override [attack] seed (a random attack without one draws one, prints it and records it)")
    g.add_argument("--ack-via-attacker", action="store_true",
                   help="route the controller's acks through the attacker proxy too")
    g.add_argument("--separate-ack", action="store_true",
                   help="send the ideal ack as a message of its own (loop/ack/tx) instead of on the actuation "
                        "message the encoder also reads")
    g.add_argument("--colocate", choices=sorted(transport.COLOCATABLE), metavar="encoder",
                   help="run the encoder inside the plant's process, as a smart sensor does: no sensor hop "
                        "(three network hops per sample instead of four)")


def load_scenario(ref: str, opts: RunOptions, *, check_design: bool = True):
    """Load a scenario and apply the run overrides (validated as if written in the file).

    ``check_design=False`` (a node started by the launcher, which checked the same text and
    overrides): skip the Schur check of a given K, so that the node needs no scipy.
    """
    from .. import scenario

    return scenario.with_overrides(scenario.load(ref, check_design=check_design), opts.overrides(),
                                   check_design=check_design)


def T_ns(sc) -> int:
    return int(round(sc.T * 1e9))


def run_digest(sc, opts: RunOptions) -> str:
    """What all nodes must agree on: the scenario text, the resolved loop and the run options."""
    d = {"source": sc.source, "K": sc.K.tolist(), "T": sc.T, "n_steps": sc.n_steps,
         "quantizer": dataclasses.asdict(sc.quantizer), "run": dataclasses.asdict(sc.run),
         "ack_via_attacker": opts.ack_via_attacker, "ack_on_actuation": opts.ack_on_actuation,
         "colocate": list(opts.colocate),
         "plant_sha256": sc.plant.source_info()["sha256"]}  # the same plant module in every node
    return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:16]


def attack_horizon(sc) -> float:
    """Horizon of the offline DoS schedule: the run's duration, as ``testbed simulate`` uses."""
    return sc.n_steps * sc.T


# ============================================================================ clock
class RunClock:
    """ns since t0 on this node's CLOCK_MONOTONIC (t0 given on CLOCK_REALTIME)."""

    def __init__(self, t0_realtime_ns: int):
        self.t0_realtime_ns = int(t0_realtime_ns)
        self.t0_mono_ns = self.t0_realtime_ns - realtime_minus_monotonic()

    def now(self) -> int:
        return time.monotonic_ns() - self.t0_mono_ns

    def sleep_until(self, t_ns: int, spin_ns: int = 0, stop: threading.Event | None = None) -> int:
        """Sleep until ``t_ns`` (ns since t0): sleep to ``t_ns - spin_ns`` then spin; returns now()."""
        target = self.t0_mono_ns + t_ns
        while True:
            rem = target - time.monotonic_ns()
            if rem <= spin_ns:
                break
            if stop is not None and stop.is_set():
                return self.now()
            time.sleep(min((rem - spin_ns) / 1e9, 0.05))
        while time.monotonic_ns() < target:
            pass
        return time.monotonic_ns() - self.t0_mono_ns


def realtime_minus_monotonic() -> int:
    """CLOCK_REALTIME - CLOCK_MONOTONIC in ns (best of a few reads, error ~1 us)."""
    best = None
    for _ in range(7):
        a = time.monotonic_ns()
        r = time.time_ns()
        b = time.monotonic_ns()
        if best is None or b - a < best[0]:
            best = (b - a, r - (a + b) // 2)
    return best[1]


# ============================================================================ process setup
_libc = None


def _prctl(option: int, arg: int) -> bool:
    global _libc
    try:
        if _libc is None:
            _libc = ctypes.CDLL(None, use_errno=True)
        return _libc.prctl(option, arg, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def tune_process(parent_pid: int | None = None) -> dict:
    """Fine timer slack, death with the parent (launcher), stacks on SIGUSR1.

    ``kill -USR1 PID`` prints every thread's Python stack to the node's stderr
    (its log file under ``testbed run``): the way to see where a node hangs.
    """
    try:
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    except (AttributeError, ValueError, OSError):
        pass
    info = {"timerslack": _prctl(29, 1)}  # PR_SET_TIMERSLACK = 29: 1 ns instead of 50 us
    if parent_pid:
        _prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG = 1
        if os.getppid() != parent_pid:  # the launcher died before we got here
            raise SystemExit(f"testbed node: launcher (pid {parent_pid}) is gone")
    return info


def on_stop_signals(callback, *, main_handler=None, grace: float | None = None,
                    signals=(signal.SIGINT, signal.SIGTERM), others: dict | None = None) -> None:
    """Call ``callback(signum)`` on a helper thread when one of ``signals`` arrives.

    A Python signal handler runs on the main thread between two bytecodes, which
    may be inside ``threading.Event.wait`` holding the event's lock: a handler that
    sets an event or notifies a condition deadlocks there (seen: a node hung for
    ever after the launcher's death sent it SIGTERM).  So the Python handler does
    nothing but (optionally) ``main_handler``; the interpreter's C-level handler
    writes the signal number to a wake-up pipe, and a daemon thread reads it and
    calls ``callback``, outside any lock the main thread holds.

    ``grace``: after the first signal, exit hard (``os._exit(1)``) if the process
    is still alive ``grace`` seconds later, so a stop that hangs anyway cannot leave
    an orphan behind.  ``others``: {signal: handler()} for signals that do not stop
    the process (fault injection), called the same way.
    """
    r, w = os.pipe()
    os.set_blocking(w, False)
    wanted = {int(s) for s in signals}
    extra = {int(s): h for s, h in (others or {}).items()}

    def py_handler(signum, _frame):
        if main_handler is not None and signum in wanted:
            main_handler(signum)

    for s in (*signals, *extra):
        signal.signal(s, py_handler)
    signal.set_wakeup_fd(w, warn_on_full_buffer=False)

    def pump() -> None:
        armed = False
        while True:
            try:
                data = os.read(r, 64)
            except OSError:
                return
            for b in data:
                if b in extra:
                    try:
                        extra[b]()
                    except Exception:  # noqa: BLE001 - must not kill the pump
                        logging.getLogger(__name__).exception("signal handler failed")
                    continue
                if b not in wanted:
                    continue
                if grace is not None and not armed:
                    armed = True
                    threading.Thread(target=_exit_after, args=(grace, b), daemon=True,
                                     name="stop-deadline").start()
                try:
                    callback(b)
                except Exception:  # noqa: BLE001 - a stop request must not kill the pump
                    logging.getLogger(__name__).exception("stop callback failed")

    threading.Thread(target=pump, daemon=True, name="signals").start()


def _exit_after(seconds: float, signum: int) -> None:
    time.sleep(seconds)
    try:
        name = signal.Signals(signum).name
    except ValueError:
        name = str(signum)
    print(f"testbed: still running {seconds:g} s after {name}; exiting hard", file=sys.stderr, flush=True)
    os._exit(1)


def parse_cpus(spec: str) -> set[int]:
    """``2``, ``2,3``, ``0-3,6`` -> a set of CPU numbers (BadInput on anything else)."""
    from ..errors import BadInput

    out: set[int] = set()
    try:
        for part in spec.split(","):
            part = part.strip()
            lo, sep, hi = part.partition("-")
            out.update(range(int(lo), int(hi) + 1) if sep else [int(lo)])
    except ValueError:
        raise BadInput(f"CPU list {spec!r}: expected e.g. 2 or 2,3 or 0-3") from None
    avail = os.sched_getaffinity(0)
    if not out or not out <= avail:
        raise BadInput(f"CPU list {spec!r}: this machine offers CPUs {','.join(map(str, sorted(avail)))}")
    return out


def set_realtime(on: bool, priority: int = 1) -> bool:
    """SCHED_FIFO (``on``) or back to SCHED_OTHER for every thread of this process.

    Applied only for the loop itself (after start-up, JIT and warm-up), so a node
    never competes at real-time priority while compiling or connecting.  The
    kernel's RT throttling still leaves 5% of each CPU to everybody else.

    Threads with a higher nice value than the main thread (the Rerun logging thread and the threads
    Rerun created from it, ``rerun_tap.NICE``) are background work and stay
    SCHED_OTHER: a real-time thread would preempt the loop it is meant to stay off.
    """
    policy = os.SCHED_FIFO if on else os.SCHED_OTHER
    param = os.sched_param(priority if on else 0)
    try:
        base = os.getpriority(os.PRIO_PROCESS, os.getpid())  # the main thread's nice value
    except OSError:
        base = 0
    ok = True
    for tid in os.listdir("/proc/self/task"):
        try:
            if on and os.getpriority(os.PRIO_PROCESS, int(tid)) > base:
                continue
            os.sched_setscheduler(int(tid), policy, param)
        except (OSError, ValueError):
            ok = False
    return ok


# ============================================================================ zenoh options
def add_security_arguments(g) -> None:
    """``--topology``, ``--secret-file``, ``--insecure`` (nodes, the recorder; the launcher makes its own secret)."""
    g.add_argument("--topology", choices=transport.TOPOLOGIES, default="router",
                   help="router: one process routes and checks every message (default); peer: direct links "
                        "between the processes, mutual TLS (--tls-dir), every process checks what it receives")
    g.add_argument("--secret-file", metavar="PATH",
                   help="the run's credentials (a 0600 file of user:password lines; make one with 'testbed secret')")
    g.add_argument("--tls-dir", metavar="DIR",
                   help="--topology peer: the run's TLS folder (ca.pem, NAME.pem, NAME.key; make one with "
                        "'testbed secret --tls DIR')")
    g.add_argument("--insecure", action="store_true",
                   help="no authentication and no access control: any local process can join the run")
    g.add_argument("--low-latency", action="store_true",
                   help="Zenoh's low-latency transport (no batching, no priorities); every process of a run "
                        "must use it or none")


def add_zenoh_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("zenoh")
    g.add_argument("--run-id", default=transport.DEFAULT_RUN_ID,
                   help="key prefix testbed/RUN_ID/... (default %(default)s)")
    g.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to listen on, e.g. tcp/10.0.0.2:7447 (repeatable)")
    g.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to connect to, e.g. tcp/10.0.0.1:7447 (repeatable)")
    g.add_argument("--zenoh-config", metavar="FILE",
                   help="Zenoh JSON5 config read first (e.g. TLS certificates); flags override it")
    add_security_arguments(g)


PEER_NEEDS_TLS = ("--topology peer: no --tls-dir: its links are mutual TLS; make the folder with "
                  "'testbed secret --tls DIR' and give it to every process of the run (or run unauthenticated "
                  "with --insecure)")


def access_control(topology: str) -> str:
    """Who checks the messages of a run (the ``access_control`` of its ``security``)."""
    return "every message, by every receiver" if topology == "peer" else "every message"


def transport_security(topology: str, insecure: bool) -> str:
    """How the links of a run are authenticated (the ``transport`` of its ``security``)."""
    return "tcp" if insecure else ("mutual tls" if topology == "peer" else "user/password")


def security_info(args) -> dict:
    """How a process's session is secured (it goes into the recording and the summary)."""
    return {"authenticated": not args.insecure, "topology": args.topology,
            "access_control": "none" if args.insecure else access_control(args.topology),
            "transport": transport_security(args.topology, args.insecure),
            "low_latency": bool(getattr(args, "low_latency", False))}


def zenoh_config(args, role: str, keys: transport.Keys):
    """The session of ``role`` (a node or the recorder).

    Standalone defaults: the plant listens on tcp/127.0.0.1:7447, the others connect to
    it.  Router topology: the hub (the launcher, or a standalone plant) is the run's
    router and checks every message; the others are its clients.  Unless ``--insecure``,
    the session authenticates with the secret file's line of ``role``; the router accepts
    the file's other lines.  Peer topology: every process is a peer, every link mutual TLS
    with ``role``'s certificate of the ``--tls-dir`` folder, and every process checks what
    it receives.
    """
    from ..errors import BadInput

    hub = role == "plant" and not getattr(args, "launched", False)
    peer = args.topology == "peer"
    hub_ep = transport.DEFAULT_HUB.replace("tcp/", "tls/", 1) if peer and not args.insecure else transport.DEFAULT_HUB
    listen, connect = list(args.listen), list(args.connect)
    if not listen and not connect and not args.zenoh_config:
        if hub:
            listen = [hub_ep]
        else:
            connect = [hub_ep]
    mode = "peer" if peer else ("router" if hub else "client")
    ll = bool(getattr(args, "low_latency", False))
    colocate = RunOptions.from_args(args).colocate
    if args.insecure:
        return transport.make_config(listen=listen, connect=connect, config_file=args.zenoh_config, mode=mode,
                                     low_latency=ll)
    if peer:
        if not getattr(args, "tls_dir", None):
            raise BadInput(PEER_NEEDS_TLS)
        tls = transport.TlsCredentials(args.tls_dir).zenoh(role)
        transport.require_tls((*listen, *connect))
        return transport.make_config(listen=listen, connect=connect, config_file=args.zenoh_config, mode=mode,
                                     acl=transport.acl_config(keys, colocate, by="cert_common_names"), low_latency=ll,
                                     tls=tls)
    if not args.secret_file:
        raise BadInput("no --secret-file: make one with 'testbed secret PATH' and give it to every process "
                       "of the run (or run unauthenticated with --insecure)")
    cred = transport.Credentials.read(args.secret_file)
    accepts = hub
    if accepts:
        missing = [u for u in (*transport.ROLES, transport.RECORDER) if u not in cred.users]
        if missing:
            raise BadInput(f"secret file {args.secret_file}: no line for {', '.join(missing)} (a {mode} that "
                           "accepts the others needs all of them)")
    return transport.make_config(listen=listen, connect=connect, config_file=args.zenoh_config, mode=mode,
                                 user=role, password=cred.password(role),
                                 dictionary_file=args.secret_file if accepts else None,
                                 acl=transport.acl_config(keys, colocate) if accepts else None, low_latency=ll)


# ============================================================================ node context
class NodeContext:
    """A node's session, keys, liveliness view, event log and run clock."""

    def __init__(self, role: str, session, sc, opts: RunOptions, keys: transport.Keys):
        import zenoh

        self._zenoh = zenoh  # first: liveliness callbacks (history=True) may fire during __init__
        self.role = role
        self.session = session
        self.sc = sc
        self.opts = opts
        self.keys = keys
        self.digest = run_digest(sc, opts)
        self.T_ns = T_ns(sc)
        self.n_steps = sc.n_steps
        self.clock_tolerance_ns = CLOCK_TOLERANCE_NS
        self.stop = threading.Event()
        self.stop_reason = ""
        self.start_msg: msg.Start | None = None
        self.clock: RunClock | None = None
        self._start_ev = threading.Event()
        self._lock = threading.Lock()
        self.alive: set[str] = set()
        self.ready: set[str] = set()
        self._peer_handlers: list = []
        self._cond = threading.Condition()
        self.events_sent = 0
        self.events_suppressed = 0
        self._ev_window: dict[str, tuple[float, int]] = {}
        self._ev_lock = threading.Lock()
        self._ev_pub = session.declare_publisher(keys.events(role), **transport.telemetry_qos())
        self.telemetry = TelemetryOut(session.declare_publisher(keys.telemetry(role), **transport.telemetry_qos()),
                                      self.T_ns, background=not ab_off("telemetry-thread"))
        self._subs = [
            session.declare_subscriber(keys.start, self._on_start),
            session.declare_subscriber(keys.stop, self._on_stop),
            session.liveliness().declare_subscriber(keys.alive("*"), self._on_alive, history=True),
            session.liveliness().declare_subscriber(keys.ready("*"), self._on_ready, history=True),
        ]
        self._tokens = []
        self.watch_collector = False  # launched by ``testbed run``: stop when the launcher goes away

    # ---- liveliness
    def _on_alive(self, sample) -> None:
        node = transport.Keys.node_of(sample.key_expr)
        gone = sample.kind == self._zenoh.SampleKind.DELETE
        with self._cond:
            if gone:
                self.alive.discard(node)
            else:
                self.alive.add(node)
            self._cond.notify_all()
        if gone and node == transport.COLLECTOR and self.watch_collector:
            self.request_stop("launcher lost")
        for h in self._peer_handlers:
            try:
                h(node, not gone)
            except Exception:  # noqa: BLE001 - a handler bug must not kill the liveliness thread
                log.exception("peer handler failed")

    def _on_ready(self, sample) -> None:
        node = transport.Keys.node_of(sample.key_expr)
        with self._cond:
            if sample.kind == self._zenoh.SampleKind.DELETE:
                self.ready.discard(node)
            else:
                self.ready.add(node)
            self._cond.notify_all()

    def on_peer(self, handler) -> None:
        """``handler(node, alive: bool)`` on every liveliness change (runs on a Zenoh thread)."""
        self._peer_handlers.append(handler)

    def declare_alive(self) -> None:
        self._tokens.append(self.session.liveliness().declare_token(self.keys.alive(self.role)))

    def declare_ready(self) -> None:
        self._tokens.append(self.session.liveliness().declare_token(self.keys.ready(self.role)))

    def wait_for(self, what: str, nodes, timeout: float) -> bool:
        """Wait until every node of ``nodes`` is in ``self.alive`` / ``self.ready``."""
        want = set(nodes)
        end = time.monotonic() + timeout
        with self._cond:
            while not want <= getattr(self, what):
                rem = end - time.monotonic()
                if rem <= 0 or self.stop.is_set():
                    return False
                self._cond.wait(min(rem, 0.1))
        return True

    def missing(self, what: str, nodes) -> list[str]:
        with self._cond:
            return sorted(set(nodes) - getattr(self, what))

    # ---- start / stop
    def _on_start(self, sample) -> None:
        try:
            st = msg.Start.decode(sample.payload)
        except msg.MessageError as e:
            self.event("bad_start", detail=str(e))
            return
        with self._lock:
            if self.start_msg is not None:
                return
            if st.digest != self.digest:
                self.event("run_mismatch", detail=f"start digest {st.digest} != mine {self.digest}: "
                                                  "different scenario or run options")
                self.request_stop("run mismatch")
                return
            self.start_msg = st
            self.clock = RunClock(st.t0_ns)
        self._start_ev.set()

    #: who may stop a run (the access control of the router topology enforces it as well)
    STOP_ORIGINS = ("plant", "launcher")

    def _on_stop(self, sample) -> None:
        try:
            s = msg.Stop.decode(sample.payload)
        except msg.MessageError as e:
            self.event("stop_rejected", detail=f"malformed stop message: {e}")
            return
        if s.origin not in self.STOP_ORIGINS:
            self.event("stop_rejected", detail=f"stop from {s.origin!r}: only the plant or the launcher stops a run")
            return
        self.request_stop(f"stop from {s.origin}: {s.reason}")

    def request_stop(self, reason: str) -> None:
        if not self.stop.is_set():
            self.stop_reason = reason
            self.stop.set()
        self._start_ev.set()
        with self._cond:
            self._cond.notify_all()

    def wait_start(self, timeout: float) -> msg.Start | None:
        self._start_ev.wait(timeout)
        return self.start_msg if not self.stop.is_set() else None

    def wait_clock(self, timeout: float = 1.0) -> RunClock | None:
        """The run clock, waiting up to ``timeout`` for the Start (a control message may overtake it)."""
        if self.clock is None:
            self._start_ev.wait(timeout)
        return self.clock

    def adopt_start(self, st: msg.Start) -> None:
        """The plant chose t0 itself."""
        with self._lock:
            self.start_msg = st
            self.clock = RunClock(st.t0_ns)
        self._start_ev.set()

    def now(self) -> int:
        return self.clock.now() if self.clock else msg.NO_TIME

    def newest_k(self, now_ns: int) -> int:
        """The newest sample whose instant t_k = k T has come at ``now_ns`` (run clock), within the
        clock tolerance: a message for a later sample cannot be genuine."""
        return (now_ns + self.clock_tolerance_ns) // self.T_ns

    @property
    def end_ns(self) -> int:
        """ns since t0 after which nothing of the run can still happen."""
        return self.n_steps * self.T_ns

    # ---- events
    EVENTS_PER_SECOND = 20  # per kind; the rest are only counted (``events_suppressed``)

    def event(self, kind: str, k: int = -1, detail: str = "", level: int = logging.WARNING) -> None:
        """Log and publish an event, at most EVENTS_PER_SECOND of each kind per second."""
        now = time.monotonic()
        with self._ev_lock:
            t_win, n = self._ev_window.get(kind, (now, 0))
            if now - t_win >= 1.0:
                t_win, n = now, 0
            if n >= self.EVENTS_PER_SECOND:
                self.events_suppressed += 1
                self._ev_window[kind] = (t_win, n)
                return
            self._ev_window[kind] = (t_win, n + 1)
        e = msg.Event(node=self.role, kind=kind, k=int(k), t_ns=self.now(), detail=detail)
        log.log(level, "%s: %s k=%d %s", self.role, kind, k, detail)
        self.events_sent += 1
        try:
            self._ev_pub.put(e.encode())
        except Exception:  # noqa: BLE001 - the session may be closing
            pass

    def publish_summary(self, data: dict) -> None:
        s = msg.NodeSummary(node=self.role, data=data)
        try:
            self.session.put(self.keys.summary(self.role), s.encode(),
                             congestion_control=self._zenoh.CongestionControl.BLOCK)
        except Exception:  # noqa: BLE001
            log.exception("summary not published")

    def close(self) -> None:
        for t in self._tokens:
            try:
                t.undeclare()
            except Exception:  # noqa: BLE001
                pass


class TelemetryOut:
    """Per-sample telemetry records, published in batches of at most ~``max_delay`` worth of samples.

    One record per message at T = 0.1 s; at T = 1 ms 20 records every 20 ms, so the
    per-message cost of Zenoh and of the readers stays off the control loop.  The batches
    are published by a thread of their own, not by the thread that sent the control
    message, and at T >= 10 ms half a period (at most 20 ms) after the record, when the
    loop's messages of that sample have long gone (``quiet_ns``).  ``immediate``: publish
    each batch at once from the caller (a reader waits for it: the greedy attacker's
    score E_k).  A node killed mid-run loses at most one batch.
    """

    def __init__(self, pub, T_ns: int, max_delay_ns: int = 20_000_000, *, background: bool = True):
        self.pub = pub
        self.n = int(max(1, min(64, max_delay_ns // max(T_ns, 1))))
        self.buf: list[bytes] = []
        self.lock = threading.Lock()
        self.tap = None  # testbed run --rerun: a deque's append (testbed.nodes.rerun_tap), nothing more
        self._digest = hashlib.sha256()  # of every record, in order: the launcher checks what it received
        self.records = 0
        self.immediate = not background
        self.quiet_ns = min(T_ns // 2, max_delay_ns) if T_ns >= 10_000_000 else 0
        self._queue: list[tuple[int, bytes]] = []   # (monotonic ns due, batch) for the publisher thread
        self._cv = threading.Condition(self.lock)
        self._pub_lock = threading.Lock()           # one publisher at a time, batches in order
        self._thread: threading.Thread | None = None
        self._closed = False

    def digest(self) -> dict:
        """The node's own account of its telemetry (it goes into its summary)."""
        with self.lock:
            return {"telemetry_records": self.records, "telemetry_sha256": self._digest.hexdigest()}

    def put(self, record: bytes) -> None:
        tap = self.tap
        if tap is not None:
            tap(record)
        with self.lock:
            if self._closed:
                return
            self._digest.update(record)
            self.records += 1
            self.buf.append(record)
            if len(self.buf) < self.n:
                return
            data = msg.pack_batch(self.buf)
            self.buf.clear()
            if not self.immediate:
                self._queue.append((time.monotonic_ns() + self.quiet_ns, data))
                if self._thread is None:
                    self._thread = threading.Thread(target=self._publisher, daemon=True, name="telemetry")
                    self._thread.start()
                self._cv.notify()
                return
        self._publish(data)

    def _publish(self, data: bytes) -> None:
        with self._pub_lock:
            try:
                self.pub.put(data)
            except Exception:  # noqa: BLE001 - the session may be closing
                pass

    def _publisher(self) -> None:
        while True:
            with self._cv:
                while not self._queue:
                    self._cv.wait()
                due = self._queue[0][0]
            rem = due - time.monotonic_ns()
            if rem > 0:
                time.sleep(rem / 1e9)
            with self._pub_lock:
                with self.lock:
                    if not self._queue:
                        continue
                    _due, data = self._queue.pop(0)
                try:
                    self.pub.put(data)
                except Exception:  # noqa: BLE001 - the session may be closing
                    pass

    def flush(self) -> None:
        """Publish everything now (from the caller), queued batches first."""
        with self._pub_lock:
            with self.lock:
                batches = [d for _due, d in self._queue]
                self._queue.clear()
                if self.buf:
                    batches.append(msg.pack_batch(self.buf))
                    self.buf.clear()
            for data in batches:
                try:
                    self.pub.put(data)
                except Exception:  # noqa: BLE001 - the session may be closing
                    pass

    def discard(self) -> None:
        """Drop what is not published yet and publish nothing more (a colocated role that died)."""
        with self.lock:
            self._closed = True
            self._queue.clear()
            self.buf.clear()


class RoleView:
    """Another role's face on a node's context: a role run inside this node's process (``--colocate``).

    It has its own name, telemetry, events, summary and liveliness tokens (so readers see
    the role as if it were a process of its own); everything else (session, clock, stop,
    peers) is the host node's.
    """

    def __init__(self, ctx: "NodeContext", role: str):
        self._ctx = ctx
        self.role = role
        self.events_sent = 0
        self.events_suppressed = 0
        self._ev_window: dict[str, tuple[float, int]] = {}
        self._ev_lock = threading.Lock()
        self._ev_pub = ctx.session.declare_publisher(ctx.keys.events(role), **transport.telemetry_qos())
        self.telemetry = TelemetryOut(ctx.session.declare_publisher(ctx.keys.telemetry(role),
                                                                    **transport.telemetry_qos()), ctx.T_ns,
                                      background=not ab_off("telemetry-thread"))
        self._tokens: list = []

    def __getattr__(self, name):
        return getattr(self._ctx, name)

    event = NodeContext.event
    publish_summary = NodeContext.publish_summary
    declare_alive = NodeContext.declare_alive
    declare_ready = NodeContext.declare_ready
    close = NodeContext.close


# ============================================================================ receiving
#: how a node receives its control-path messages (``--rx``)
RX_MODES = ("thread", "direct", "spin")


class Inlet:
    """A node's primary input under rx mode ``spin``: a callback as usual, and a spin just before it is due.

    Each sample reaches two subscribers of the same key in the node's session: a callback
    (zenoh-python's thread, which sleeps until a sample wakes it) and a FIFO that Zenoh's
    receive thread fills without Python.  From ``margin_ns`` before the earliest arrival,
    relative to its sample instant t_k, of the last 8 samples, for at most ``budget_ns``,
    the node's thread polls the FIFO: a sample that comes then is handled at once, without
    a thread to wake; the callback's copy is then skipped (both streams hold the same
    samples in the same order, so a sample is the n-th of each).  Outside that window the
    callback handles it and drops the FIFO's copy.  One sample at a time, in order.

    ``handler(sample)`` returns the sample index k of a control message (or None): the
    arrivals teach the inlet when to spin.  ``thread``: a spinner thread of its own; else
    the node's loop calls ``window`` and ``spin`` (the plant, waiting for u_k).
    """

    HISTORY = 8

    def __init__(self, node: "Node", key: str, handler, *, budget_ns: int, margin_ns: int = 300_000,
                 thread: bool = True):
        import zenoh

        self.node = node
        self.handler = handler
        self.budget_ns = int(budget_ns)
        self.margin_ns = int(margin_ns)
        self.lock = threading.Lock()
        self.n_fifo = 0       # samples taken from the FIFO
        self.n_cb = 0         # samples that reached the callback
        self.handled = 0      # the index of the next sample to handle
        self.offsets: collections.deque = collections.deque(maxlen=self.HISTORY)
        self.last_k = -1
        self.spun = 0         # samples handled while spinning
        self.woken = 0        # samples the callback handled
        self.spin_ns = 0      # time spent spinning
        self.broken = False   # the two streams differed once: the callback alone from then on
        self._seen: dict[int, bytes] = {}  # the samples the spinner handled, by index (the last 64)
        session = node.ctx.session
        self.fifo = session.declare_subscriber(key, zenoh.handlers.FifoChannel(1024))
        self.sub = session.declare_subscriber(key, self._on_callback)
        if thread:
            threading.Thread(target=self._spinner, daemon=True, name=f"spin-{key.rsplit('/', 1)[-1]}").start()

    # ---- the two streams
    @staticmethod
    def _ident(sample) -> bytes:
        att = sample.attachment
        return (b"" if att is None else att.to_bytes()) + b"|" + sample.payload.to_bytes()

    def _on_callback(self, sample) -> None:
        with self.lock:
            i = self.n_cb
            self.n_cb += 1
            if self.broken:
                self._handle(sample)
                return
            mine = self._ident(sample)
            while self.n_fifo <= i:  # keep the FIFO in step: drop its copies of what the callback got
                try:
                    s = self.fifo.try_recv()
                except Exception:  # noqa: BLE001 - undeclared: the session is closing
                    s = None
                if s is None:
                    break
                if self.n_fifo == i and self._ident(s) != mine:
                    self.broken = True
                self.n_fifo += 1
            if i < self.handled and not self.broken:
                if self._seen.get(i, mine) == mine:
                    return  # the spinner had it
                self.broken = True
            if self.broken:  # the two streams differ (samples on one key from two links): no more spinning
                logging.getLogger(__name__).warning("rx spin: the two copies of a stream differ; spinning off")
                self.offsets.clear()
                self.budget_ns = 0
            self.handled = max(self.handled, i + 1)
            self.woken += 1
            self._handle(sample)

    def spin(self, until_ns: int) -> bool:
        """Poll the FIFO until a sample is handled or ``until_ns`` (run clock); True if one was."""
        import zenoh

        clock = self.node.ctx.clock
        t = time.monotonic_ns()
        try:
            while clock.now() < until_ns:
                try:
                    s = self.fifo.try_recv()
                except zenoh.ZError:  # undeclared: the session is closing
                    return False
                if s is None:
                    os.sched_yield()  # releases the GIL and lets this CPU's other threads (Zenoh's) run
                    continue
                with self.lock:
                    if self.broken:
                        return False
                    i = self.n_fifo
                    self.n_fifo += 1
                    if i < self.handled:
                        continue  # the callback had it
                    self.handled = i + 1
                    self.spun += 1
                    self._seen[i] = self._ident(s)
                    self._seen.pop(i - 64, None)
                    self._handle(s)
                return True
            return False
        finally:
            self.spin_ns += time.monotonic_ns() - t

    def _handle(self, sample) -> None:
        ctx = self.node.ctx
        clock = ctx.clock
        rx = clock.now() if clock is not None else None
        k = self.handler(sample)
        if k is not None and rx is not None and k > self.last_k:
            self.last_k = k
            self.offsets.append(rx - k * ctx.T_ns)

    # ---- when to spin
    def window(self, now: int) -> tuple[int, int] | None:
        """(start, end) of the spin window of the next sample due, in run-clock ns, or None."""
        if not self.offsets or self.budget_ns <= 0:
            return None
        T_ns = self.node.ctx.T_ns
        lead = min(self.offsets) - self.margin_ns
        j = max(self.last_k + 1, -(-(now - lead - self.budget_ns) // T_ns))
        start = j * T_ns + lead
        return start, start + self.budget_ns

    def _spinner(self) -> None:
        ctx = self.node.ctx
        stop = ctx.stop
        while not stop.is_set():
            clock = ctx.clock
            now = clock.now() if clock is not None else 0
            w = self.window(now) if clock is not None else None
            if w is None:
                stop.wait(0.05)
                continue
            if now < w[0]:
                stop.wait(min((w[0] - now) / 1e9, 0.05))
                continue
            j = (w[0] - min(self.offsets) + self.margin_ns) // ctx.T_ns
            if not self.spin(w[1]):  # nothing in this window: no second one for this sample
                with self.lock:
                    self.last_k = max(self.last_k, j)

    def stats(self) -> dict:
        return {"spun": self.spun, "woken": self.woken, "spin_ms": round(self.spin_ns / 1e6, 3)}


def ab_off(change: str) -> bool:
    """Whether the benchmark switched a change of the loop off (``TESTBED_AB_OFF=name,...``, for A/B runs only)."""
    return change in {c.strip() for c in os.environ.get("TESTBED_AB_OFF", "").split(",")}


def warm_publisher(pub, payload: bytes, times: int = 3, pause: float = 0.001) -> None:
    """First puts on a publisher are slow: send a few with the warm-up index (readers ignore them)."""
    att = msg.Header(msg.WARMUP_K, 0).encode()
    for _ in range(times):
        pub.put(payload, attachment=att)
        time.sleep(pause)


def setup_logging(role: str, verbose: bool) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, stream=sys.stderr,
                        format=f"%(asctime)s {role:10s} %(levelname)s %(message)s")


def process_age() -> float:
    """Seconds since this process was created (10 ms resolution), or NaN."""
    try:
        with open("/proc/self/stat") as f:
            start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])
        return time.clock_gettime(time.CLOCK_BOOTTIME) - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, AttributeError):
        return float("nan")


def phase(who: str, name: str) -> None:
    """A start-up or shut-down milestone in the log (``-v``): ``benchmarks/bench_startup.py`` reads them."""
    if log.isEnabledFor(logging.INFO):
        log.info("%s: phase %s t=%.6f age=%.3f cpu=%.3f", who, name, time.time(), process_age(), time.process_time())


# ============================================================================ node base
class Node:
    """A node shell: ``setup`` (declare), ``warmup`` (JIT), ``run`` (after the start), ``summary``."""

    role = ""

    def __init__(self, ctx: NodeContext, args):
        self.ctx = ctx
        self.args = args
        self.sc = ctx.sc
        self.model = ctx.sc.make_model()  # the predictions' model (n, m); the plant node has the true plant
        self.crash_at = getattr(args, "crash_at", None)
        self.malformed = 0
        self.error: BaseException | None = None
        self._pubs: list = []
        self.rx_mode = getattr(args, "rx", None) or "thread"
        spin_us = getattr(args, "rx_spin_us", None)
        self.rx_spin_ns = int(spin_us * 1e3) if spin_us is not None else min(1_000_000, ctx.T_ns // 20)
        self.inlet: Inlet | None = None

    # -- to override
    def setup(self) -> None: ...

    def declare_alive(self) -> None:
        self.ctx.declare_alive()

    def declare_ready(self) -> None:
        self.ctx.declare_ready()

    def warmup(self) -> None: ...

    def warm_publishers(self) -> None: ...

    def run(self) -> None:
        self.wait_end()

    def summary(self) -> dict:
        return {}

    # -- helpers
    def publisher(self, key: str, control: bool = True):
        qos = transport.control_qos() if control else transport.telemetry_qos()
        return self.ctx.session.declare_publisher(key, **qos)

    def guard(self, fn):
        """Wrap a Zenoh callback: an exception stops the node (exit code 1) instead of vanishing."""

        def wrapped(sample):
            if self.error is not None:
                return None
            try:
                return fn(sample)
            except Exception as e:  # noqa: BLE001
                self.fail(e)
                return None

        return wrapped

    def subscribe(self, key: str, fn, *, blocking: bool = False, primary: bool = False, thread: bool = True):
        """Subscribe ``fn(sample)`` (guarded) the way the node's ``--rx`` mode says.

        ``thread``: zenoh-python's callback thread runs it (one thread per subscriber, woken
        for each sample).  ``direct``: Zenoh's own receive thread runs it, one thread wake-up
        less per message; only for a handler that never waits (``blocking=False``): one that
        waits for another message there would wait for ever.  ``spin``: as ``direct``, and the
        node's primary input (``primary``, the one on the loop's path) is an ``Inlet``: its
        own thread handles it and spins just before it is due (``thread=False``: the node's
        loop calls ``Inlet.step`` itself).  ``fn`` returns the sample index of a control
        message (the inlet learns when it is due) or None.
        """
        import zenoh

        h = self.guard(fn)
        if self.rx_mode == "spin" and primary:
            self.inlet = Inlet(self, key, h, budget_ns=self.rx_spin_ns, thread=thread)
            return self.inlet.sub
        if self.rx_mode != "thread" and not blocking:
            return self.ctx.session.declare_subscriber(key, zenoh.handlers.Callback(h, indirect=False))
        return self.ctx.session.declare_subscriber(key, h)

    def rx_summary(self) -> dict:
        d = {"rx": self.rx_mode}
        if self.inlet is not None:
            d["rx_inlet"] = self.inlet.stats()
        return d

    def fail(self, e: BaseException) -> None:
        if self.error is None:
            self.error = e
            import traceback

            tb = "".join(traceback.format_exception(e)).rstrip()
            log.error("%s crashed:\n%s", self.role, tb)
            self.ctx.event("crash", detail=f"{type(e).__name__}: {e}", level=logging.ERROR)
            self.ctx.request_stop(f"crash: {type(e).__name__}: {e}")

    def maybe_crash(self, k: int) -> None:
        """Fault injection (``--crash-at K``): raise at sample K."""
        if self.crash_at is not None and k == self.crash_at:
            raise RuntimeError(f"injected crash of the {self.role} at sample {k}")

    def bad_message(self, what: str, e: Exception, k: int = -1) -> None:
        self.malformed += 1
        if self.malformed <= 20:
            self.ctx.event("malformed", k=k, detail=f"{what}: {e}")

    def rx_header(self, sample, what: str):
        """The sample's header, or None for a warm-up put or a malformed header (counted)."""
        try:
            h = msg.Header.decode(sample.attachment)
        except msg.MessageError as e:
            self.bad_message(what, e)
            return None
        return None if h.warmup else h

    def wait_end(self, grace_s: float = 5.0) -> None:
        """Until a stop arrives, or the run's end plus ``grace_s`` (no plant to say so)."""
        ctx = self.ctx
        while not ctx.stop.is_set():
            if ctx.clock is not None and ctx.now() > ctx.end_ns + int(grace_s * 1e9):
                ctx.request_stop("run over (no stop message)")
                break
            ctx.stop.wait(0.05)
