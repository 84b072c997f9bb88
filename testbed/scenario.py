"""Scenario files: one TOML file describes a run; loaded into frozen dataclasses.

Every bad value gets a ``ScenarioError`` naming the file, the key and what is
wrong.  The full schema is documented in the README ("Scenario files").
"""

from __future__ import annotations

import math
import dataclasses
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

import plants
from attackers import generators as attack_generators

from .control import c2d, closed_loop, dlqr, spectral_radius
from .errors import BadInput
from .flow import FlowOptions
from .quantizer import QuantizerParams

BUNDLED_DIR = "scenarios"


class ScenarioError(BadInput):
    """A scenario file that cannot be used, with the reason."""


# ----------------------------------------------------------------------------- dataclasses
@dataclass(frozen=True)
class PlantSpec:
    name: str
    params: tuple[tuple[str, Any], ...]
    x0: tuple[float, ...]

    def make(self) -> plants.Plant:
        return plants.make(self.name, **dict(self.params))


@dataclass(frozen=True)
class ControllerSpec:
    K: tuple[tuple[float, ...], ...]           # resolved gain, m x n
    source: str                                # "K" or "lqr"
    Q: tuple[tuple[float, ...], ...] | None = None
    R: tuple[tuple[float, ...], ...] | None = None

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

    def schedule(self, T: float, horizon: float):
        """The offline schedule (None for the online greedy attacker)."""
        if self.online:
            return None
        d = {k: _thaw(v) for k, v in self.params}
        seed = d.pop("seed", None)
        return attack_generators.make_schedule(self.kind, d, T=T, horizon=horizon, seed=seed)


@dataclass(frozen=True)
class RunSpec:
    duration: float
    converge_tol: float = 1e-4
    timing: str = "ideal"          # live plant: "ideal" | "physical"
    deadline: float = 0.5          # live plant, ideal timing: fraction of T to wait for u_k


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
        return self.plant.make()

    def theta(self, n_steps: int | None = None) -> np.ndarray | None:
        """theta_k of the offline schedule for k = 0..N-1 (None for an online attacker)."""
        N = self.n_steps if n_steps is None else n_steps
        sch = self.attack.schedule(self.T, N * self.T)
        return None if sch is None else sch.theta_samples(self.T, N)


# ----------------------------------------------------------------------------- validation
_SECTIONS = {"plant", "quantizer", "controller", "attack", "run", "flow", "name", "description"}
_KEYS = {
    "plant": {"name", "params", "x0"},
    "quantizer": {"T", "M", "L", "E0", "mode", "zoom_out", "E_min", "allow_M_le_Lambda",
                  "allow_x0_outside"},
    "controller": {"K", "lqr"},
    "run": {"duration", "converge_tol", "timing", "deadline"},
    "flow": {"rtol", "atol", "x_max", "max_steps"},
}


class _Ctx:
    def __init__(self, where: str):
        self.where = where

    def err(self, key: str, msg: str) -> ScenarioError:
        return ScenarioError(f"{self.where}: [{key}] {msg}")


