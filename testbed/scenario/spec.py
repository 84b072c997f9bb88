"""What a scenario file becomes: frozen dataclasses, one per section (``[plant]``, ``[model]``,
``[quantizer]``, ``[controller]``, ``[attack]``, ``[run]``, ``[flow]``), and the ``Scenario`` that holds
them.  ``testbed.scenario`` reads and validates the TOML into them."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Generic, Self, TypeVar

import numpy as np

import plants
from attackers import generators as attack_generators

from ..common.errors import BadInput
from ..loop.channel import NetworkModel
from ..loop.device import DeviceSpec
from ..loop.params import FlowOptions, QuantizerParams

if TYPE_CHECKING:
    from attackers.schedule import Schedule
    from plants.base import PlantProcess
    from plants.fmu import FMUPlant

    from ..methods.base import Method


def _freeze(v: Any) -> Any:
    if isinstance(v, list):
        return tuple(_freeze(x) for x in v)
    if isinstance(v, dict):
        return tuple(sorted((k, _freeze(x)) for k, x in v.items()))
    return v


def _thaw(v: Any) -> Any:
    if isinstance(v, tuple):
        return [_thaw(x) for x in v]
    return v


class ScenarioError(BadInput):
    """A scenario file that cannot be used, with the reason."""


# ----------------------------------------------------------------------------- dataclasses
B = TypeVar("B")


@dataclass(frozen=True)
class BuiltOnce(Generic[B]):
    """A spec that builds its object (a plant, a model, a method) once per process and keeps it in ``built``:
    not compared, not copied by ``dataclasses.replace`` (init=False: the copy builds its own), not pickled
    (a worker builds its own).  The objects are immutable (a run's state lives in the ends and processes)."""

    built: B | None = field(default=None, init=False, repr=False, compare=False)

    def _build(self) -> B:  # pragma: no cover - each spec says how
        raise NotImplementedError

    def make(self) -> B:
        """The object, built on the first call (or handed over by the scenario's check) and kept."""
        built = self.built
        if built is None:
            built = self._build()
            object.__setattr__(self, "built", built)
        return built

    def with_built(self, obj: B | None) -> Self:
        """This spec holding ``obj``, the object the scenario's check built from it."""
        object.__setattr__(self, "built", obj)
        return self

    def __getstate__(self) -> dict:
        return {**self.__dict__, "built": None}


@dataclass(frozen=True)
class PlantSpec(BuiltOnce["plants.Plant"]):
    name: str                      # the plant's display name (its class's ``name``; "fmu:FILE" for an FMU)
    params: tuple[tuple[str, Any], ...]
    x0: tuple[float, ...]
    ref: str = ""                  # [plant] name as written: registered, entry point or "module:Class"
    base_dir: str = ""             # the scenario file's folder ("" for bundled scenarios and strings)
    fmu: FMUSpec | None = None     # [plant] fmu = "...": the true plant is an FMU
    device: DeviceSpec | None = None  # [plant.sensor], [plant.actuator], [plant.disturbance] (``testbed.loop.device``)

    def _build(self) -> plants.Plant:
        if self.fmu is not None:
            raise ScenarioError(f"the plant is the FMU {self.fmu.path}: it has no equation (1) object "
                                "(the [model] section gives one)")
        return plants.make(self.ref or self.name, self.base_dir or None, **dict(self.params))

    def source_info(self) -> dict[str, str]:
        """The plant module's ``module``, ``class``, ``file``, ``source`` and ``sha256`` (``plants.refs.source_info``).

        For an FMU: its ``file`` and the sha256 of the file (no source)."""
        if self.fmu is not None:
            import hashlib

            try:
                sha = hashlib.sha256(Path(self.fmu.path).read_bytes()).hexdigest()
            except OSError:
                sha = ""
            return {"module": "", "class": "", "file": self.fmu.path, "source": "", "sha256": sha}
        from plants.refs import source_info

        return source_info(plants.resolve(self.ref or self.name, self.base_dir or None))


@dataclass(frozen=True)
class MethodSpec(BuiltOnce["Method"]):
    """``[method] name = "...", params = {...}``: the coding-and-control method (default the paper's)."""

    name: str = "paper"            # a bundled or registered name, an entry point or "module.path:ClassName"
    params: tuple[tuple[str, Any], ...] = ()
    base_dir: str = ""             # the scenario file's folder ("module:Class" methods are imported from it)

    def _build(self) -> Method:
        """The method object (``testbed.methods.Method``: its params, a factory of ends): a run's state lives in
        its ends, never in the method."""
        from .. import methods

        return methods.make(self.name, self.base_dir or None, _thaw(self.params))

    def source_info(self) -> dict[str, str]:
        """The method module's ``module``, ``class``, ``file``, ``source`` and ``sha256`` (as for plants)."""
        from .. import methods

        return methods.source_info(methods.resolve(self.name, self.base_dir or None))


@dataclass(frozen=True)
class FMUSpec:
    """``[plant] fmu = "plant.fmu"``, ``inputs = [...]``, ``states = [...]``, ``params = {...}``."""
    path: str                                  # absolute (resolved against the scenario's folder)
    inputs: tuple[str, ...]
    states: tuple[str, ...]
    params: tuple[tuple[str, Any], ...] = ()
    checked: bool = True                       # False: read from a recording, the file not looked at

    def open(self) -> FMUPlant:
        """The FMU as a ``plants.PlantProcess`` (``plants.fmu.FMUPlant``)."""
        from plants.fmu import FMUPlant

        return FMUPlant(self.path, inputs=self.inputs, states=self.states, params=dict(self.params))


@dataclass(frozen=True)
class ModelSpec(BuiltOnce["plants.Plant"]):
    """``[model]``: the plant model of the predictions (rule (xi)), the LQR design and the analysis."""

    name: str                  # a plant reference, resolved as [plant] name is
    params: tuple[tuple[str, Any], ...]
    explicit: bool = False     # the scenario has a [model] section
    base_dir: str = ""         # the scenario file's folder

    def _build(self) -> plants.Plant:
        return plants.make(self.name, self.base_dir or None, **dict(self.params))


@dataclass(frozen=True)
class ControllerSpec:
    K: tuple[tuple[float, ...], ...]           # resolved gain, m x n
    source: str                                # "K" or "lqr"
    Q: tuple[tuple[float, ...], ...] | None = None
    R: tuple[tuple[float, ...], ...] | None = None
    u_max: float = 1e6                         # actuator limit: the plant clamps |u_k| to it

    @property
    def K_array(self) -> np.ndarray:
        return np.array(self.K, dtype=float)


@dataclass(frozen=True)
class AttackSpec:
    kind: str
    params: tuple[tuple[str, Any], ...]
    budget: tuple[float, float, float, float] | None  # (kappa_F, rho_F, kappa_D, rho_D) if known

    @property
    def params_dict(self) -> dict[str, Any]:
        return dict(self.params)

    @property
    def online(self) -> bool:
        return self.kind == "greedy"

    def greedy_params(self) -> np.ndarray:
        d = self.params_dict
        return np.array([d["kappa_F"], d["rho_F"], d["kappa_D"], d["rho_D"], d.get("threshold", 0.0)])

    @property
    def score(self) -> str:
        return self.params_dict.get("score", "state")

    def schedule(self, T: float, horizon: float) -> Schedule | None:
        """The offline schedule (None for the online greedy attacker)."""
        if self.online:
            return None
        d = {k: _thaw(v) for k, v in self.params}
        seed = d.pop("seed", None)
        return attack_generators.make_schedule(self.kind, d, T=T, horizon=horizon, seed=seed)


@dataclass(frozen=True)
class DelaySpec:
    """An actuation-delay bound [s] the delay-aware quantizer rule covers (``[run] delay``, ``delay_lost``)."""

    nominal: float
    min: float
    max: float
    declared: bool = False     # written in the scenario (else the default)


@dataclass(frozen=True)
class SimDelaySpec:
    """``[run] sim_delay``: how long u_k takes to reach the plant in a simulated physical-timing run.

    The latency after t_k of a received sample's u_k (a lost sample's u_k = 0 leaves the
    controller at its loss deadline and takes the same latency after it).
    """

    kind: str = "constant"     # "constant" | "uniform" | "trace"
    value: float = 0.0         # constant
    min: float = 0.0           # uniform
    max: float = 0.0
    seed: int | None = None
    values: tuple[float, ...] = ()  # trace

    def draw(self, n_steps: int) -> np.ndarray:
        """The latency of sample k = 0..N-1 in integer ns (a trace shorter than N holds its last value)."""
        if self.kind == "constant":
            v = np.full(n_steps, self.value)
        elif self.kind == "uniform":
            v = np.random.default_rng(self.seed).uniform(self.min, self.max, n_steps)
        else:
            t = np.asarray(self.values, dtype=float)
            v = np.full(n_steps, t[-1] if t.size else 0.0)
            v[:min(n_steps, t.size)] = t[:n_steps]
        return np.round(v * 1e9).astype(np.int64)


@dataclass(frozen=True)
class RunSpec:
    duration: float
    converge_tol: float = 1e-4
    timing: str = "ideal"          # live plant: "ideal" | "physical"
    deadline: float = 0.5          # live plant: fraction of T to wait for u_k
    loss_fraction: float = 0.8     # the controller decides a sample lost at t_k + loss_fraction d T
    actuation: str = "scheduled"   # physical timing: u_k acts at its scheduled instant | on arrival
    delay: DelaySpec | None = None       # physical timing: a received sample's actuation delay (bound)
    delay_lost: DelaySpec | None = None  # ... and a lost sample's (u_k = 0 from the loss deadline)
    sim_delay: SimDelaySpec | None = None   # physical timing: the simulator's latency of u_k


@dataclass(frozen=True)
class Scenario:
    name: str
    plant: PlantSpec
    quantizer: QuantizerParams
    controller: ControllerSpec
    attack: AttackSpec
    run: RunSpec
    flow: FlowOptions
    source: str = ""       # the TOML text it was read from (stored in recordings)
    path: str = ""
    description: str = ""  # one line (``testbed scenarios``)
    model: ModelSpec | None = None   # [model] (defaults to [plant]'s)
    L_u: float = 0.0       # input gain of the model (delay-aware rule)
    base_dir: str = ""     # the file's folder: "module:Class" plants are imported from there first
    method: MethodSpec = MethodSpec()   # [method] (default: the paper's)
    method_note: str = ""  # a swapped method (``--method``): what it leaves out, one line (testbed.scenario.methodswap)
    network: NetworkModel | None = None   # [network]: the emulated channels (None: ideal links)
    # the TOML document of ``source`` as it was parsed, once (``document``)
    doc: dict = field(default_factory=dict, repr=False, compare=False)

    def document(self) -> dict:
        """The parsed TOML of ``source``, a copy to edit: the text is parsed once, when the scenario is read
        (``testbed.scenario.loads``); overrides, method swaps and campaign points edit this copy."""
        import copy

        if self.doc or not self.source:
            return copy.deepcopy(self.doc)
        import tomllib

        return tomllib.loads(self.source)

    def make_method(self) -> Method:
        """The coding-and-control method ([method]; ``testbed.methods.Method``)."""
        return self.method.make()

    def code_not_run(self) -> list[str]:
        """One line for each of the plant, the model and the method whose code is not here: a recording's
        module that is not importable and whose stored source was not run (``testbed.open`` without
        ``trust_code``, a reader without ``--trust-code``; ``plants.refs.stand_in_plant``).  What needs that
        code (re-simulation, the escape verdict, the region of attraction) is skipped; empty: all runs."""
        from plants.refs import not_run

        from .. import methods

        classes: list[type] = [methods.resolve(self.method.name, self.method.base_dir or None)]
        if self.plant.fmu is None:
            classes.append(plants.resolve(self.plant.ref or self.plant.name, self.plant.base_dir or None))
        if self.model is not None:
            classes.append(plants.resolve(self.model.name, self.model.base_dir or None))
        return [w for w in dict.fromkeys(not_run(c) for c in classes) if w]

    @property
    def T(self) -> float:
        return self.quantizer.T

    @property
    def n_steps(self) -> int:
        return int(round(self.run.duration / self.quantizer.T))

    @property
    def K(self) -> np.ndarray:
        return self.controller.K_array

    @property
    def x0(self) -> np.ndarray:
        return np.array(self.plant.x0, dtype=float)

    def make_plant(self) -> plants.Plant:
        """The true plant ([plant]): what the simulator and the live plant node integrate."""
        return self.plant.make()

    def make_model(self) -> plants.Plant:
        """The plant model ([model], default [plant]: then the plant object itself)."""
        if (self.model is None or not self.model.explicit) and self.plant.fmu is None:
            return self.plant.make()
        return (self.model or ModelSpec(self.plant.ref or self.plant.name, self.plant.params,
                                        base_dir=self.plant.base_dir)).make()

    def make_process(self) -> PlantProcess:
        """The true plant as it advances in time (``plants.base.PlantProcess``): an ODE plant or an FMU."""
        if self.plant.fmu is not None:
            return self.plant.fmu.open()
        from ..loop.protocol import OdeProcess

        return OdeProcess(self.make_plant(), self.flow)

    def sim_latency(self, n_steps: int | None = None) -> np.ndarray | None:
        """The latency [ns] of u_k in a simulated run (``[run] sim_delay``; None under ideal timing).

        Default: a constant latency at the received sample's nominal actuation delay under
        arrival actuation, and 0 under scheduled actuation (every u_k then acts on schedule); with a
        ``[network]`` section 0 (the links' delays are added by the simulator; a ``sim_delay`` given
        is the nodes' own latency on top of them).
        """
        if self.run.timing != "physical":
            return None
        N = self.n_steps if n_steps is None else n_steps
        if self.network is not None and self.run.sim_delay is None:
            return np.zeros(N, dtype=np.int64)   # the [network] links' delays are u_k's latency
        assert self.run.delay is not None  # physical timing: parsed with its bound
        spec = self.run.sim_delay or SimDelaySpec(
            "constant", value=self.run.delay.nominal if self.run.actuation == "arrival" else 0.0)
        return spec.draw(N)

    @property
    def timing_params(self) -> np.ndarray:
        """[physical, scheduled, delta_s, d T, loss deadline] in integer ns (``PlantProtocol``, the kernel)."""
        r = self.run
        Tn = int(round(self.T * 1e9))
        sched = int(round(r.delay.nominal * 1e9)) if (r.timing == "physical" and r.delay) else 0
        return np.array([int(r.timing == "physical"), int(r.actuation == "scheduled"), sched,
                         int(r.deadline * Tn), int(r.loss_fraction * r.deadline * Tn)], dtype=np.int64)

    def theta(self, n_steps: int | None = None) -> np.ndarray | None:
        """theta_k of the offline schedule for k = 0..N-1 (None for an online attacker)."""
        N = self.n_steps if n_steps is None else n_steps
        sch = self.attack.schedule(self.T, N * self.T)
        return None if sch is None else sch.theta_samples(self.T, N)
