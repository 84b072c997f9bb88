"""The sections of a scenario file, each checked and turned into its part of a ``Scenario``.

``testbed.scenario.from_dict`` composes them in the file's order of checks; every bad value raises a
``ScenarioError`` naming the file, the key and what is wrong (docs/scenarios.md)."""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, NamedTuple, cast, overload

import numpy as np

import plants
from attackers import generators as attack_generators

from ..common import validate
from ..common.errors import BadInput
from ..loop import device
from ..loop.channel import ChannelError, NetworkModel, parse_network
from ..loop.control import c2d, closed_loop, dlqr, spectral_radius
from ..loop.params import RULES, Codebook, CodebookTooLarge, FlowOptions, delay_margin_gain
from . import traces
from .methodswap import Swapped
from .spec import (
    AttackSpec,
    ControllerSpec,
    DelaySpec,
    FMUSpec,
    MethodSpec,
    ModelSpec,
    ScenarioError,
    SimDelaySpec,
    _freeze,
)

if TYPE_CHECKING:
    from ..methods.base import Method

# ----------------------------------------------------------------------------- validation
SECTIONS = {"plant", "model", "quantizer", "controller", "attack", "run", "flow", "name", "description", "method",
            "network"}


KEYS = {
    "plant": {"name", "params", "x0", "fmu", "inputs", "states", *device.TABLES},
    "model": {"name", "params"},
    "quantizer": {"T", "M", "L", "E0", "mode", "zoom_out", "E_min", "allow_M_le_Lambda",
                  "allow_x0_outside", "rule", "L_u"},
    "controller": {"K", "lqr", "u_max"},
    "run": {"duration", "converge_tol", "timing", "deadline", "loss_fraction", "actuation", "delay",
            "delay_lost", "sim_delay"},
    "flow": {"rtol", "atol", "x_max", "max_steps"},
}


class Ctx:
    def __init__(self, where: str, read_recording_trace: traces.RecordingTraceReader | None = None) -> None:
        self.where = where
        self.read_recording_trace = read_recording_trace  # how a recording named as a trace is read

    def err(self, key: str, msg: str) -> ScenarioError:
        return ScenarioError(f"{self.where}: [{key}] {msg}")


@overload
def _num(ctx: Ctx, key: str, v: object, *, positive: bool = False, nonneg: bool = False,
         integer: Literal[True]) -> int: ...
@overload
def _num(ctx: Ctx, key: str, v: object, *, positive: bool = False, nonneg: bool = False,
         integer: Literal[False] = False) -> float: ...
def _num(ctx: Ctx, key: str, v: object, *, positive: bool = False, nonneg: bool = False,
         integer: bool = False) -> float:
    """A number (``validate.number``: an ``int`` when ``integer``) or the error naming ``key``."""
    try:
        return validate.number(v, integer=integer, lo=0 if positive or nonneg else None, lo_open=positive)
    except validate.Invalid as e:
        raise ctx.err(key, str(e)) from None


