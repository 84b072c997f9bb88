"""The typed configuration of a live run: the options every node must share (``RunOptions``, they enter
the start digest), one node's configuration (``NodeConfig``) and the recorder's (``RecorderConfig``), and
the scenario the options make.

``testbed node`` and ``testbed record`` build theirs from their flags (``testbed.commands.liveconfig``);
the launcher builds one for each process it starts and hands it over as those flags (``argv``), or, for
a node from outside, in the join file (``testbed.nodes.joined``)."""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from ..common import optionspec
from ..common.optionspec import option
from ..wire import transport
from ..wire.session import SessionOptions
from .inlet import RX_MODES

if TYPE_CHECKING:
    from ..scenario import Scenario

#: ``testbed run --foxglove``'s port when none is given
FOXGLOVE_PORT = 8765
#: ``--realtime auto``: SCHED_FIFO for a loop faster than this (s), where it is permitted
FAST_T = 0.01


# ============================================================================ run options
#: the commands that take the run options (``add_run_option_arguments``): every process of a run, and the simulator
SHARED = ("run", "node", "record", "conformance", "simulate")


def _shared(default=None, help="", digest=True, **kw):
    """A run option: every process of a run takes it, and (unless said) it enters the start digest."""
    return option(default, help, commands=SHARED, digest=digest, **kw)


@dataclass(frozen=True)
class RunOptions:
    """Options of a live run that every node must share (they enter the start digest).

    Any field left None keeps the scenario's value.  Each field is the one definition of its flag
    (``testbed.common.optionspec``): the flag of every command that takes it, ``cli``, the join file and docs/cli.md.
    """

    duration: float | None = _shared(help="override [run] duration (seconds)", kind=float)
    T: float | None = _shared(help="override [quantizer] T, the sample period (re-validates the scenario)", kind=float,
                              metavar="SECONDS")
    timing: str | None = _shared(help="override [run] timing", choices=("ideal", "physical"))
    deadline: float | None = _shared(help="override [run] deadline (fraction of T the plant waits for u_k)",
                                     kind=float, metavar="FRACTION")
    mode: str | None = _shared(help="override [quantizer] mode", choices=("ideal", "resilient"))
    loss_fraction: float | None = _shared(
        help="override [run] loss_fraction: the controller declares sample k lost at t_k + C d T", kind=float,
        metavar="C")
    actuation: str | None = _shared(
        help="override [run] actuation (physical timing: u_k acts at its scheduled instant or on arrival)",
        choices=("scheduled", "arrival"))
    rule: str | None = _shared(help="override [quantizer] rule (the prediction rule)", choices=("paper", "delay-aware"))
    seed: int | None = _shared(
        help="override [attack] seed (a random attack without one draws one, prints it and records it)", kind=int,
        metavar="S", digest=False)  # the attack is not in run_digest: only the attacker draws from it
    method: str | None = _shared(
        help="override [method] name: the coding-and-control method (testbed methods lists them; [quantizer] keys it "
             "does not use are ignored with a note)", metavar="NAME")
    ack_via_attacker: bool = _shared(False, "route the controller's acks through the attacker proxy too")
    separate_ack: bool = _shared(False, "send the ideal ack as a message of its own (loop/ack/tx) instead of on the "
                                        "actuation message the encoder also reads")
    colocate: tuple[str, ...] = _shared(
        (), "run the encoder inside the plant's process, as a smart sensor does: no sensor hop (three network hops "
            "per sample instead of four)", choices=tuple(sorted(transport.COLOCATABLE)), metavar="encoder",
        convert=transport.colocated_roles)

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

    @staticmethod
    def override_flags() -> dict[str, str]:
        """The options that override a scenario key (``testbed.scenario.OVERRIDES``) -> their flag."""
        return {f.name: optionspec.flag_of(f, o) for f, o in optionspec.options(RunOptions)
                if not o.switch and f.name != "colocate"}

    def overrides(self) -> dict:
        """The scenario overrides (``testbed.scenario.with_overrides``): the valued options, None left out."""
        return {k: getattr(self, k) for k in self.override_flags() if getattr(self, k) is not None}

    def cli(self) -> list[str]:
        """The same options as command-line flags (for the launcher)."""
        return optionspec.argv(self, "node")

    def join_fields(self) -> dict:
        """The options as the join file carries them (``run_options``: every option a node takes, tuples as lists)."""
        return {f.name: list(v) if isinstance(v := getattr(self, f.name), tuple) else v
                for f, _ in optionspec.options(RunOptions, "node")}

    @classmethod
    def of_join(cls, d: dict, where: str = "join file") -> RunOptions:
        """The options of a join file's ``run_options`` (``join_fields``); an unknown one is ``BadInput``."""
        from ..common.errors import BadInput

        known = {f.name: f for f, _ in optionspec.options(cls, "node")}
        for k in d:
            if k not in known:
                raise BadInput(f"{where}: unknown run option {k!r}")
        given: dict[str, Any] = {k: tuple(v or ()) if isinstance(known[k].default, tuple) else v for k, v in d.items()}
        return cls(**given)


