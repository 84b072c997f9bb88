"""Empirical DoS tolerance: where the quantized loop converges under budget-limited attacks.

For every budget point (rho_F, rho_D) of a grid, with fixed (kappa_F, kappa_D)
(Assumptions 3 and 4), the batch simulator runs the full loop (quantizer,
decoder, plant) from one or more initial states under three attackers:

* ``random``: ``attackers`` generator "random" (several seeds), within the budget by construction;
* ``periodic``: period 1 / rho_F and length rho_D / rho_F, i.e. exactly the average
  rates, with the first attack delayed just enough for the constants
  (kappa_F, kappa_D) (:func:`periodic_within_budget`); not defined for rho_F = 0;
* ``greedy``: the online worst-case attacker of ``attackers.greedy`` (hits
  transmissions as soon as and for as long as the budget allows, or, with a
  threshold, when ||x_k|| is near its running maximum).

Attacks persist over the whole horizon (Theorem 1 is about persistent attacks).
A run ``escaped`` when the quantized loop, continued without attack from where it
ended, does not recover (``testbed.sim.batch.EscapeCriterion``, ``judge_escape``: the
same verdict as ``testbed simulate``'s): the attacker has pushed the loop where even
unattacked operation no longer brings it back.  It ``converged`` when
||x_N||_inf < tol and it did not escape; the remaining runs are ``bounded``.

Impulsive attacks (length 0) only drop a packet when they fall on a sampling
instant; the random and periodic generators place attacks in continuous time,
so at rho_D = 0 they are nearly harmless, while the greedy attacker always hits
samples.  Theorem 1's rho_D* = rho_D + rho_F T covers the worst case.

``vulnerable_states`` maps, for one budget, the initial states inside the nominal
region of attraction from which the greedy attacker makes the loop fail.

A state beyond ``x_max`` (default 1e3, far outside the region of attraction of
every bundled plant) ends its run as diverged, hence escaped: without this cap the
integrator spends most of a sweep on states the attack has already blown up
(the -b x1^5 term of the Lienard plant is stiff there); the classification is
unchanged (checked on the README sweep) and a sweep runs about 5 times faster.

Each initial state x_0 runs with E_0 = max(quantizer E_0, ||x_0||_inf) rounded up
to a power of 1.25 (Assumption 5 with little slack; the simulator takes one E_0
per call, so states are grouped by that value).

With model mismatch (a scenario's ``[model]``), ``plant`` is the true plant the
state follows and ``model`` the plant model of the encoder's and decoder's
predictions (rule (xi)); the escape test continues that loop (true plant, model's
predictions), as ``testbed.sim.batch.summarize`` does.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from attackers.generators import make_schedule

from ..loop.flow import DEFAULT_FLOW, FLOW_OK, FlowOptions
from ..sim.batch import ESCAPE_HORIZON, EscapeCriterion, judge_escape
from .parallel import Stages, n_chunks, run_batch
from .roa import RoaResult

if TYPE_CHECKING:
    import numpy.typing as npt

    from plants.base import Plant

    from ..loop.params import QuantizerParams
    from .parallel import Executor, Progress

KINDS = ("random", "periodic", "greedy")


# ============================================================================ schedules
def periodic_within_budget(rho_F: float, rho_D: float, kappa_F: float, kappa_D: float) -> dict | None:
    """Parameters of the "periodic" generator with average rates (rho_F, rho_D) within (kappa_F, kappa_D).

    period P = 1 / rho_F, length l = rho_D P.  The j-th attack [o + j P, o + j P + l]
    satisfies Assumption 3 at its start iff j + 1 <= kappa_F + rho_F (o + j P), i.e.
    o >= P (1 - kappa_F), and Assumption 4 at its end iff
    (j + 1) l <= kappa_D + rho_D (o + j P + l), i.e. o >= P (1 - rho_D) - kappa_D / rho_D.
    The offset o is the smallest one (plus a rounding margin).  None if rho_F = 0.
    """
    if rho_F <= 0.0:
        return None
    P = 1.0 / rho_F
    length = rho_D * P
    o = max(0.0, P * (1.0 - kappa_F))
    if rho_D > 0.0:
        o = max(o, P * (1.0 - rho_D) - kappa_D / rho_D)
    if o > 0.0:
        o = o * (1.0 + 1e-9) + 1e-12
    return {"period": P, "length": length, "offset": o}


def e0_levels(X0: npt.ArrayLike, E0: float, ratio: float = 1.25, floor: float = 1e-6) -> np.ndarray:
    """E_0 per initial state: max(E0, ||x0||_inf) rounded up to a power of ``ratio`` (>= floor)."""
    r = np.maximum(np.max(np.abs(np.atleast_2d(X0)), axis=1), floor)
    up = ratio ** np.ceil(np.log(r) / math.log(ratio) - 1e-12)
    return np.where(r <= E0, E0, up)


def run_grouped(plant: Plant, K: npt.ArrayLike, qp: QuantizerParams, X0: npt.ArrayLike, E0s: npt.ArrayLike,
                n_steps: int, *, theta: npt.ArrayLike | None = None, sched_idx: npt.ArrayLike | None = None,
                greedy_params: npt.ArrayLike | None = None, score: str = "state", flow: FlowOptions = DEFAULT_FLOW,
                executor: Executor | None = None, progress: Progress | None = None,
                model: Plant | None = None) -> dict:
    """The batch simulator with one E_0 per trajectory; arrays in input order (``parallel.run_batch``).

    ``plant`` is the true plant, ``model`` the predictions' model (default ``plant``)."""
    return run_batch(plant, K, qp, X0, n_steps, E0=E0s, theta=theta, sched_idx=sched_idx,
                     greedy_params=greedy_params, score=score, flow=flow,
                     fields=("x_final", "status", "attacked", "saturations", "max_norm", "stop_k", "state_final"),
                     executor=executor, progress=progress, model=model)


