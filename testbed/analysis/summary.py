"""Scenario-level analysis: the budget of a scenario, Theorems 1 and 2, the escaping trajectory.

This is what ``testbed analyze`` prints; the pieces live in ``theorem1``,
``theorem2``, ``roa`` and ``sweep``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from attackers.budget import check as budget_check

from ..sim.batch import EscapeCriterion, in_nominal_roa, plant_and_model, simulate_batch
from .region import analyze_theorem1
from .sweep import classify, run_grouped
from .theorem1 import RULES, Loop
from .theorem2 import RemainderRadius, delta_for_gamma, gamma_for_delta, theorem2, theorem2_auto

if TYPE_CHECKING:
    import numpy.typing as npt

    from ..scenario import Scenario

#: the value of delta the paper reports for its example (Section V)
PAPER_DELTA = 1.94e-7

#: (kappa_F, kappa_D) used for sweeps when the scenario states no budget
DEFAULT_KAPPAS = (1.0, 0.2)


def scenario_budget(sc: Scenario, horizon: float | None = None) -> tuple[tuple[float, float, float, float], str]:
    """(kappa_F, rho_F, kappa_D, rho_D) of a scenario's attacker and where it comes from.

    * an explicit budget (kinds "random", "greedy", or an [attack.budget] table): as given;
    * "periodic": rho_F = 1 / period, rho_D = length / period, and the smallest
      kappa_F, kappa_D for which the schedule satisfies Assumptions 3 and 4 over the
      run (``attackers.budget.check``);
    * other offline schedules ("intervals", "none"): rho_F = rho_D = 0 and the
      smallest kappas over the run (a finite attack is all initial energy).
    """
    if sc.attack.budget is not None:
        kF, rF, kD, rD = (float(v) for v in sc.attack.budget)
        return (kF, rF, kD, rD), "scenario"
    H = sc.run.duration if horizon is None else horizon
    sch = sc.attack.schedule(sc.T, H)
    assert sch is not None  # an online attack (greedy) has a budget: returned above
    if sc.attack.kind == "periodic":
        d = sc.attack.params_dict
        rF, rD = 1.0 / float(d["period"]), float(d["length"]) / float(d["period"])
        src = "periodic schedule: average rates, smallest kappas over the run"
    else:
        rF, rD = 0.0, 0.0
        src = f"{sc.attack.kind} schedule: rho = 0, smallest kappas over the run"
    rep = budget_check(sch, rF, rD, H)
    return (float(rep.kappa_F_min), rF, float(rep.kappa_D_min), rD), src


def sweep_kappas(sc: Scenario) -> tuple[float, float]:
    """(kappa_F, kappa_D) for sweeps: the scenario's explicit budget, else ``DEFAULT_KAPPAS``."""
    if sc.attack.budget is not None:
        return float(sc.attack.budget[0]), float(sc.attack.budget[2])
    return DEFAULT_KAPPAS