def add_run_option_arguments(p: argparse.ArgumentParser,
                             title: str = "run options (must be the same for every node of a run)") -> None:
    optionspec.add_arguments(p, RunOptions, "run", group=p.add_argument_group(title))


# ============================================================================ one process's configuration
def _node(default=None, help="", group="node", **kw):
    return option(default, help, commands=("node",), group=group, **kw)


def _record(default=None, help="", **kw):
    return option(default, help, commands=("record",), **kw)


@dataclass(frozen=True)
class NodeConfig:
    """One node process of a run (``testbed node ROLE``): the run's options, its session, and its own settings
    (each field the one definition of its flag: ``testbed.common.optionspec``).

    ``scenario`` None: the run of the join file named by ``$TESTBED_JOIN`` (``testbed.nodes.joined``)."""

    role: str
    scenario: str | None
    opts: RunOptions = RunOptions()
    session: SessionOptions = SessionOptions()
    ready_timeout: float = _node(120.0, "give up if the other nodes are not up after S seconds (default %(default)s)",
                                 kind=float, metavar="S")
    realtime: bool = _node(False, "run the loop under SCHED_FIFO (needs CAP_SYS_NICE)")
    cpus: str | None = _node(help="pin this node to these CPUs, e.g. 2 or 2,3 or 2-3", metavar="LIST")
    rx: str = _node("thread", "how control messages are received: thread (zenoh-python's callback thread), direct "
                              "(on Zenoh's own receive thread where the handler never waits), spin (direct, and the "
                              "node's input on the loop's path is polled just before it is due) (default %(default)s)",
                    choices=RX_MODES)
    rx_spin_us: float | None = _node(help="--rx spin: spin at most this long per sample (default min(1000, T/20 in us))",
                                     kind=float, metavar="US")
    parent_pid: int | None = _node(kind=int, hidden=True)
    launched: bool = _node(False, hidden=True)  # started by testbed run: waits for its collector, stops when it goes
    crash_at: int | None = _node(help="fault injection: raise at sample K", kind=int, metavar="K")
    verbose: bool = _node(False, "log at INFO (start-up, every event)", short="-v")
    rerun_url: str | None = _node(help="stream this node's telemetry to a Rerun gRPC URL", metavar="URL",
                                  group="rerun (testbed run --rerun passes these)")
    rerun_save: str | None = _node(help="write this node's telemetry to a Rerun file", metavar="PATH.rrd",
                                   group="rerun (testbed run --rerun passes these)")
    recording_id: str | None = _node(help="Rerun recording id shared by the nodes of a run (default: --run-id)",
                                     group="rerun (testbed run --rerun passes these)")
    wait_collector: bool = _node(False, "also wait for the launcher's collector before starting", group="plant")
    start_lead: float = _node(0.2, "t0 = now + S once everybody is ready (default %(default)s)", kind=float,
                              metavar="S", group="plant")
    spin_us: float | None = _node(help="busy-wait this long before each sample instant (default min(200, T/20 in us))",
                                  kind=float, metavar="US", group="plant")
    encoder_crash_at: int | None = _node(
        help="--colocate encoder: fault injection: the colocated encoder raises at sample K (it alone stops)", kind=int,
        metavar="K", group="plant")
    ack_grace: float | None = _node(help="wait this fraction of T for a late ack before withholding (default 0.2 d)",
                                    kind=float, metavar="FRACTION", group="encoder")
    corrupt: str | None = _node(help="fault injection: corrupt the payload of these samples",
                                metavar="K[:range|:length],...", group="attacker")

    def argv(self) -> list[str]:
        """``testbed node`` and the flags that make the same configuration (the launcher's command line)."""
        return ["node", self.role, *([self.scenario] if self.scenario is not None else []), *self.opts.cli(),
                *self.session.argv(), *optionspec.argv(self, "node")]