def _matrix(ctx: Ctx, key: str, v: object, shape: tuple[int, int]) -> tuple[tuple[float, ...], ...]:
    try:
        a = np.array(v, dtype=float)
    except (TypeError, ValueError):
        raise ctx.err(key, f"must be a matrix of numbers, got {v!r}") from None
    if a.ndim == 1 and shape[0] == 1:
        a = a[None, :]
    if a.shape != shape:
        raise ctx.err(key, f"must have shape {shape[0]} x {shape[1]}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ctx.err(key, "must be finite")
    return tuple(tuple(float(x) for x in row) for row in a)


def _unknown(ctx: Ctx, section: str, table: dict, allowed: set[str]) -> None:
    bad = sorted(set(table) - allowed)
    if bad:
        raise ctx.err(section, f"unknown key(s) {bad}; allowed: {sorted(allowed)}")


def _str(ctx: Ctx, key: str, v: object, choices: Iterable[str] | None = None) -> str:
    if not isinstance(v, str):
        raise ctx.err(key, f"must be a string, got {v!r}")
    if choices is not None:
        try:
            validate.choice(v, choices)
        except validate.Invalid as e:
            raise ctx.err(key, str(e)) from None
    return v


def _table(ctx: Ctx, key: str, v: object) -> dict:
    if not isinstance(v, dict):
        raise ctx.err(key, "must be a table")
    return v


def _make_plant(ctx: Ctx, key: str, name: object, params: dict, base_dir: str = "") -> plants.Plant:
    """A plant from a reference (registered name, entry point or "module:Class", see ``plants.refs``)."""
    if not isinstance(name, str) or not name:
        raise ctx.err(f"{key}.name", f"must be a non-empty string, got {name!r}")
    try:
        return plants.instantiate(plants.resolve(name, base_dir or None), name, params)
    except ValueError as e:
        raise ctx.err(key, str(e)) from None


def method_section(ctx: Ctx, data: dict, base_dir: str, swapped: Swapped | None = None) -> tuple[MethodSpec, Method]:
    """[method] and the [quantizer] keys it uses: (MethodSpec, method).  A key the method does not use is
    an error naming it (a swapped method, :func:`testbed.scenario.swap_method`, has them left out already).
    ``swapped``: the swap that wrote ``data``'s [method]; the method it built is taken, not built again."""
    from .. import methods

    mt = _table(ctx, "method", data.get("method", {}))
    _unknown(ctx, "method", mt, {"name", "params"})
    name = mt.get("name", methods.DEFAULT)
    if not isinstance(name, str) or not name:
        raise ctx.err("method.name", f"must be a non-empty string, got {name!r}")
    params = _table(ctx, "method.params", mt.get("params", {}))
    if swapped is not None and swapped.data.get("method") == mt:
        obj = swapped.method
    else:
        try:
            obj = methods.make(name, base_dir or None, params)
        except methods.MethodError as e:
            raise ctx.err("method", str(e)) from None
    qt = data.get("quantizer", {})
    used = set(obj.uses) | {"T"}
    unused = [k for k in qt if k not in used] if isinstance(qt, dict) else []
    if unused:
        raise ctx.err(f"quantizer.{unused[0]}", f"is not used by the method {name!r} (it uses "
                      f"{', '.join(['T', *obj.uses])}); remove it")
    return MethodSpec(name, _freeze(params), base_dir).with_built(obj), obj


class PlantPart(NamedTuple):
    """What [plant] gives the other sections: its table and params, the FMU or the plant object, the sizes."""
    table: dict
    params: dict
    fmu: FMUSpec | None
    plant: plants.Plant | None
    n: int
    m: int
    name: str
    x0: tuple[float, ...]


class QuantizerPart(NamedTuple):
    """[method] and [quantizer]: the method, its keys with their defaults filled in, the checked numbers."""
    method: MethodSpec
    uses: set
    table: dict
    T: float
    M: int
    L: float
    E0: float
    mode: str
    zoom_out: float | None
    E_min: float
    Lam: float
    rule: str


class Timing(NamedTuple):
    """[run] actuation, delay, delay_lost, sim_delay, loss_fraction."""
    loss_fraction: float
    actuation: str
    delay: DelaySpec | None
    delay_lost: DelaySpec | None
    sim_delay: SimDelaySpec | None


def top_level(ctx: Ctx, data: object, name: str) -> tuple[str, str]:
    """The document's tables and the top-level ``name`` and ``description``: (name, description)."""
    if not isinstance(data, dict):
        raise ctx.err("", "scenario must be a TOML table")
    _unknown(ctx, "top level", data, SECTIONS)
    for sec in ("plant", "quantizer", "controller", "run"):
        if sec not in data:
            raise ctx.err(sec, "section missing")
        _table(ctx, sec, data[sec])
    name = data.get("name", name)
    if not isinstance(name, str) or not name:
        raise ctx.err("name", f"must be a non-empty string, got {name!r}")
    return name, _str(ctx, "description", data.get("description", ""))


def plant_section(ctx: Ctx, data: dict, base_dir: str, check_fmu: bool) -> PlantPart:
    """[plant]: the true plant (a registered or imported plant, or an FMU) and x0."""
    pt = data["plant"]
    _unknown(ctx, "plant", pt, KEYS["plant"])
    params = _table(ctx, "plant.params", pt.get("params", {}))
    fmu = None
    if "fmu" in pt:
        fmu = _fmu_spec(ctx, pt, params, base_dir, check_fmu)
        if "model" not in data:
            raise ctx.err("plant.fmu", "an FMU plant needs a [model] section: the model (name, params) the "
                          "quantizer predicts with and the controller is designed on")
        plant = None
        n, m = len(fmu.states), len(fmu.inputs)
        plant_name = f"fmu:{Path(fmu.path).name}"
    else:
        if "name" not in pt:
            raise ctx.err("plant.name", f"missing; registered plants: {', '.join(plants.names())} (or "
                          "'module.path:ClassName', or fmu = \"file.fmu\")")
        for k in ("inputs", "states"):
            if k in pt:
                raise ctx.err(f"plant.{k}", "only with fmu = \"file.fmu\"")
        plant = _make_plant(ctx, "plant", pt["name"], params, base_dir)
        n, m = plant.n, plant.m
        plant_name = plant.name or type(plant).__name__
    if "x0" not in pt:
        raise ctx.err("plant.x0", "missing")
    x0 = _matrix(ctx, "plant.x0", [pt["x0"]], (1, n))[0]
    return PlantPart(pt, params, fmu, plant, n, m, plant_name, x0)


def model_section(ctx: Ctx, data: dict, p: PlantPart, base_dir: str) -> tuple[plants.Plant, ModelSpec]:
    """[model]: what the predictions, the design and the analysis use (default: [plant]): (object, spec)."""
    pt, n, m = p.table, p.n, p.m
    if "model" not in data:
        assert p.plant is not None  # an FMU plant needs a [model] (plant_section)
        return p.plant, ModelSpec(pt["name"], _freeze(p.params), base_dir=base_dir).with_built(p.plant)
    mt = _table(ctx, "model", data["model"])
    _unknown(ctx, "model", mt, KEYS["model"])
    if p.fmu is not None and "name" not in mt:
        raise ctx.err("model.name", "missing: an FMU plant has no equations to default to")
    mname = mt.get("name", pt.get("name"))
    if "params" in mt:
        mparams = _table(ctx, "model.params", mt["params"])
    else:
        mparams = p.params if mname == pt.get("name") else {}
    model_obj = _make_plant(ctx, "model", mname, mparams, base_dir)
    assert isinstance(mname, str)  # _make_plant raised otherwise
    if (model_obj.n, model_obj.m) != (n, m):
        raise ctx.err("model", f"{model_obj.name} has n = {model_obj.n}, m = {model_obj.m}; the plant "
                               f"{p.name} has n = {n}, m = {m}")
    return model_obj, ModelSpec(mname, _freeze(mparams), explicit=True, base_dir=base_dir).with_built(model_obj)


def run_section(ctx: Ctx, data: dict) -> tuple[float, float, str, float]:
    """[run] duration, converge_tol, timing, deadline (the timing decides the quantizer's default rule)."""
    rt = data["run"]
    _unknown(ctx, "run", rt, KEYS["run"])
    if "duration" not in rt:
        raise ctx.err("run.duration", "missing")
    duration = _num(ctx, "run.duration", rt["duration"], positive=True)
    tol = _num(ctx, "run.converge_tol", rt.get("converge_tol", 1e-4), positive=True)
    timing = _str(ctx, "run.timing", rt.get("timing", "ideal"), ("ideal", "physical"))
    deadline = _num(ctx, "run.deadline", rt.get("deadline", 0.5), positive=True)
    if deadline >= 1:
        raise ctx.err("run.deadline", f"is a fraction of T and must be < 1, got {deadline}")
    return duration, tol, timing, deadline


def quantizer_section(ctx: Ctx, data: dict, base_dir: str, n: int, x0: Iterable[float], timing: str,
                      swapped: Swapped | None = None) -> QuantizerPart:
    """[method] and [quantizer]: the keys the method uses (defaults for the others), Assumptions 2 and 5."""
    qt = data["quantizer"]
    _unknown(ctx, "quantizer", qt, KEYS["quantizer"])
    mspec, mobj = method_section(ctx, data, base_dir, swapped)
    muses = set(mobj.uses)
    qt = dict(qt)
    for k in ("T", "M", "L", "E0"):
        if k not in qt:
            if k == "T" or k in muses:
                raise ctx.err(f"quantizer.{k}", "missing" + ("" if k == "T" else f" (used by the method {mspec.name!r})"))
            qt[k] = {"M": 2, "L": 1.0, "E0": max(1.0, *(abs(float(v)) for v in x0))}[k]
    T = _num(ctx, "quantizer.T", qt["T"], positive=True)
    M = _num(ctx, "quantizer.M", qt["M"], integer=True)
    if M < 2:
        raise ctx.err("quantizer.M", f"must be an integer >= 2, got {M}")
    L = _num(ctx, "quantizer.L", qt["L"], positive=True)
    E0 = _num(ctx, "quantizer.E0", qt["E0"], positive=True)
    mode = _str(ctx, "quantizer.mode", qt.get("mode", "resilient"), ("ideal", "resilient"))
    try:
        Codebook(n, M, resilient=(mode == "resilient"))
    except CodebookTooLarge as e:
        raise ctx.err("quantizer.M", str(e)) from None
    zoom_out = qt.get("zoom_out")
    if zoom_out is not None:
        zoom_out = _num(ctx, "quantizer.zoom_out", zoom_out)
        if zoom_out < 1:
            raise ctx.err("quantizer.zoom_out", f"must be >= 1, got {zoom_out}")
    E_min = _num(ctx, "quantizer.E_min", qt.get("E_min", 0.0), nonneg=True)
    for k in ("allow_M_le_Lambda", "allow_x0_outside"):
        if not isinstance(qt.get(k, False), bool):
            raise ctx.err(f"quantizer.{k}", f"must be true or false, got {qt[k]!r}")
    Lam = math.exp(L * T)
    if M <= Lam and {"M", "L"} <= muses and not qt.get("allow_M_le_Lambda", False):
        raise ctx.err("quantizer.M", f"M = {M} <= Lambda = e^(L T) = {Lam:.4g} breaks Assumption 2 "
                      "(set allow_M_le_Lambda = true to run it anyway)")
    if max(abs(v) for v in x0) > E0 and "E0" in muses and not qt.get("allow_x0_outside", False):
        raise ctx.err("quantizer.E0", f"||x0||_inf = {max(abs(v) for v in x0):g} > E0 = {E0:g} breaks "
                      "Assumption 5 (set allow_x0_outside = true to run it anyway)")
    rule = _str(ctx, "quantizer.rule", qt.get("rule", "delay-aware" if timing == "physical" else "paper"),
                RULES)
    return QuantizerPart(mspec, muses, qt, T, M, L, E0, mode, zoom_out, E_min, Lam, rule)


def timing_section(ctx: Ctx, data: dict, T: float, deadline: float, timing: str, rule: str) -> Timing:
    """[run] actuation, delay, delay_lost: when u_k acts (physical timing), and the bounds the delay-aware
    rule covers; sim_delay: the latency of u_k in a simulation."""
    rt = data["run"]
    loss_fraction = _num(ctx, "run.loss_fraction", rt.get("loss_fraction", 0.8), positive=True)
    if loss_fraction >= 1:
        raise ctx.err("run.loss_fraction", f"must be < 1 (the loss deadline comes before the plant's), got "
                                           f"{loss_fraction}")
    actuation = _str(ctx, "run.actuation", rt.get("actuation", "scheduled"), ("scheduled", "arrival"))
    dT = deadline * T
    t_loss = loss_fraction * dT

    def bound(key: str, default_lo: float, default_nom: float, default_hi: float) -> DelaySpec:
        if key not in rt:
            return DelaySpec(default_nom, default_lo, default_hi)
        dt_ = _table(ctx, f"run.{key}", rt[key])
        _unknown(ctx, f"run.{key}", dt_, {"nominal", "min", "max"})
        nom = _num(ctx, f"run.{key}.nominal", dt_.get("nominal", default_nom), nonneg=True)
        lo = _num(ctx, f"run.{key}.min", dt_.get("min", nom if actuation == "scheduled" else default_lo),
                  nonneg=True)
        hi = _num(ctx, f"run.{key}.max", dt_.get("max", nom if actuation == "scheduled" else default_hi),
                  nonneg=True)
        if not lo <= nom <= hi:
            raise ctx.err(f"run.{key}", f"needs min <= nominal <= max, got {lo:g}, {nom:g}, {hi:g}")
        if hi > dT * (1 + 1e-12):
            raise ctx.err(f"run.{key}.max", f"{hi:g} s is beyond the plant's deadline d T = {dT:g} s (a u_k "
                                            "that comes later is not used)")
        if actuation == "scheduled" and lo != nom:
            raise ctx.err(f"run.{key}.min", "under scheduled actuation u_k never acts before its instant: "
                                            "min = nominal")
        return DelaySpec(nom, lo, hi, declared=True)

    delay = delay_lost = None
    if timing == "physical" or rule == "delay-aware":
        if actuation == "scheduled":
            delay = bound("delay", 0.4 * dT, 0.4 * dT, 0.4 * dT)
            if "delay_lost" in rt:
                raise ctx.err("run.delay_lost", "under scheduled actuation a lost sample's u_k = 0 acts at the "
                                                "deadline d T: there is nothing to set")
            delay_lost = DelaySpec(dT, dT, dT)
        else:
            delay = bound("delay", 0.0, 0.5 * t_loss, t_loss)
            delay_lost = bound("delay_lost", t_loss, 0.5 * (t_loss + dT), dT)
    elif "delay" in rt or "delay_lost" in rt:
        raise ctx.err("run.delay", "applies to physical timing (timing = 'physical') or the delay-aware rule only")
    return Timing(loss_fraction, actuation, delay, delay_lost, _sim_delay(ctx, rt, T))


def _sim_delay(ctx: Ctx, rt: dict, T: float) -> SimDelaySpec | None:
    """[run] sim_delay: constant, uniform (seeded) or a trace of latencies, each shorter than T."""
    if "sim_delay" not in rt:
        return None
    sd = _table(ctx, "run.sim_delay", rt["sim_delay"])
    kind = _str(ctx, "run.sim_delay.kind", sd.get("kind", "constant"), ("constant", "uniform", "trace"))
    allowed = {"constant": {"kind", "value"}, "uniform": {"kind", "min", "max", "seed"},
               "trace": {"kind", "values"}}[kind]
    _unknown(ctx, "run.sim_delay", sd, allowed)
    if kind == "constant":
        sim_delay = SimDelaySpec("constant", value=_num(ctx, "run.sim_delay.value", sd.get("value", 0.0),
                                                          nonneg=True))
    elif kind == "uniform":
        lo = _num(ctx, "run.sim_delay.min", sd.get("min", 0.0), nonneg=True)
        hi = _num(ctx, "run.sim_delay.max", sd.get("max", 0.0), nonneg=True)
        if lo > hi:
            raise ctx.err("run.sim_delay", f"needs min <= max, got {lo:g}, {hi:g}")
        if "seed" not in sd:
            raise ctx.err("run.sim_delay.seed", "missing (kind = 'uniform' needs a seed, so that a run "
                                                "can be repeated)")
        seed = _num(ctx, "run.sim_delay.seed", sd["seed"], integer=True, nonneg=True)
        sim_delay = SimDelaySpec("uniform", min=lo, max=hi, seed=seed)
    else:
        vals = sd.get("values")
        if not isinstance(vals, list) or not vals:
            raise ctx.err("run.sim_delay.values", "must be a non-empty list of latencies [s]")
        sim_delay = SimDelaySpec("trace", values=tuple(_num(ctx, "run.sim_delay.values", v, nonneg=True)
                                                       for v in vals))
    top = max([sim_delay.value, sim_delay.max, *sim_delay.values])
    if top > T:
        raise ctx.err("run.sim_delay", f"a latency of {top:g} s is longer than the period T = {T:g} s")
    return sim_delay


def delay_rule(ctx: Ctx, q: QuantizerPart, model_obj: plants.Plant, deadline: float, tm: Timing) -> tuple[dict, float]:
    """The delay-aware rule's margins (``[quantizer] L_u``, default the model's input gain): (the
    QuantizerParams' delay fields, L_u)."""
    dpar = dict(delay_hat=0.0, margin_gain=0.0, delay_hat_lost=0.0, margin_gain_lost=0.0)
    L_u = 0.0
    qt, T, Lam, delay, delay_lost = q.table, q.T, q.Lam, tm.delay, tm.delay_lost
    if q.rule == "delay-aware":
        region = float(getattr(model_obj, "lipschitz_region", math.inf))
        L_u = _num(ctx, "quantizer.L_u", qt["L_u"], nonneg=True) if "L_u" in qt else \
            float(model_obj.input_gain(region))
        assert delay is not None and delay_lost is not None  # timing_section sets both for this rule
        ns = lambda v: round(v * 1e9) / 1e9  # noqa: E731 - delays act in whole ns, as the live plant measures them
        dpar = dict(delay_hat=ns(delay.nominal),
                    margin_gain=delay_margin_gain(Lam, L_u, delay.nominal, delay.min, delay.max),
                    delay_hat_lost=int(deadline * round(T * 1e9)) / 1e9 if tm.actuation == "scheduled"
                    else ns(delay_lost.nominal),
                    margin_gain_lost=delay_margin_gain(Lam, L_u, delay_lost.nominal, delay_lost.min, delay_lost.max))
    elif "L_u" in qt:
        raise ctx.err("quantizer.L_u", "is used by the delay-aware rule only (rule = 'delay-aware')")
    return dpar, L_u


def controller_section(ctx: Ctx, data: dict, model_obj: plants.Plant, n: int, m: int, T: float,
                       check_design: bool) -> ControllerSpec:
    """[controller]: K given or designed by LQR on the model, checked Schur stable."""
    ct = data["controller"]
    _unknown(ctx, "controller", ct, KEYS["controller"])
    if ("K" in ct) == ("lqr" in ct):
        raise ctx.err("controller", "give exactly one of K = [[...]] or lqr = { Q = ..., R = ... }")
    u_max = _num(ctx, "controller.u_max", ct.get("u_max", 1e6), positive=True)
    if "K" in ct:
        K = _matrix(ctx, "controller.K", ct["K"], (m, n))
        ctrl = ControllerSpec(K=K, source="K", u_max=u_max)
        if check_design:
            Ad, Bd = c2d(model_obj.A, model_obj.B, T)
    else:
        Ad, Bd = c2d(model_obj.A, model_obj.B, T)
        lq = _table(ctx, "controller.lqr", ct["lqr"])
        _unknown(ctx, "controller.lqr", lq, {"Q", "R"})
        Q = _matrix(ctx, "controller.lqr.Q", lq.get("Q", np.eye(n).tolist()), (n, n))
        R = _matrix(ctx, "controller.lqr.R", lq.get("R", np.eye(m).tolist()), (m, m))
        try:
            Kd = dlqr(Ad, Bd, np.array(Q), np.array(R))
        except (np.linalg.LinAlgError, ValueError) as e:
            raise ctx.err("controller.lqr", f"discrete LQR failed: {e}") from None
        ctrl = ControllerSpec(K=tuple(tuple(float(v) for v in r) for r in Kd), source="lqr", Q=Q, R=R, u_max=u_max)
    if check_design or ctrl.source != "K":
        rad = spectral_radius(closed_loop(Ad, Bd, ctrl.K_array))
        if not rad < 1:
            raise ctx.err("controller.K", f"A~ + B~ K is not Schur stable (spectral radius {rad:.4g})")
    return ctrl


def attack_section(ctx: Ctx, data: dict, base_dir: str) -> AttackSpec:
    """[attack]: the kind, its parameters (a trace read now) and the budget (Assumption 4)."""
    at = _table(ctx, "attack", data.get("attack", {"kind": "none"}))
    kind = at.get("kind")
    if kind is None:
        raise ctx.err("attack.kind", f"missing; one of {sorted(attack_generators.GENERATORS)}")
    kind = _str(ctx, "attack.kind", kind, sorted(attack_generators.GENERATORS))
    aparams = {k: v for k, v in at.items() if k not in ("kind", "budget")}
    req, opt = attack_generators.PARAMS[kind]   # a misspelled key is named as one, whatever its value
    _unknown(ctx, "attack", aparams, {*req, *opt, *(("score",) if kind == "greedy" else ())})
    budget: tuple[float, float, float, float] | None = None
    if "budget" in at:
        bt = _table(ctx, "attack.budget", at["budget"])
        _unknown(ctx, "attack.budget", bt, {"kappa_F", "rho_F", "kappa_D", "rho_D"})
        budget = cast(tuple[float, float, float, float],  # the four keys
                      tuple(_num(ctx, f"attack.budget.{k}", bt.get(k, 0.0), nonneg=True)
                            for k in ("kappa_F", "rho_F", "kappa_D", "rho_D")))
    if kind in ("random", "greedy"):
        vals: dict[str, float] = {}
        for k in ("kappa_F", "rho_F", "kappa_D", "rho_D"):
            if k not in aparams:
                raise ctx.err(f"attack.{k}", f"missing (needed by kind = {kind!r})")
            vals[k] = _num(ctx, f"attack.{k}", aparams[k], nonneg=True)
        budget = budget or cast(tuple[float, float, float, float],  # the four keys
                                tuple(vals[k] for k in ("kappa_F", "rho_F", "kappa_D", "rho_D")))
    if budget is not None and not budget[3] < 1:
        raise ctx.err("attack.rho_D", f"must be < 1 (Assumption 4), got {budget[3]}")
    if kind == "greedy":
        thr = _num(ctx, "attack.threshold", aparams.get("threshold", 0.0), nonneg=True)
        if thr > 1:
            raise ctx.err("attack.threshold", f"must be in [0, 1], got {thr}")
        _str(ctx, "attack.score", aparams.get("score", "state"), ("state", "E"))
    if kind == "trace":
        aparams = _trace_params(ctx, aparams, base_dir)
    _check_attack_params(ctx, kind, aparams)
    return AttackSpec(kind=str(kind), params=_freeze(aparams), budget=budget)


def flow_section(ctx: Ctx, data: dict) -> FlowOptions:
    """[flow]: the integrator's tolerances and limits."""
    ft = _table(ctx, "flow", data.get("flow", {}))
    _unknown(ctx, "flow", ft, KEYS["flow"])
    opts: dict[str, Any] = {k: (_num(ctx, f"flow.{k}", v, positive=True, integer=(k == "max_steps")))
                            for k, v in ft.items()}
    return FlowOptions(**opts)


def network_section(data: dict, where: str) -> NetworkModel | None:
    """[network]: the emulated channels (testbed/loop/channel.py), or None."""
    try:
        return parse_network(data["network"]) if "network" in data else None
    except ChannelError as e:
        raise ScenarioError(f"{where}: {e}") from None


def _fmu_spec(ctx: Ctx, pt: dict, params: dict, base_dir: str, check: bool = True) -> FMUSpec:
    """``[plant] fmu``, ``inputs``, ``states``, ``params``, checked against the FMU's model description."""
    if "name" in pt:
        raise ctx.err("plant", "give either name = \"...\" or fmu = \"file.fmu\", not both")
    f = pt["fmu"]
    if not isinstance(f, str) or not f:
        raise ctx.err("plant.fmu", f"must be a path to an .fmu file, got {f!r}")
    path = Path(f).expanduser()
    if not path.is_absolute():
        path = Path(base_dir or ".") / path
    lists: dict[str, tuple[str, ...]] = {}
    for k in ("inputs", "states"):
        v = pt.get(k)
        if not isinstance(v, list) or not v or not all(isinstance(x, str) and x for x in v):
            raise ctx.err(f"plant.{k}", f"must be a non-empty list of the FMU's variable names, got {v!r}")
        if len(set(v)) != len(v):
            raise ctx.err(f"plant.{k}", f"names a variable twice: {v}")
        lists[k] = tuple(v)
    if check:
        from plants.fmu import FMUError, describe

        try:
            describe(str(path.resolve()), inputs=lists["inputs"], states=lists["states"], params=params)
        except FMUError as e:
            raise ctx.err("plant.fmu", str(e)) from None
    return FMUSpec(path=str(path.resolve()), inputs=lists["inputs"], states=lists["states"],
                   params=_freeze(params), checked=check)


def _trace_params(ctx: Ctx, aparams: dict, base_dir: str) -> dict:
    """``[attack] kind = "trace"``: ``source = PATH`` (a recording or a file, relative to the scenario's
    folder) read now, or the embedded form ``samples``, ``T``, ``n_samples`` (what a recording stores)."""
    if "samples" in aparams:
        return dict(aparams)
    src = aparams.get("source")
    if not isinstance(src, str) or not src:
        raise ctx.err("attack.source", "missing: a recording (.mcap) or a file of dropped sample indices")
    path = Path(src) if Path(src).is_absolute() else Path(base_dir or ".") / src
    try:
        return traces.read_trace(path, ctx.read_recording_trace)
    except (OSError, ValueError, BadInput) as e:
        raise ctx.err("attack.source", f"{src}: {e}") from None


def _check_attack_params(ctx: Ctx, kind: str, aparams: dict) -> None:
    """Types of the attack's parameters: numbers are numbers (a string "1.0" is an error)."""
    for k, v in aparams.items():
        if k == "score":
            continue
        if k == "intervals":
            if not isinstance(v, list) or not all(isinstance(iv, list) and len(iv) == 2 for iv in v):
                raise ctx.err("attack.intervals", "must be a list of [start, length] pairs in seconds")
            for iv in v:
                for x in iv:
                    _num(ctx, "attack.intervals", x)
            continue
        if k == "seed":
            _num(ctx, "attack.seed", v, integer=True)
            continue
        if k == "source":
            continue
        if k == "samples":
            if not isinstance(v, list) or not all(isinstance(i, int) and not isinstance(i, bool) for i in v):
                raise ctx.err("attack.samples", "must be a list of sample indices")
            continue
        _num(ctx, f"attack.{k}", v)
