"""The options of a live run that every node must share (they enter the start digest), and the
scenario they make."""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
from dataclasses import dataclass

from ..wire import transport


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

    @classmethod
    def from_args(cls, args) -> "RunOptions":
        return cls(**{k: getattr(args, k, None) for k, _ in cls._OVERRIDES},
                   ack_via_attacker=bool(getattr(args, "ack_via_attacker", False)),
                   separate_ack=bool(getattr(args, "separate_ack", False)),
                   colocate=transport.colocated_roles(getattr(args, "colocate", None)))

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

    base = scenario.load(ref, check_design=check_design) if isinstance(ref, str) else ref
    return scenario.with_overrides(base, opts.overrides(),
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