def scenario_theta(sc: Scenario, n_steps: int | None = None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(theta table or None, greedy params or None) of the scenario's attacker for the batch simulator."""
    N = sc.n_steps if n_steps is None else n_steps
    if sc.attack.online:
        return None, sc.attack.greedy_params()
    theta = sc.theta(N)
    assert theta is not None  # an offline schedule
    return theta[None, :], None


def find_escape(sc: Scenario, *, s_max: float | None = None, step: float = 0.25,
                roa_horizon: float = 30.0) -> tuple[float, np.ndarray] | None:
    """Smallest s >= 1 (on a grid of ``step``) such that the loop from s x_0, under the
    scenario's own attack, escapes (``sweep.classify``) although s x_0 is in the nominal region.

    E_0 = max(scenario E_0, ||s x_0||_inf) (Assumption 5).  Returns (s, x0) or None.
    The loop runs the true plant (``[plant]``) with the model's predictions; "nominal
    region" is the model's nominal loop; "escaped" is ``testbed.sim.batch.judge_escape``.
    Needs an equation (1) true plant (the batch simulator cannot run an FMU).
    """
    plant, model = sc.make_plant(), sc.make_model()
    x0 = sc.x0
    nx = float(np.max(np.abs(x0)))
    if nx == 0:
        return None
    s_max = s_max or max(2.0, 10.0 / nx if nx < 1 else 3.0)
    S = np.arange(1.0, s_max + 1e-9, step)
    X = S[:, None] * x0[None, :]
    inside = in_nominal_roa(model, sc.K, sc.T, X, horizon=roa_horizon, tol=sc.run.converge_tol, flow=sc.flow)
    theta, gp = scenario_theta(sc)
    kw = {"theta": theta, "sched_idx": np.zeros(len(X), dtype=int)} if theta is not None else {"greedy_params": gp}
    E0s = np.maximum(sc.quantizer.E0, np.max(np.abs(X), axis=1))
    out = run_grouped(plant, sc.K, sc.quantizer, X, E0s, sc.n_steps,
                      score=sc.attack.score if sc.attack.online else "state", flow=sc.flow, model=model, **kw)
    crit = EscapeCriterion.for_loop(model, sc.quantizer, sc.run.converge_tol)
    _, esc = classify(plant, sc.K, sc.quantizer, out, crit, model=model, flow=sc.flow)
    hit = np.flatnonzero(inside & esc)
    if hit.size == 0:
        return None
    k = int(hit[0])
    return float(S[k]), X[k]


def trajectory(sc: Scenario, x0: npt.ArrayLike, *, E0: float | None = None) -> np.ndarray:
    """x_k of the scenario's loop from ``x0`` (batch simulator, recorded), shape (N, n): the true plant
    (``[plant]``, an equation (1) plant) with the model's predictions."""
    import dataclasses

    plant, model = sc.make_plant(), sc.make_model()
    qp = dataclasses.replace(sc.quantizer, E0=float(E0 if E0 is not None else max(sc.quantizer.E0,
                                                                                    np.max(np.abs(x0)))))
    theta, gp = scenario_theta(sc)
    res = simulate_batch(plant, sc.K, qp, np.asarray(x0, dtype=float)[None, :], sc.n_steps, theta=theta,
                         greedy_params=gp, score=sc.attack.score if sc.attack.online else "state", record=True,
                         flow=sc.flow, model=model)
    k = int(res.stop_k[0])
    assert res.x is not None  # record=True
    return np.vstack([res.x[0, :k], res.x_final[0][None, :]])


def _clean(v: Any) -> Any:
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items() if not str(k).startswith("_")}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    if isinstance(v, (np.floating, float)):
        v = float(v)
        return v if math.isfinite(v) else None
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, np.ndarray):
        return _clean(v.tolist())
    return v


