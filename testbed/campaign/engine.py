"""The run engine: many single runs (scenario x method x attack seed), one row each, and their summary.

``testbed versus`` is a small campaign on it; campaigns (``testbed campaign``) reuse it.  A
*point* is a scenario with its method and attack seed fixed; :func:`run_point` simulates it
with the per-sample simulator (the live nodes' protocol objects, every method) and returns a row
with the keys of ``testbed simulate --json`` that a comparison needs.  :func:`summarize_rows`
gives, per method, the success rate (success = converged) with a 95 % Wilson score interval and
the paired comparison to a reference method over the same seeds (``testbed.common.comparestats``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from .. import scenario as scenario_mod
from ..common import comparestats
from ..common.errors import BadInput

if TYPE_CHECKING:
    import numpy.typing as npt

    from ..scenario import Scenario
    from ..sim.loop import SimResult

#: the keys of one row (``testbed versus --json``)
ROW_KEYS = ("method", "seed", "converged", "escaped", "final_norm", "max_norm", "saturations", "samples_lost",
            "bits", "settle_samples")


@dataclass(frozen=True)
class Point:
    """One run: ``sc`` with ``method`` swapped in (None: its own) and the attack seed ``seed`` (None: its own)."""

    sc: Scenario
    method: str | None = None
    seed: int | None = None

    def scenario(self) -> Scenario:
        """The point's scenario: the method swapped in by the one rule (``scenario.swap_method``: the
        scenario's own method keeps its params) and the attack seed (None: the scenario's own, also a
        seed drawn for it by ``scenario.with_seed``, which a swap re-reading the file would lose)."""
        over: dict[str, Any] = {}
        if self.method is not None:
            over["method"] = self.method
        seed = self.seed if self.seed is not None else attack_seed(self.sc)
        if seed is not None and (self.seed is not None or over):
            over["seed"] = int(seed)
        return scenario_mod.with_overrides(self.sc, over) if over else self.sc


def attack_seed(sc: Scenario) -> int | None:
    """The seed of a scenario's random attack (None: the attack draws nothing)."""
    if sc.attack.kind != "random":
        return None
    s = sc.attack.params_dict.get("seed")
    return None if s is None else int(s)


def settle_samples(x: np.ndarray, x_final: npt.ArrayLike, tol: float) -> int | None:
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


def simulate_one(sc: Scenario) -> tuple[dict, SimResult]:
    """One scenario on the per-sample simulator, as ``testbed simulate`` runs it: (its ``testbed simulate
    --json`` document, the ``SimResult``)."""
    from ..sim.batch import simulate_scenario, summarize

    res = simulate_scenario(sc)
    return summarize(sc, res), res


def outcome(s: dict) -> dict:
    """The ``OUTCOME_KEYS`` of a ``testbed simulate --json`` document."""
    return {k: s[k] for k in OUTCOME_KEYS}


def run_point(point: Point, *, keep: bool = False) -> dict | tuple[dict, Scenario, SimResult]:
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


def run_points(points: Sequence[Point], *, keep: bool = False,
               progress: Callable[[int, int], object] | None = None) -> list:
    """Every point in order (one process); ``progress(i, n)`` after each."""
    out = []
    for i, p in enumerate(points):
        out.append(run_point(p, keep=keep))
        if progress:
            progress(i + 1, len(points))
    return out


def wilson(successes: int, n: int) -> tuple[float, float] | None:
    """The 95 % Wilson score interval of a binomial proportion (scipy's); None for n = 0."""
    return comparestats.wilson(successes, n)


def paired_difference(a: list[bool | None], b: list[bool | None]) -> dict:
    """Success of ``a`` minus success of ``b`` over the same seeds (paired): ``difference``, its 95 %
    Newcombe hybrid score interval ``ci95``, the exact McNemar ``mcnemar_p``, the discordant pairs
    (``a_only``, ``b_only``), ``both``, ``neither`` and ``n`` (``testbed.common.comparestats.paired_binary``)."""
    return comparestats.paired_binary(a, b)


#: the paired continuous outcomes of a comparison (Wilcoxon signed-rank, bootstrap of the median difference)
CONTINUOUS = ("settle_samples", "max_norm", "saturations")


def outcome_counts(rows: list[dict]) -> dict:
    """How runs ended, by the rows' own verdicts: ``converged``, ``bounded`` (neither converged nor escaped:
    still converging at the end of the horizon, or held in a ball) and ``escaped``."""
    esc = sum(1 for r in rows if r.get("escaped"))
    conv = sum(1 for r in rows if r.get("converged") and not r.get("escaped"))
    return {"converged": conv, "bounded": len(rows) - conv - esc, "escaped": esc}


def compare_paired(pairs: list[tuple[dict, dict]], seed: int = 0) -> dict:
    """Rows paired (A, B) on the same seeds and initial states: ``paired_difference`` (converged),
    ``paired_escaped`` (escaped), and ``paired_continuous`` (``CONTINUOUS``: each A - B)."""
    a = [p[0] for p in pairs]
    b = [p[1] for p in pairs]
    return {"paired_difference": paired_difference([r.get("converged") for r in a], [r.get("converged") for r in b]),
            "paired_escaped": paired_difference([r.get("escaped") for r in a], [r.get("escaped") for r in b]),
            "paired_continuous": {k: comparestats.paired_continuous([r.get(k) for r in a], [r.get(k) for r in b],
                                                                    seed=seed) for k in CONTINUOUS}}


def summarize_rows(rows: list[dict], methods: list[str]) -> dict:
    """Per method: ``n``, ``successes``, ``success_rate``, ``wilson95``, ``converged``/``bounded``/``escaped``
    counts and (except the first) the paired comparison to the first method over the seeds both ran
    (``compare_paired``: ``paired_difference`` with ``vs``, ``paired_escaped``, ``paired_continuous``)."""
    by = {m: {r["seed"]: r for r in rows if r["method"] == m} for m in methods}
    out = {}
    ref = methods[0]
    for m in methods:
        rs = list(by[m].values())
        d = {**comparestats.success_rate(sum(1 for r in rs if r["converged"]), len(rs)), **outcome_counts(rs)}
        if m != ref:
            seeds = [k for k in by[m] if k in by[ref]]
            cmp = compare_paired([(by[m][k], by[ref][k]) for k in seeds])
            d["paired_difference"] = {"vs": ref, **cmp["paired_difference"]}
            d["paired_escaped"] = cmp["paired_escaped"]
            d["paired_continuous"] = cmp["paired_continuous"]
        out[m] = d
    return out


def seeds_for(sc: Scenario, n: int | None, first: int) -> list[int | None]:
    """The attack seeds S..S+N-1 (``--seeds N --seed S``), or [the scenario's own] without ``n``."""
    if n is None:
        return [None]
    if sc.attack.kind != "random":
        raise BadInput(f"--seeds: the attack of scenario {sc.name} ({sc.attack.kind}) draws nothing; "
                       "--seeds applies to a random attack")
    return list(range(int(first), int(first) + int(n)))