#: the recorder's exit code when its file could not be written to the end (``RecordingFailed``)
RECORD_FAILED = 4


@dataclass(frozen=True)
class RecorderConfig:
    """The recorder process of a run (``testbed record``; each field the one definition of its flag)."""

    scenario: str
    opts: RunOptions = RunOptions()
    session: SessionOptions = SessionOptions()
    out: str | None = _record(help="recording file (default recordings/<scenario>-<UTC start>-<run id>.mcap); never "
                                   "overwritten", metavar="PATH.mcap")
    force: bool = _record(False, "replace an existing --out file")
    loop: str = _record("auto", "record the control-path messages too (auto: when T >= 10 ms; default %(default)s)",
                        choices=("auto", "on", "off"))
    flush: float = _record(0.5, "flush the file at least every S seconds (what a SIGKILL can lose; default "
                                "%(default)s)", kind=float, metavar="S")
    linger: float = _record(2.0, "standalone: stop S seconds after the plant's Stop (default %(default)s)", kind=float,
                            metavar="S")
    nice: int = _record(10, "run at this nice value so the loop's nodes go first on a busy machine (default "
                            "%(default)s)", kind=int, metavar="N")
    cpus: str | None = _record(help="pin the recorder to these CPUs, e.g. 6 or 6,7", metavar="LIST")
    parent_pid: int | None = _record(kind=int, hidden=True)
    launched: bool = _record(False, hidden=True)  # by testbed run
    scenario_ref: str | None = _record(hidden=True)
    verbose: bool = _record(False, "log at INFO (start-up, every event)", short="-v")

    def argv(self) -> list[str]:
        """``testbed record`` and the flags that make the same configuration (the launcher's command line)."""
        return ["record", self.scenario, *self.opts.cli(), *self.session.argv(), *optionspec.argv(self, "record")]


def pairs(items: Iterable[str], sep: str, what: str, roles: Sequence[str] = transport.ROLES) -> dict[str, str]:
    """Repeated ``ROLE<sep>VALUE`` flags -> {role: value}; one clear line for a malformed one."""
    from ..common.errors import BadInput

    out = {}
    for it in items:
        role, s, val = it.partition(sep)
        if not s or role not in roles:
            raise BadInput(f"{what} must be ROLE{sep}VALUE with ROLE in {', '.join(roles)}, got {it!r}")
        out[role] = val
    return out


def _number(kind, value: str, flag: str):
    """A time (``float``, seconds) or a sample index (``int``) of ``ROLE@VALUE``: finite and >= 0."""
    from ..common import validate
    from ..common.errors import BadInput

    try:
        return validate.text_number(value, kind)
    except validate.Invalid as e:
        raise BadInput(f"{flag}: {e}") from None


def _roles(sep: str, flag: str, who=transport.ROLES, number=None):
    """The converter of a repeatable ``ROLE<sep>VALUE`` flag: {role: value} (``number``: the value checked)."""
    def convert(items):
        d = pairs(items, sep, flag, who)
        return d if number is None else {r: _number(number, v, flag) for r, v in d.items()}
    return convert


def _run(default=None, help="", group="run control", **kw):
    return option(default, help, commands=("run",), group=group, **kw)