def analyze(sc: Scenario, *, budget: Sequence[float] | None = None, gamma: float | str = "auto", share: float = 0.5,
            rules: Iterable[str] = RULES, n_phi0: int | None = None,
            n_phi1: int | None = None, rule: str = "paper") -> dict:
    """Theorems 1 and 2 for a scenario, on its plant model (``[model]``, default ``[plant]``).

    Parameters
    ----------
    sc : a ``testbed.scenario.Scenario``.
    budget : (kappa_F, rho_F, kappa_D, rho_D); default :func:`scenario_budget`.
    gamma : Lemma 2's gamma, or "auto" (maximize the E_0 bound, ``theorem2_auto``).
    share : part of Theorem 1's decay margin given to the nonlinearity and quantization.
    rule : the mu rule of the headline certificate and of Theorem 2 ("paper": (mu0), (mu1);
        "tight": the smallest constants of (mu)).

    When (stability) fails at the budget's rates, Theorem 2 cannot hold there; it is
    then evaluated with the budget's kappas and rho_F = rho_D = 0 (``theorem2_budget``
    says which), so that delta and the E_0 bound of an attack with only initial
    energy are still reported.

    Returns
    -------
    dict (JSON-ready, see README); entries starting with "_" hold Python objects
    (regions, certificate, Theorem 2 result) for plotting and are dropped by :func:`to_json`.
    """
    plant = sc.make_model()
    loop = Loop.from_scenario(sc)
    if budget is None:
        budget, src = scenario_budget(sc)
    else:
        budget, src = tuple(float(v) for v in budget), "given"
    if rule not in rules:
        rules = tuple(rules) + (rule,)
    t1 = analyze_theorem1(loop, budget, rules=rules, n_phi0=n_phi0, n_phi1=n_phi1, rule=rule)
    cert = t1["_certificate"]
    radius = RemainderRadius(plant)
    b2, b2_src = budget, "budget"
    if not t1.get("theorem1_holds", True):
        b2 = (budget[0], 0.0, budget[2], 0.0)
        b2_src = "budget kappas with rho_F = rho_D = 0 ((stability) fails at the budget's rates)"
        cert = t1["_regions"][rule].best_for(0.0, 0.0)
    if gamma == "auto":
        t2 = theorem2_auto(loop, plant, cert, b2, radius=radius, share=share)
    else:
        t2 = theorem2(loop, plant, cert, float(gamma), b2, radius=radius, share=share)
    gammas = np.logspace(-14, 0, 15)
    table = delta_for_gamma(loop, plant, gammas, radius=radius)
    for row in table:
        r2 = theorem2(loop, plant, cert, row["gamma"], b2, radius=radius, share=share)
        row["E0_bound"] = r2.E0_bound if r2.holds else None
    c = t1["certificate"]
    out = {
        "scenario": sc.name, **plant_and_model(sc), "n": plant.n, "m": plant.m, "T": sc.T, "M": sc.quantizer.M,
        "L": sc.quantizer.L, "Lambda": sc.quantizer.Lambda, "K": np.asarray(sc.K).tolist(),
        "rho_Phi0": loop.rho0, "rho_Phi1": loop.rho1,
        "budget": dict(zip(("kappa_F", "rho_F", "kappa_D", "rho_D"), budget)), "budget_source": src,
        "phi0": c["phi0"], "phi1": c["phi1"], "P0": c["P0"], "P1": (np.asarray(c["P1"]) * t2.s).tolist(),
        "eta0": t2.eta0, "eta1": t2.eta1, "mu0": c["mu0"], "mu1": c["mu1"], "nu0": c["nu0"], "nu1": c["nu1"],
        "rho_D_max": t1["rho_D_max"], "rho_F_max": t1["rho_F_max"],
        "theorem1_holds": t1.get("theorem1_holds"), "rule": rule,
        "theorem1_holds_by_rule": {r: t1[r].get("theorem1_holds") for r in rules},
        "theorem2_budget": b2_src,
        "gamma": t2.lemma.gamma, "delta": t2.delta, "omega0": t2.omega0, "omega1": t2.omega1, "omega": t2.omega,
        "E0_bound": t2.E0_bound, "theorem2_holds": t2.holds, "E0": sc.quantizer.E0,
        "E0_within_bound": bool(t2.holds and sc.quantizer.E0 < t2.E0_bound),
        "gamma_for_paper_delta": gamma_for_delta(loop, plant, PAPER_DELTA, radius=radius),
        "theorem1": {k: v for k, v in t1.items() if not k.startswith("_")},
        "theorem2": t2.to_dict(),
        "delta_table": table,
        "_regions": t1["_regions"], "_plain": t1["_plain"], "_certificate": cert, "_theorem2": t2,
        "_loop": loop,
    }
    return out


def to_json(d: dict) -> dict:
    """Drop the Python objects and make every number JSON-safe (non-finite -> null)."""
    return _clean(d)