def _num(ctx, key, v, *, positive=False, nonneg=False, integer=False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ctx.err(key, f"must be a number, got {v!r}")
    if not math.isfinite(v):
        raise ctx.err(key, f"must be finite, got {v!r}")
    if integer and (not float(v).is_integer()):
        raise ctx.err(key, f"must be an integer, got {v!r}")
    if positive and not v > 0:
        raise ctx.err(key, f"must be > 0, got {v!r}")
    if nonneg and not v >= 0:
        raise ctx.err(key, f"must be >= 0, got {v!r}")
    return int(v) if integer else float(v)


def _matrix(ctx, key, v, shape) -> tuple[tuple[float, ...], ...]:
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


def _unknown(ctx, section, table, allowed):
    bad = sorted(set(table) - allowed)
    if bad:
        raise ctx.err(section, f"unknown key(s) {bad}; allowed: {sorted(allowed)}")


def _freeze(v):
    if isinstance(v, list):
        return tuple(_freeze(x) for x in v)
    if isinstance(v, dict):
        return tuple(sorted((k, _freeze(x)) for k, x in v.items()))
    return v


def _thaw(v):
    if isinstance(v, tuple):
        return [_thaw(x) for x in v]
    return v


def from_dict(data: dict, *, name: str = "scenario", where: str = "<scenario>", source: str = "") -> Scenario:
    """Validate a parsed TOML document and build a Scenario."""
    ctx = _Ctx(where)
    if not isinstance(data, dict):
        raise ctx.err("", "scenario must be a TOML table")
    _unknown(ctx, "top level", data, _SECTIONS)
    for sec in ("plant", "quantizer", "controller", "run"):
        if sec not in data:
            raise ctx.err(sec, "section missing")
        if not isinstance(data[sec], dict):
            raise ctx.err(sec, "must be a table")
    name = data.get("name", name)
    if not isinstance(name, str) or not name:
        raise ctx.err("name", f"must be a non-empty string, got {name!r}")
    description = data.get("description", "")
    if not isinstance(description, str):
        raise ctx.err("description", f"must be a string, got {description!r}")

    # [plant]
    pt = data["plant"]
    _unknown(ctx, "plant", pt, _KEYS["plant"])
    if "name" not in pt:
        raise ctx.err("plant.name", f"missing; registered plants: {', '.join(plants.names())}")
    params = pt.get("params", {})
    if not isinstance(params, dict):
        raise ctx.err("plant.params", "must be a table")
    try:
        plant = plants.make(str(pt["name"]), **params)
    except ValueError as e:
        raise ctx.err("plant", str(e)) from None
    n, m = plant.n, plant.m
    if "x0" not in pt:
        raise ctx.err("plant.x0", "missing")
    x0 = _matrix(ctx, "plant.x0", [pt["x0"]], (1, n))[0]

    # [quantizer]
    qt = data["quantizer"]
    _unknown(ctx, "quantizer", qt, _KEYS["quantizer"])
    for k in ("T", "M", "L", "E0"):
        if k not in qt:
            raise ctx.err(f"quantizer.{k}", "missing")
    T = _num(ctx, "quantizer.T", qt["T"], positive=True)
    M = _num(ctx, "quantizer.M", qt["M"], integer=True)
    if M < 2:
        raise ctx.err("quantizer.M", f"must be an integer >= 2, got {M}")
    L = _num(ctx, "quantizer.L", qt["L"], positive=True)
    E0 = _num(ctx, "quantizer.E0", qt["E0"], positive=True)
    mode = qt.get("mode", "resilient")
    if mode not in ("ideal", "resilient"):
        raise ctx.err("quantizer.mode", f"must be 'ideal' or 'resilient', got {mode!r}")
    zoom_out = qt.get("zoom_out")
    if zoom_out is not None:
        zoom_out = _num(ctx, "quantizer.zoom_out", zoom_out)
        if zoom_out < 1:
            raise ctx.err("quantizer.zoom_out", f"must be >= 1, got {zoom_out}")
    E_min = _num(ctx, "quantizer.E_min", qt.get("E_min", 0.0), nonneg=True)
    Lam = math.exp(L * T)
    if M <= Lam and not qt.get("allow_M_le_Lambda", False):
        raise ctx.err("quantizer.M", f"M = {M} <= Lambda = e^(L T) = {Lam:.4g} breaks Assumption 2 "
                      "(set allow_M_le_Lambda = true to run it anyway)")
    if max(abs(v) for v in x0) > E0 and not qt.get("allow_x0_outside", False):
        raise ctx.err("quantizer.E0", f"||x0||_inf = {max(abs(v) for v in x0):g} > E0 = {E0:g} breaks "
                      "Assumption 5 (set allow_x0_outside = true to run it anyway)")
    qp = QuantizerParams(T=T, M=M, L=L, E0=E0, mode=mode, zoom_out=zoom_out, E_min=E_min)

    # [controller]
    ct = data["controller"]
    _unknown(ctx, "controller", ct, _KEYS["controller"])
    if ("K" in ct) == ("lqr" in ct):
        raise ctx.err("controller", "give exactly one of K = [[...]] or lqr = { Q = ..., R = ... }")
    if "K" in ct:
        K = _matrix(ctx, "controller.K", ct["K"], (m, n))
        ctrl = ControllerSpec(K=K, source="K")
    else:
        lq = ct["lqr"]
        if not isinstance(lq, dict):
            raise ctx.err("controller.lqr", "must be a table { Q = [[...]], R = [[...]] }")
        _unknown(ctx, "controller.lqr", lq, {"Q", "R"})
        Q = _matrix(ctx, "controller.lqr.Q", lq.get("Q", np.eye(n).tolist()), (n, n))
        R = _matrix(ctx, "controller.lqr.R", lq.get("R", np.eye(m).tolist()), (m, m))
        Ad, Bd = c2d(plant.A, plant.B, T)
        try:
            Kd = dlqr(Ad, Bd, np.array(Q), np.array(R))
        except (np.linalg.LinAlgError, ValueError) as e:
            raise ctx.err("controller.lqr", f"discrete LQR failed: {e}") from None
        ctrl = ControllerSpec(K=tuple(tuple(float(v) for v in r) for r in Kd), source="lqr", Q=Q, R=R)
    Ad, Bd = c2d(plant.A, plant.B, T)
    rad = spectral_radius(closed_loop(Ad, Bd, ctrl.K_array))
    if not rad < 1:
        raise ctx.err("controller.K", f"A~ + B~ K is not Schur stable (spectral radius {rad:.4g})")

    # [attack]
    at = data.get("attack", {"kind": "none"})
    if not isinstance(at, dict):
        raise ctx.err("attack", "must be a table")
    kind = at.get("kind")
    if kind is None:
        raise ctx.err("attack.kind", f"missing; one of {sorted(attack_generators.GENERATORS)}")
    aparams = {k: v for k, v in at.items() if k not in ("kind", "budget")}
    budget = None
    if "budget" in at:
        bt = at["budget"]
        if not isinstance(bt, dict):
            raise ctx.err("attack.budget", "must be a table { kappa_F, rho_F, kappa_D, rho_D }")
        _unknown(ctx, "attack.budget", bt, {"kappa_F", "rho_F", "kappa_D", "rho_D"})
        budget = tuple(_num(ctx, f"attack.budget.{k}", bt.get(k, 0.0), nonneg=True)
                       for k in ("kappa_F", "rho_F", "kappa_D", "rho_D"))
    if kind in ("random", "greedy"):
        vals = {}
        for k in ("kappa_F", "rho_F", "kappa_D", "rho_D"):
            if k not in aparams:
                raise ctx.err(f"attack.{k}", f"missing (needed by kind = {kind!r})")
            vals[k] = _num(ctx, f"attack.{k}", aparams[k], nonneg=True)
        budget = budget or tuple(vals[k] for k in ("kappa_F", "rho_F", "kappa_D", "rho_D"))
    if budget is not None and not budget[3] < 1:
        raise ctx.err("attack.rho_D", f"must be < 1 (Assumption 4), got {budget[3]}")
    if kind == "greedy":
        _unknown(ctx, "attack", aparams, {"kappa_F", "rho_F", "kappa_D", "rho_D", "threshold", "score"})
        thr = _num(ctx, "attack.threshold", aparams.get("threshold", 0.0), nonneg=True)
        if thr > 1:
            raise ctx.err("attack.threshold", f"must be in [0, 1], got {thr}")
        if aparams.get("score", "state") not in ("state", "E"):
            raise ctx.err("attack.score", f"must be 'state' or 'E', got {aparams.get('score')!r}")
    attack = AttackSpec(kind=str(kind), params=_freeze(aparams), budget=budget)

    # [run]
    rt = data["run"]
    _unknown(ctx, "run", rt, _KEYS["run"])
    if "duration" not in rt:
        raise ctx.err("run.duration", "missing")
    duration = _num(ctx, "run.duration", rt["duration"], positive=True)
    if duration < T:
        raise ctx.err("run.duration", f"shorter than one sampling period T = {T}")
    tol = _num(ctx, "run.converge_tol", rt.get("converge_tol", 1e-4), positive=True)
    timing = rt.get("timing", "ideal")
    if timing not in ("ideal", "physical"):
        raise ctx.err("run.timing", f"must be 'ideal' or 'physical', got {timing!r}")
    deadline = _num(ctx, "run.deadline", rt.get("deadline", 0.5), positive=True)
    if deadline >= 1:
        raise ctx.err("run.deadline", f"is a fraction of T and must be < 1, got {deadline}")
    run = RunSpec(duration=duration, converge_tol=tol, timing=timing, deadline=deadline)

    # [flow]
    ft = data.get("flow", {})
    _unknown(ctx, "flow", ft, _KEYS["flow"])
    flow = FlowOptions(**{k: (_num(ctx, f"flow.{k}", v, positive=True, integer=(k == "max_steps")))
                          for k, v in ft.items()})

    sc = Scenario(name=name, plant=PlantSpec(plant.name, _freeze(params), x0), quantizer=qp,
                  controller=ctrl, attack=attack, run=run, flow=flow, source=source, path=where,
                  description=description)
    # the attack generator validates its own parameters
    try:
        sc.attack.schedule(T, max(duration, T))
    except (ValueError, TypeError, KeyError) as e:
        raise ctx.err("attack", str(e)) from None
    return sc


def bundled_names() -> list[str]:
    d = resources.files("testbed").joinpath(BUNDLED_DIR)
    return sorted(p.name[:-5] for p in d.iterdir() if p.name.endswith(".toml"))


def load(ref: str | Path) -> Scenario:
    """Load a scenario from a file path or a bundled name (``paper``, ``paper-escape``, ...)."""
    p = Path(ref)
    if p.suffix == ".toml" or p.exists():
        if not p.is_file():
            raise ScenarioError(f"{ref}: no such scenario file (bundled: {', '.join(bundled_names())})")
        text = p.read_text()
        name, where = p.stem, str(p)
    else:
        res = resources.files("testbed").joinpath(BUNDLED_DIR, f"{ref}.toml")
        if not res.is_file():
            raise ScenarioError(f"{ref!r} is neither a scenario file nor a bundled scenario "
                                f"(bundled: {', '.join(bundled_names())})")
        text = res.read_text()
        name, where = str(ref), f"bundled:{ref}"
    return loads(text, name=name, where=where)


def loads(text: str, *, name: str = "scenario", where: str = "<string>") -> Scenario:
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ScenarioError(f"{where}: not valid TOML: {e}") from None
    return from_dict(data, name=name, where=where, source=text)


#: run-time overrides a scenario accepts (``testbed run|simulate --duration ...``): name -> (table, key)
OVERRIDES = {"duration": ("run", "duration"), "timing": ("run", "timing"), "deadline": ("run", "deadline"),
             "mode": ("quantizer", "mode"), "T": ("quantizer", "T"), "x0": ("plant", "x0"),
             "E0": ("quantizer", "E0"), "M": ("quantizer", "M"), "attack": ("attack", None)}


def with_overrides(sc: Scenario, overrides: dict | None) -> Scenario:
    """``sc`` with run-time overrides applied and validated as if written in its file.

    ``sc.source`` stays the original text; recordings store the overrides beside it.
    """
    over = {k: v for k, v in (overrides or {}).items() if v is not None}
    if not over:
        return sc
    unknown = set(over) - set(OVERRIDES)
    if unknown:
        raise ScenarioError(f"unknown override(s): {', '.join(sorted(unknown))}")
    data = tomllib.loads(sc.source)
    for k, v in over.items():
        table, key = OVERRIDES[k]
        if key is None:  # attack: a table merged into [attack] (a new kind replaces it)
            if not isinstance(v, dict):
                raise ScenarioError(f"override {k} must be a table of [{table}] keys, got {v!r}")
            old = data.get(table, {})
            data[table] = {**({} if "kind" in v and v["kind"] != old.get("kind") else old), **v}
            continue
        data.setdefault(table, {})[key] = float(v) if isinstance(v, int) and not isinstance(v, bool) else v
    sc2 = from_dict(data, name=sc.name, where=f"{sc.path} (with run overrides)", source=sc.source)
    return dataclasses.replace(sc2, path=sc.path)