@dataclass(frozen=True)
class RunConfig:
    """A whole live run (``testbed run``): built once from the command line (``testbed.commands.liveconfig``)
    and passed to the launcher (``testbed.live.launcher``), which builds each node's ``NodeConfig`` and the
    recorder's ``RecorderConfig`` from it.  The field names are those of ``testbed run``'s flags; a
    repeatable ``ROLE=VALUE`` or ``ROLE@VALUE`` flag is a dict by role.  The fields with an ``option`` are the one
    definition of their flag (``testbed.common.optionspec``); the others' flags are defined by the module that uses them
    (``cliargs``, ``live.netns``, ``live.recorder``, ``view.rerun``, ``live.external``)."""

    scenario: str
    opts: RunOptions = RunOptions()
    session: SessionOptions = field(default_factory=lambda: SessionOptions.of("run"))
    json: bool = False
    # network and security
    node_connect: str | None = _run(help="endpoint the nodes connect to (default: --listen)", metavar="ENDPOINT",
                                    group="network")
    node_listen: dict = _run({}, "a node's own listener (default tcp/127.0.0.1:0), e.g. plant=tcp/10.0.0.2:0",
                             metavar="ROLE=ENDPOINT", repeat=True, group="network",
                             convert=_roles("=", "--node-listen"))     # role -> endpoint
    node_prefix: dict = _run({}, "run a node under a command, e.g. plant='ip netns exec tb-plant' or 'ssh host'",
                             metavar="ROLE=COMMAND", repeat=True, group="network",
                             convert=_roles("=", "--node-prefix"))     # role -> command
    netns: bool = False
    netns_clean: bool = False
    # recording
    out: str | None = None
    force: bool = _run(False, "replace an existing --out file", group="recording")
    no_record: bool = _run(False, "do not record the run", group="recording")
    on_record_error: str = "continue"
    record_loop: str = _run("auto", "also record the control-path messages (auto: when T >= 10 ms)",
                            choices=("auto", "on", "off"), group="recording")
    # viewers and a node from outside
    rerun: tuple[str, ...] | None = None
    rrd: str | None = None
    roa: bool = True
    foxglove: int | None = _run(
        help=f"serve the run live over Foxglove's WebSocket protocol on 127.0.0.1:PORT (default {FOXGLOVE_PORT}; "
             "needs foxglove-sdk); connect Foxglove to ws://127.0.0.1:PORT", kind=int, nargs="?", const=FOXGLOVE_PORT,
        metavar="PORT", group="foxglove (live view)")
    foxglove_linger: float = _run(0.0, "keep the server up S seconds after the run (default %(default)s)", kind=float,
                                  metavar="S", group="foxglove (live view)")
    external: str | None = None
    # run control
    startup_timeout: float = option(
        120.0, "give up if the nodes are not running after S seconds (default %(default)s)", kind=float, metavar="S",
        commands=("run", "conformance"), group="run control",
        per={"conformance": {"help": "the node must have joined and the run started within S seconds (default "
                                     "%(default)s)"}})
    run_dir: str | None = _run(help="directory for node logs (default: a temporary one, kept on faults)")
    spawn: str = _run("fork", "how local nodes start: fork (default) from the launcher, which has loaded Python, numba "
                              "and the loop's compiled kernels once, or exec (a fresh 'python -m testbed.cli node' per "
                              "node, as with --node-prefix, which always execs)", choices=("fork", "exec"))
    realtime: str = _run("auto", "the nodes' loops and the run's router under SCHED_FIFO: on (--realtime alone), off, "
                                 f"or auto (default): on when T < {FAST_T * 1e3:g} ms and this user may (root or "
                                 "CAP_SYS_NICE), where a scheduling delay of a millisecond misses a deadline",
                         choices=("auto", "on", "off"), nargs="?", const="on", metavar="auto|on|off")
    cpu: dict = _run({}, "pin a node (plant, encoder, attacker, controller), the recorder or the launcher (the run's "
                         "router) to CPUs, e.g. plant=2 or launcher=0,1 (repeatable)", metavar="WHO=CPUS", repeat=True,
                     convert=_roles("=", "--cpu", (*transport.ROLES, transport.RECORDER, transport.LAUNCHER)))
    rx: str | None = _run(help="how the nodes receive control messages (testbed node --rx)", choices=RX_MODES)
    rx_spin_us: float | None = _run(help="--rx spin: spin budget per sample (us)", kind=float)
    spin_us: float | None = _run(help="plant busy-wait before each sample instant (us)", kind=float)
    ack_grace: float | None = _run(help="encoder grace for a late ack, fraction of T", kind=float)
    verbose: bool = _run(False, "nodes log at INFO", short="-v")
    progress: bool = _run(False, "the status line (sample k of N, losses by cause, deadline misses, E_k at both ends, "
                                 "about once a second) on stderr even when it is not a terminal (on a terminal it is "
                                 "always shown)")
    # fault injection
    kill: dict = _run({}, "SIGKILL a node (or the recorder) SECONDS after t0 (repeatable)", metavar="ROLE@SECONDS",
                      repeat=True, group="fault injection",
                      convert=_roles("@", "--kill", (*transport.ROLES, transport.RECORDER), float))
    stall: tuple[str, ...] = _run((), "freeze a node's process (SIGSTOP) SECONDS after t0 and resume it (SIGCONT) "
                                      "DURATION seconds later (repeatable)", metavar="ROLE@SECONDS:DURATION",
                                  repeat=True, group="fault injection")  # ``testbed.live.stalls``
    crash: dict = _run({}, "make a node raise at sample K (repeatable)", metavar="ROLE@K", repeat=True,
                       group="fault injection", convert=_roles("@", "--crash", number=int))  # role -> sample
    corrupt: str | None = _run(help="the attacker corrupts the payload of these samples",
                               metavar="K[:range|:length],...", group="fault injection")
    cut: tuple[str, ...] = ()                            # ROLE@SECONDS:DURATION (``testbed.live.netns``)

    # the launcher's session, by the names of its flags
    run_id = property(lambda self: self.session.run_id)
    listen = property(lambda self: self.session.listen[0] if self.session.listen else None)
    zenoh_config = property(lambda self: self.session.zenoh_config)
    topology = property(lambda self: self.session.topology)
    secret_file = property(lambda self: self.session.secret_file)
    tls_dir = property(lambda self: self.session.tls_dir)
    insecure = property(lambda self: self.session.insecure)
    low_latency = property(lambda self: self.session.low_latency)

    def sched_fifo(self, T: float) -> bool:
        """Whether the nodes' loops and the run's router ask for SCHED_FIFO in a run of sample period ``T``: the one
        reading of ``--realtime`` (``auto``: a loop faster than ``FAST_T``, where this process may)."""
        if self.realtime == "auto":
            from .process import fifo_permitted

            return T < FAST_T and fifo_permitted()
        return self.realtime == "on"


