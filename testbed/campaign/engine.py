"""The run engine: many single runs (scenario x method x attack seed), one row each, and their summary.

``testbed versus`` is a small campaign on it; campaigns (``testbed campaign``) reuse it.  A
*point* is a scenario with its method and attack seed fixed; :func:`run_point` simulates it
with the per-sample simulator (the live nodes' protocol objects, every method) and returns a row
with the keys of ``testbed simulate --json`` that a comparison needs.  :func:`summarize_rows`
gives, per method, the success rate (success = converged) with a 95 % Wilson score interval and
the paired difference to a reference method over the same seeds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .. import scenario as scenario_mod
from ..errors import BadInput

#: the keys of one row (``testbed versus --json``)
ROW_KEYS = ("method", "seed", "converged", "escaped", "final_norm", "max_norm", "saturations", "samples_lost",
            "bits", "settle_samples")


@dataclass(frozen=True)
class Point:
    """One run: ``sc`` with ``method`` swapped in (None: its own) and the attack seed ``seed`` (None: its own)."""

    sc: object
    method: str | None = None
    seed: int | None = None

    def scenario(self):
        """The point's scenario: the method swapped in by the one rule (``scenario.swap_method``: the
        scenario's own method keeps its params) and the attack seed (None: the scenario's own, also a
        seed drawn for it by ``scenario.with_seed``, which a swap re-reading the file would lose)."""
        over = {}
        if self.method is not None:
            over["method"] = self.method
        seed = self.seed if self.seed is not None else attack_seed(self.sc)
        if self.seed is not None or (seed is not None and over):
            over["seed"] = int(seed)
        return scenario_mod.with_overrides(self.sc, over) if over else self.sc


def attack_seed(sc) -> int | None:
    """The seed of a scenario's random attack (None: the attack draws nothing)."""
    if sc.attack.kind != "random":
        return None
    s = sc.attack.params_dict.get("seed")
    return None if s is None else int(s)


def settle_samples(x, x_final, tol: float) -> int | None:
    """The first sample k from which ||x_j||_inf < tol for every j >= k (x_N included); None if never."""
    norms = np.concatenate([np.max(np.abs(np.atleast_2d(x)), axis=1) if len(x) else np.zeros(0),
                            [float(np.max(np.abs(x_final)))]])
    below = norms < tol
    if not below[-1]:
        return None
    bad = np.flatnonzero(~below)
    return int(bad[-1] + 1) if bad.size else 0


#: the outcome of a run under the key names of ``testbed simulate --json`` (a campaign's row holds them)
OUTCOME_KEYS = ("method", "bits", "converged", "escaped", "diverged", "final_norm", "max_norm", "x_final",
                "saturations", "samples_lost", "packets_dropped", "losses", "encoder_decoder_agree", "plant_fault",
                "method_fault")


def simulate_one(sc):
    """One scenario on the per-sample simulator, as ``testbed simulate`` runs it: (its ``testbed simulate
    --json`` document, the ``SimResult``)."""
    from ..sim.batch import simulate_scenario, summarize

    res = simulate_scenario(sc)
    return summarize(sc, res), res


def outcome(s: dict) -> dict:
    """The ``OUTCOME_KEYS`` of a ``testbed simulate --json`` document."""
    return {k: s[k] for k in OUTCOME_KEYS}


def run_point(point: Point, *, keep=False):
    """Simulate one point; its row (``ROW_KEYS``, and ``lockstep_breaks``, ``method_fault``). ``keep``:
    also return the scenario and the ``SimResult``."""
    sc = point.scenario()
    s, res = simulate_one(sc)
    row = {"method": sc.method.name, "seed": attack_seed(sc), "converged": s["converged"], "escaped": s["escaped"],
           "final_norm": s["final_norm"], "max_norm": s["max_norm"], "saturations": s["saturations"],
           "samples_lost": s["samples_lost"], "bits": s["bits"],
           "settle_samples": settle_samples(res.x, res.x_final, sc.run.converge_tol),
           "withheld": len(s["withheld_at"]), "lockstep_breaks": len(res.lockstep_breaks),
           "method_fault": res.method_fault}
    return (row, sc, res) if keep else row


def run_points(points, *, keep=False, progress=None) -> list:
    """Every point in order (one process); ``progress(i, n)`` after each."""
    out = []
    for i, p in enumerate(points):
        out.append(run_point(p, keep=keep))
        if progress:
            progress(i + 1, len(points))
    return out


def wilson(successes: int, n: int, z: float = 1.959963984540054) -> tuple[float, float] | None:
    """The Wilson score interval of a binomial proportion (95 % for the default z); None for n = 0."""
    if n == 0:
        return None
    p = successes / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return max(0.0, centre - half), min(1.0, centre + half)


def paired_difference(a: list[bool], b: list[bool], z: float = 1.959963984540054) -> dict:
    """Success of ``a`` minus success of ``b`` over the same seeds (paired): the mean difference, a 95 %
    normal interval of the mean of the paired differences, and the discordant pairs (a only, b only)."""
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    n = d.size
    mean = float(d.mean()) if n else None
    half = float(z * d.std(ddof=1) / math.sqrt(n)) if n > 1 else None
    return {"difference": mean, "ci95": None if half is None else [mean - half, mean + half],
            "a_only": int(np.sum(d > 0)), "b_only": int(np.sum(d < 0)), "n": int(n)}


def summarize_rows(rows: list[dict], methods: list[str]) -> dict:
    """Per method: ``n``, ``successes``, ``success_rate``, ``wilson95`` and (except the first)
    ``paired_difference`` to the first method (rows paired by seed)."""
    by = {m: {r["seed"]: bool(r["converged"]) for r in rows if r["method"] == m} for m in methods}
    out = {}
    ref = methods[0]
    for m in methods:
        ok = list(by[m].values())
        n, s = len(ok), int(sum(ok))
        w = wilson(s, n)
        d = {"n": n, "successes": s, "success_rate": s / n if n else None, "wilson95": None if w is None else list(w)}
        if m != ref:
            seeds = [k for k in by[m] if k in by[ref]]
            pd = paired_difference([by[m][k] for k in seeds], [by[ref][k] for k in seeds])
            d["paired_difference"] = {"vs": ref, **pd}
        out[m] = d
    return out


def seeds_for(sc, n: int | None, first: int) -> list[int | None]:
    """The attack seeds S..S+N-1 (``--seeds N --seed S``), or [the scenario's own] without ``n``."""
    if n is None:
        return [None]
    if sc.attack.kind != "random":
        raise BadInput(f"--seeds: the attack of scenario {sc.name} ({sc.attack.kind}) draws nothing; "
                       "--seeds applies to a random attack")
    return list(range(int(first), int(first) + int(n)))