def classify(plant: Plant, K: npt.ArrayLike, qp: QuantizerParams, out: dict, criterion: EscapeCriterion, *,
             model: Plant | None = None, flow: FlowOptions = DEFAULT_FLOW, executor: Executor | None = None,
             progress: Progress | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(converged, escaped) per run of a batch ``out`` (``run_batch`` fields x_final, status,
    state_final): escaped by ``testbed.sim.batch.judge_escape`` (the quantized loop continued
    without attack, ``criterion``), its continuation on ``executor``; converged: ||x_N|| < x_tol
    and not escaped.

    ``plant`` is the true plant, ``model`` (default ``plant``) the predictions' model."""
    called = []

    def run(X: np.ndarray, S: np.ndarray, n_steps: int, stop: tuple[float, float, float]) -> dict:
        called.append(1)
        return run_batch(plant, K, qp, X, n_steps, init_state=S, stop=stop, model=model, flow=flow,
                         fields=("x_final", "status", "state_final"), executor=executor, progress=progress)

    esc = judge_escape(plant, K, qp, out["x_final"], out["state_final"], out["status"], criterion, model=model,
                       flow=flow, run=run)
    if not called and progress is not None:
        progress(1, 1)
    conv = (out["status"] == FLOW_OK) & (np.max(np.abs(out["x_final"]), axis=1) < criterion.x_tol) & ~esc
    return conv, esc


# ============================================================================ the sweep
@dataclass
class SweepResult:
    """Fractions of runs per budget point and attacker kind ((n_F, n_D) arrays; nan: not applicable)."""

    rho_F: np.ndarray
    rho_D: np.ndarray
    kappa_F: float
    kappa_D: float
    T: float
    horizon: float
    tol: float
    seeds: int
    threshold: float
    X0: np.ndarray
    kinds: tuple
    converged: dict = field(default_factory=dict)
    escaped: dict = field(default_factory=dict)
    lost: dict = field(default_factory=dict)     # mean fraction of simulated samples with theta_k = 1
    runs: int = 0
    traj_steps: int = 0
    wall: float = 0.0
    escape_criterion: dict = field(default_factory=dict)

    @property
    def rate(self) -> float:
        return self.traj_steps / self.wall if self.wall > 0 else math.nan

    def worst(self) -> np.ndarray:
        """Smallest converged fraction over the kinds at each budget point."""
        return np.nanmin(np.stack([self.converged[k] for k in self.kinds]), axis=0)

    def all_converged(self, kind: str | None = None) -> np.ndarray:
        """Budget points where every run (of ``kind``, or of all kinds) converged."""
        c = self.worst() if kind is None else self.converged[kind]
        return np.nan_to_num(c, nan=1.0) >= 1.0

    def empirical_boundary(self, kind: str | None = None) -> np.ndarray:
        """For each rho_D, the largest rho_F such that all runs converged for every rho_F' <= rho_F (nan if none)."""
        ok = self.all_converged(kind)
        out = np.full(len(self.rho_D), np.nan)
        for j in range(len(self.rho_D)):
            col = ok[:, j]
            if not col[0]:
                continue
            bad = np.flatnonzero(~col)
            out[j] = self.rho_F[bad[0] - 1] if bad.size else self.rho_F[-1]
        return out

    def to_dict(self) -> dict:
        def clean(a: npt.ArrayLike) -> list:
            return [[None if not np.isfinite(v) else float(v) for v in row] for row in np.asarray(a)]
        return {"rho_F": self.rho_F.tolist(), "rho_D": self.rho_D.tolist(), "kappa_F": self.kappa_F,
                "kappa_D": self.kappa_D, "T": self.T, "horizon": self.horizon, "tol": self.tol, "seeds": self.seeds,
                "threshold": self.threshold, "X0": self.X0.tolist(), "kinds": list(self.kinds),
                "converged": {k: clean(v) for k, v in self.converged.items()},
                "escaped": {k: clean(v) for k, v in self.escaped.items()},
                "lost": {k: clean(v) for k, v in self.lost.items()},
                "worst_converged": clean(self.worst()),
                "empirical_boundary": [None if not np.isfinite(v) else float(v) for v in self.empirical_boundary()],
                "runs": self.runs, "traj_steps": self.traj_steps, "wall_s": self.wall,
                "traj_steps_per_s": self.rate, "escape_criterion": self.escape_criterion}


def _capped(flow: FlowOptions, x_max: float | None) -> FlowOptions:
    return flow if x_max is None else replace(flow, x_max=min(flow.x_max, float(x_max)))


def sweep(plant: Plant, K: npt.ArrayLike, qp: QuantizerParams, X0: npt.ArrayLike, rho_F: npt.ArrayLike,
          rho_D: npt.ArrayLike, *, kappa_F: float = 1.0, kappa_D: float = 0.5, seeds: int = 4,
          horizon: float = 60.0, kinds: Sequence[str] = KINDS, threshold: float = 0.0, score: str = "state",
          tol: float = 1e-4, escape_horizon: float = ESCAPE_HORIZON, seed: int = 0, flow: FlowOptions = DEFAULT_FLOW,
          x_max: float | None = 1e3, progress: Progress | None = None, executor: Executor | None = None,
          model: Plant | None = None) -> SweepResult:
    """Run the loop over a grid of budgets (rho_F x rho_D) and attacker kinds.

    Parameters
    ----------
    plant, K, qp : the loop (QuantizerParams; E_0 per initial state as in the module docstring);
        ``plant`` is the true plant.
    model : the predictions' model (default ``plant``).
    X0 : (B0, n) initial states (or (n,)).
    rho_F, rho_D : 1-D grids (rho_D < 1).
    kappa_F, kappa_D : the fixed constants of Assumptions 3 and 4.
    seeds : random schedules per budget point (seeds seed, seed + 1, ... per point).
    horizon : seconds of attacked operation; tol : convergence radius.
    kinds : subset of ``KINDS``; threshold, score : the greedy attacker's parameters.
    x_max : escape cap on ||x||_inf (module docstring); None keeps ``flow.x_max``.
    progress : callback progress(done_chunks, total_chunks).
    executor : a ``parallel.Executor`` (None: this process); the result does not depend on it.

    All runs of the grid form two batches (offline schedules, greedy attacker) and the
    escape checks a third, each split into chunks on the executor.
    """
    flow = _capped(flow, x_max)
    model = plant if model is None else model
    X0 = np.atleast_2d(np.asarray(X0, dtype=float))
    rho_F = np.asarray(rho_F, dtype=float)
    rho_D = np.asarray(rho_D, dtype=float)
    if np.any(rho_D >= 1) or np.any(rho_D < 0) or np.any(rho_F < 0):
        raise ValueError("need 0 <= rho_D < 1 and rho_F >= 0")
    bad = set(kinds) - set(KINDS)
    if bad:
        raise ValueError(f"unknown kinds {sorted(bad)}; known: {KINDS}")
    T = qp.T
    N = int(round(horizon / T))
    crit = EscapeCriterion.for_loop(model, qp, tol, escape_horizon)
    nF, nD, B0 = len(rho_F), len(rho_D), X0.shape[0]
    E0x = e0_levels(X0, qp.E0)
    res = SweepResult(rho_F, rho_D, float(kappa_F), float(kappa_D), T, float(horizon), float(tol), int(seeds),
                      float(threshold), X0, tuple(kinds), escape_criterion=crit.to_dict())
    for k in kinds:
        res.converged[k] = np.full((nF, nD), np.nan)
        res.escaped[k] = np.full((nF, nD), np.nan)
        res.lost[k] = np.full((nF, nD), np.nan)
    t0 = time.perf_counter()
    # ---- offline schedules of the whole grid: (kind, i, j) per table row (generated in parallel too:
    #      drawing thousands of random schedules is Python work of the same order as simulating them)
    groups = [list(range(a, min(a + 2, nF))) for a in range(0, nF, 2)]
    spec = (tuple(kinds), rho_F, rho_D, float(kappa_F), float(kappa_D), int(seeds), int(seed), T, float(horizon), N)
    items = [(spec, g) for g in groups]
    drawn = executor.map(_schedule_rows, items) if executor is not None else [_schedule_rows(it) for it in items]
    rows = [r for p in drawn for r in p[0]]
    tags = [t for p in drawn for t in p[1]]
    n_off = len(rows) * B0
    n_gr = nF * nD * B0 if "greedy" in kinds else 0
    stages = Stages(progress, [n_chunks(n_off, N, executor), n_chunks(n_gr, N, executor),
                               n_chunks(n_off + n_gr, int(round(escape_horizon / T)), executor)])
    parts, run_tags = [], []
    if rows:
        tab = np.array(rows, dtype=np.uint8)
        sidx = np.repeat(np.arange(len(rows)), B0)
        parts.append(run_grouped(plant, K, qp, np.tile(X0, (len(rows), 1)), np.tile(E0x, len(rows)), N,
                                 theta=tab, sched_idx=sidx, flow=flow, executor=executor,
                                 progress=stages.next(), model=model))
        run_tags += [tags[r] for r in sidx]
    else:
        stages.next()
    if "greedy" in kinds:
        gp = np.array([[kappa_F, rF, kappa_D, rD, threshold] for rF in rho_F for rD in rho_D for _ in range(B0)])
        parts.append(run_grouped(plant, K, qp, np.tile(X0, (nF * nD, 1)), np.tile(E0x, nF * nD), N,
                                 greedy_params=gp, score=score, flow=flow, executor=executor,
                                 progress=stages.next(), model=model))
        run_tags += [("greedy", i, j) for i in range(nF) for j in range(nD) for _ in range(B0)]
    else:
        stages.next()
    if parts:
        out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        conv, esc = classify(plant, K, qp, out, crit, model=model, flow=flow, executor=executor,
                             progress=stages.next())
        lost = out["attacked"] / np.maximum(out["stop_k"], 1)
        _accumulate(res, run_tags, conv, esc, lost)
        res.runs = len(run_tags)
        res.traj_steps = len(run_tags) * N
    res.wall = time.perf_counter() - t0
    return res


def _schedule_rows(item: tuple) -> tuple[list, list]:
    """theta rows and (kind, i, j) tags of the offline schedules of the budget rows ``rows_i``."""
    (kinds, rho_F, rho_D, kappa_F, kappa_D, seeds, seed, T, horizon, N), rows_i = item
    nD = len(rho_D)
    rows, tags = [], []
    for i in rows_i:
        rF = rho_F[i]
        for j, rD in enumerate(rho_D):
            if "random" in kinds:
                for s in range(seeds):
                    sch = make_schedule("random", {"kappa_F": kappa_F, "rho_F": rF, "kappa_D": kappa_D,
                                                   "rho_D": rD}, T=T, horizon=horizon,
                                        seed=seed + s + seeds * (j + nD * i))
                    rows.append(sch.theta_samples(T, N))
                    tags.append(("random", i, j))
            if "periodic" in kinds:
                pp = periodic_within_budget(rF, rD, kappa_F, kappa_D)
                if pp is not None:
                    sch = make_schedule("periodic", pp, T=T, horizon=horizon)
                    rows.append(sch.theta_samples(T, N))
                    tags.append(("periodic", i, j))
    return rows, tags


def _accumulate(res: SweepResult, tags: Sequence[tuple], conv: np.ndarray, esc: np.ndarray, lost: np.ndarray) -> None:
    groups: dict = {}
    for r, t in enumerate(tags):
        groups.setdefault(t, []).append(r)
    for (kind, i, j), idx in groups.items():
        res.converged[kind][i, j] = float(np.mean(conv[idx]))
        res.escaped[kind][i, j] = float(np.mean(esc[idx]))
        res.lost[kind][i, j] = float(np.mean(lost[idx]))


# ============================================================================ vulnerable positions
@dataclass
class VulnerableResult:
    """Outcome per grid state under one budget: -1 outside the nominal region, 0 converged,
    1 not converged but inside the region (bounded), 2 escaped."""

    xs: np.ndarray
    ys: np.ndarray
    dims: tuple
    outcome: np.ndarray      # (ny, nx) int8
    budget: tuple
    kind: str
    threshold: float
    horizon: float
    wall: float = 0.0
    traj_steps: int = 0
    escape_criterion: dict = field(default_factory=dict)

    @property
    def fraction_vulnerable(self) -> float:
        """Failed (bounded or escaped) fraction of the nominal region's grid states."""
        inside = self.outcome >= 0
        return float(np.mean(self.outcome[inside] >= 1)) if inside.any() else math.nan

    def to_dict(self) -> dict:
        inside = self.outcome >= 0
        return {"budget": dict(zip(("kappa_F", "rho_F", "kappa_D", "rho_D"), self.budget)), "kind": self.kind,
                "threshold": self.threshold, "horizon": self.horizon, "grid": [len(self.xs), len(self.ys)],
                "states_in_region": int(inside.sum()), "converged": int(np.sum(self.outcome == 0)),
                "bounded": int(np.sum(self.outcome == 1)), "escaped": int(np.sum(self.outcome == 2)),
                "fraction_vulnerable": self.fraction_vulnerable, "wall_s": self.wall,
                "traj_steps": self.traj_steps, "escape_criterion": self.escape_criterion}


def vulnerable_states(plant: Plant, K: npt.ArrayLike, qp: QuantizerParams, budget: Sequence[float],
                      roa: RoaResult, *, stride: int = 1, kind: str = "greedy",
                      horizon: float = 30.0, threshold: float = 0.0, score: str = "state", tol: float = 1e-4,
                      seed: int = 0, escape_horizon: float = ESCAPE_HORIZON, flow: FlowOptions = DEFAULT_FLOW,
                      x_max: float | None = 1e3, kappa_D_shares: Sequence[float] = (0.0, 0.5, 1.0),
                      progress: Progress | None = None, executor: Executor | None = None,
                      model: Plant | None = None) -> VulnerableResult:
    """Which states of the nominal region fail under a budget-limited attacker.

    Parameters
    ----------
    plant, K, qp : the loop; ``plant`` is the true plant, ``model`` (default ``plant``) the
        predictions' model.
    budget : (kappa_F, rho_F, kappa_D, rho_D).
    roa : a :class:`RoaResult` (its grid, subsampled by ``stride``, gives the states).
    kind : "greedy" (online), "random" (one schedule, ``seed``) or "periodic".
    kappa_D_shares : for "greedy", the attacker may spend only part of its initial
        duration budget (a greedy attacker with kappa_D' = share * kappa_D also
        satisfies Assumption 4 with kappa_D); a state is vulnerable when ANY of
        these strategies defeats the loop from it.  The outcome is sensitive to
        the exact attack (quantization makes it irregular), so this family is a
        stronger, still budget-limited, adversary than one greedy policy.
    x_max : escape cap on ||x||_inf (see the module docstring).
    executor : a ``parallel.Executor`` (None: this process); the result does not depend on it.

    Returns
    -------
    VulnerableResult: per state -1 outside the region, else 0 when every strategy
    converged, 2 when some strategy made it escape, 1 otherwise (some did not converge).
    """
    flow = _capped(flow, x_max)
    model = plant if model is None else model
    kF, rF, kD, rD = budget
    crit = EscapeCriterion.for_loop(model, qp, tol, escape_horizon)
    xs, ys = roa.xs[::stride], roa.ys[::stride]
    inside = roa.inside[::stride, ::stride]
    GX, GY = np.meshgrid(xs, ys, indexing="xy")
    X = np.tile(roa.center, (inside.sum(), 1))
    X[:, roa.dims[0]] = GX[inside]
    X[:, roa.dims[1]] = GY[inside]
    N = int(round(horizon / qp.T))
    E0s = e0_levels(X, 0.0, floor=1e-3 * max(abs(xs).max(), abs(ys).max()))
    t0 = time.perf_counter()
    if kind == "greedy":
        kd_shares = tuple(kappa_D_shares) or (1.0,)
        shares: tuple[float | None, ...] = kd_shares
        gp = np.array([[kF, rF, sh * kD, rD, threshold] for sh in kd_shares for _ in range(len(X))])
        stages = Stages(progress, [n_chunks(len(gp), N, executor), n_chunks(len(gp), N, executor)])
        out = run_grouped(plant, K, qp, np.tile(X, (len(shares), 1)), np.tile(E0s, len(shares)), N,
                          greedy_params=gp, score=score, flow=flow, executor=executor, progress=stages.next(),
                          model=model)
        c, e = classify(plant, K, qp, out, crit, model=model, flow=flow, executor=executor,
                        progress=stages.next())
        conv = np.all(c.reshape(len(shares), len(X)), axis=0)
        esc = np.any(e.reshape(len(shares), len(X)), axis=0)
    else:
        if kind == "random":
            sch = make_schedule("random", {"kappa_F": kF, "rho_F": rF, "kappa_D": kD, "rho_D": rD}, T=qp.T,
                                horizon=horizon, seed=seed)
        elif kind == "periodic":
            pp = periodic_within_budget(rF, rD, kF, kD)
            sch = make_schedule("periodic" if pp else "none", pp or {}, T=qp.T, horizon=horizon)
        else:
            raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
        tab = sch.theta_samples(qp.T, N)[None, :]
        stages = Stages(progress, [n_chunks(len(X), N, executor), n_chunks(len(X), N, executor)])
        out = run_grouped(plant, K, qp, X, E0s, N, theta=tab, sched_idx=np.zeros(len(X), dtype=int), flow=flow,
                          executor=executor, progress=stages.next(), model=model)
        conv, esc = classify(plant, K, qp, out, crit, model=model, flow=flow, executor=executor,
                             progress=stages.next())
        shares = (None,)
    wall = time.perf_counter() - t0
    outcome = np.full(inside.shape, -1, dtype=np.int8)
    outcome[inside] = np.where(conv, 0, np.where(esc, 2, 1))
    return VulnerableResult(xs, ys, roa.dims, outcome, tuple(budget), kind, threshold, horizon, wall,
                            len(X) * N * len(shares), crit.to_dict())