def load_scenario(ref: str | Scenario, opts: RunOptions, *, check_design: bool = True) -> Scenario:
    """Load a scenario (a file, a bundled name, or a loaded ``Scenario``) and apply the run overrides
    (validated as if written in the file).

    ``check_design=False`` (a node started by the launcher, which checked the same text and
    overrides): skip the Schur check of a given K, so that the node needs no scipy.
    """
    from .. import scenario
    from ..record.tracereader import read_recording_trace

    over = opts.overrides()
    if isinstance(ref, str):  # parsed and built once, the overrides applied to the parsed text
        return scenario.load(ref, check_design=check_design, overrides=over,
                             read_recording_trace=read_recording_trace)
    return scenario.with_overrides(ref, over, check_design=check_design, read_recording_trace=read_recording_trace)


def T_ns(sc: Scenario) -> int:
    return int(round(sc.T * 1e9))


def run_digest(sc: Scenario, opts: RunOptions) -> str:
    """What all nodes must agree on: the scenario text, the resolved loop, the run options, and the plant's
    and the method's module (the method's reference and params, a ``--method`` swap included, and the
    sha256 of each module's source: the same code in every node)."""
    d = {"source": sc.source, "K": sc.K.tolist(), "T": sc.T, "n_steps": sc.n_steps,
         "quantizer": dataclasses.asdict(sc.quantizer), "run": dataclasses.asdict(sc.run),
         "ack_via_attacker": opts.ack_via_attacker, "ack_on_actuation": opts.ack_on_actuation,
         "colocate": list(opts.colocate),
         "plant_sha256": sc.plant.source_info()["sha256"],
         "method": [sc.method.name, [list(p) for p in sc.method.params]],
         "method_sha256": sc.method.source_info()["sha256"]}
    return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:16]


def attack_horizon(sc: Scenario) -> float:
    """Horizon of the offline DoS schedule: the run's duration, as ``testbed simulate`` uses."""
    return sc.n_steps * sc.T
