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
from dataclasses import dataclass, field

from ..wire import transport
from ..wire.session import SessionOptions


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
    method: str | None = None
    ack_via_attacker: bool = False
    separate_ack: bool = False
    colocate: tuple[str, ...] = ()

    _OVERRIDES = (("duration", "--duration"), ("T", "--T"), ("timing", "--timing"), ("deadline", "--deadline"),
                  ("mode", "--mode"), ("loss_fraction", "--loss-fraction"), ("actuation", "--actuation"),
                  ("rule", "--rule"), ("seed", "--seed"), ("method", "--method"))

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


# ============================================================================ one process's configuration
def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _settings(cfg) -> list[str]:
    """A process configuration's own settings as flags: ``--NAME VALUE`` for each of its ``_VALUED`` that is set,
    ``--NAME`` for each of its ``_SWITCHES`` that is on."""
    out = []
    for name in cfg._VALUED:
        v = getattr(cfg, name)
        if v is not None:
            out += [_flag(name), repr(v) if isinstance(v, float) else str(v)]
    return out + [_flag(name) for name in cfg._SWITCHES if getattr(cfg, name)]


@dataclass(frozen=True)
class NodeConfig:
    """One node process of a run (``testbed node ROLE``): the run's options, its session, and its own settings.

    ``scenario`` None: the run of the join file named by ``$TESTBED_JOIN`` (``testbed.nodes.joined``)."""

    role: str
    scenario: str | None
    opts: RunOptions = RunOptions()
    session: SessionOptions = SessionOptions()
    ready_timeout: float = 120.0
    realtime: bool = False
    cpus: str | None = None
    rx: str = "thread"
    rx_spin_us: float | None = None
    parent_pid: int | None = None
    launched: bool = False                # started by testbed run: waits for its collector, stops when it goes
    crash_at: int | None = None
    verbose: bool = False
    rerun_url: str | None = None
    rerun_save: str | None = None
    recording_id: str | None = None
    wait_collector: bool = False
    start_lead: float = 0.2
    spin_us: float | None = None
    encoder_crash_at: int | None = None
    ack_grace: float | None = None
    corrupt: str | None = None

    #: settings passed on as ``--NAME VALUE`` when set (``argv``)
    _VALUED = ("ready_timeout", "cpus", "rx", "rx_spin_us", "parent_pid", "crash_at", "rerun_url", "rerun_save",
               "recording_id", "start_lead", "spin_us", "encoder_crash_at", "ack_grace", "corrupt")
    _SWITCHES = ("realtime", "launched", "verbose", "wait_collector")

    def argv(self) -> list[str]:
        """``testbed node`` and the flags that make the same configuration (the launcher's command line)."""
        return ["node", self.role, *([self.scenario] if self.scenario is not None else []), *self.opts.cli(),
                *self.session.argv(), *_settings(self)]


#: the recorder's exit code when its file could not be written to the end (``RecordingFailed``)
RECORD_FAILED = 4


@dataclass(frozen=True)
class RecorderConfig:
    """The recorder process of a run (``testbed record``)."""

    scenario: str
    opts: RunOptions = RunOptions()
    session: SessionOptions = SessionOptions()
    out: str | None = None
    force: bool = False
    loop: str = "auto"
    flush: float = 0.5
    linger: float = 2.0
    nice: int = 10
    cpus: str | None = None
    parent_pid: int | None = None
    launched: bool = False
    scenario_ref: str | None = None
    verbose: bool = False

    _VALUED = ("out", "loop", "flush", "linger", "nice", "cpus", "parent_pid", "scenario_ref")
    _SWITCHES = ("force", "launched", "verbose")

    def argv(self) -> list[str]:
        """``testbed record`` and the flags that make the same configuration (the launcher's command line)."""
        return ["record", self.scenario, *self.opts.cli(), *self.session.argv(), *_settings(self)]


@dataclass(frozen=True)
class RunConfig:
    """A whole live run (``testbed run``): built once from the command line (``testbed.commands.liveconfig``)
    and passed to the launcher (``testbed.live.launcher``), which builds each node's ``NodeConfig`` and the
    recorder's ``RecorderConfig`` from it.  The field names are those of ``testbed run``'s flags; a
    repeatable ``ROLE=VALUE`` or ``ROLE@VALUE`` flag is a dict by role."""

    scenario: str | None
    opts: RunOptions = RunOptions()
    json: bool = False
    # network and security
    run_id: str | None = None
    listen: str | None = None
    node_connect: str | None = None
    node_listen: dict = field(default_factory=dict)      # role -> endpoint
    node_prefix: dict = field(default_factory=dict)      # role -> command
    zenoh_config: str | None = None
    topology: str = "auto"
    secret_file: str | None = None
    tls_dir: str | None = None
    insecure: bool = False
    low_latency: bool = False
    netns: bool = False
    netns_clean: bool = False
    # recording
    out: str | None = None
    force: bool = False
    no_record: bool = False
    on_record_error: str = "continue"
    record_loop: str = "auto"
    # viewers and a node from outside
    rerun: tuple[str, ...] | None = None
    rrd: str | None = None
    roa: bool = True
    foxglove: int | None = None
    foxglove_linger: float = 0.0
    external: str | None = None
    # run control
    startup_timeout: float = 120.0
    run_dir: str | None = None
    spawn: str = "fork"
    realtime: bool = False
    cpu: dict = field(default_factory=dict)              # role, recorder or launcher -> CPU list
    rx: str | None = None
    rx_spin_us: float | None = None
    spin_us: float | None = None
    ack_grace: float | None = None
    verbose: bool = False
    progress: bool = False                               # the status line on stderr on a pipe too (``live.status``)
    # fault injection
    kill: dict = field(default_factory=dict)             # role or recorder -> seconds after t0
    stall: tuple[str, ...] = ()                          # ROLE@SECONDS:DURATION (``testbed.live.stalls``)
    crash: dict = field(default_factory=dict)            # role -> sample
    corrupt: str | None = None
    cut: tuple[str, ...] = ()                            # ROLE@SECONDS:DURATION (``testbed.live.netns``)


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
    g.add_argument("--method", metavar="NAME",
                   help="override [method] name: the coding-and-control method (testbed methods lists them; "
                        "[quantizer] keys it does not use are ignored with a note)")
    g.add_argument("--ack-via-attacker", action="store_true",
                   help="route the controller's acks through the attacker proxy too")
    g.add_argument("--separate-ack", action="store_true",
                   help="send the ideal ack as a message of its own (loop/ack/tx) instead of on the actuation "
                        "message the encoder also reads")
    g.add_argument("--colocate", choices=sorted(transport.COLOCATABLE), metavar="encoder",
                   help="run the encoder inside the plant's process, as a smart sensor does: no sensor hop "
                        "(three network hops per sample instead of four)")


def load_scenario(ref, opts: RunOptions, *, check_design: bool = True):
    """Load a scenario (a file, a bundled name, or a loaded ``Scenario``) and apply the run overrides
    (validated as if written in the file).

    ``check_design=False`` (a node started by the launcher, which checked the same text and
    overrides): skip the Schur check of a given K, so that the node needs no scipy.
    """
    from .. import scenario

    if isinstance(ref, str):  # parsed and built once, the overrides applied to the parsed text
        return scenario.load(ref, check_design=check_design, overrides=opts.overrides())
    return scenario.with_overrides(ref, opts.overrides(), check_design=check_design)


def T_ns(sc) -> int:
    return int(round(sc.T * 1e9))


def run_digest(sc, opts: RunOptions) -> str:
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


def attack_horizon(sc) -> float:
    """Horizon of the offline DoS schedule: the run's duration, as ``testbed simulate`` uses."""
    return sc.n_steps * sc.T
