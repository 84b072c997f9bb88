"""The strongest attacker: the fewest lost samples, and the least DoS duration, that drive the loop out.

The paper ends on an open question: "there are vulnerable positions in the
state space from which it is easy for the attacker to make the state leave the
region of attraction".  This module answers it on the batch simulator, under the
paper's model of the attacker (Section II.C, Assumptions 3 and 4).

**What an attack costs.**  Sample k (at t_k = k T) is lost iff t_k lies in an
attack interval [a_i, a_i + tau_i]; only the set of lost samples (theta_k) acts on
the loop.  Assumption 3 counts the attacks, N(t); Assumption 4 sums their
durations, |A(t)|.  A run of L consecutive lost samples k0..k0+L-1 is covered by
one attack [k0 T, (k0 + L - 1) T] of duration (L - 1) T, or by j <= L attacks
*back to back* (the gap between two of them strictly between two sampling
instants) of total duration (L - j) T: one attack [0.3, +0.5] and the two attacks
[0.3, +0.2], [0.6, +0.2] lose the same samples 3..8 with |A| = 0.5 and 0.4.  Runs
separated by a delivered sample need an attack each.  Hence a set of S lost
samples in R runs can be lost with at most N >= R attacks, and then costs at
least (S - min(N, S)) T, which :func:`realize` attains.  The least duration
alone is degenerate (S impulsive attacks cost 0); the real answer is the
trade-off between the number of attacks and the lost samples, for each N:

    S*(N) = the fewest lost samples with which some schedule of at most N
            attacks makes the loop escape,

priced (S*(N) - min(N, S*(N))) T: the *front* N = 1, 2, ... (S*(N) does not
increase with N).  Runs are (k0, L) pairs, separated by at least one delivered
sample; a schedule of exactly m runs with S lost samples is one of
``count_schedules(m, S - m, n_steps)``.

**Escape** is judged by the quantized loop itself (``testbed.sim.batch.EscapeCriterion``,
``judge_escape``): from its state after the horizon (the plant's x_N and both ends'
xi_N, E_N), the loop continued without attack must recover (||x|| and E below their
tolerances) within the criterion's horizon; the same function decides ``escaped``
for ``testbed simulate``, ``run``, ``report``, ``sweep`` and ``vulnerability``.

**Search** (:func:`least_single`, :func:`worst_attack`):

* N = 1, exact: every start k0 and length L, by increasing L (first a bound from the
  attack at k0 = 0 of every length; then all starts for every shorter length).
  The smallest escaping L is S*(1); every shorter single attack was simulated.
* N >= 2, below U = S*(N - 1): first *exhaustively*, every schedule of exactly N
  runs with S = N, N + 1, ... lost samples, as long as the schedules enumerated for
  this N stay within ``exhaustive_limit``; the first S at which one escapes is the
  least for exactly N runs.  If the limit stops the enumeration first, a beam search
  (width ``beam``: the non-escaping schedules of N - 1 runs that drove ||x_k|| highest,
  each extended by one more run) and a local descent (drop one lost sample of the
  best schedule, or move a run by one sample, while one still escapes) look further.
* ``exact`` for N holds only when it is proven: every schedule of at most N attacks
  losing fewer than S*(N) samples was simulated and none escapes (``proof`` says,
  per N, below how many lost samples this was shown, within the N samples).

Every candidate schedule is one row of a theta table; a batch of them is one
``parallel.run_batch`` call, so the search runs on all cores or a Dask cluster."""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from math import comb
from typing import TYPE_CHECKING

import numpy as np

from plants.base import Plant

from ..loop.flow import DEFAULT_FLOW, FlowOptions
from ..loop.params import QuantizerParams
from ..sim.batch import EscapeCriterion
from .parallel import Stages, n_chunks, run_batch
from .sweep import classify

if TYPE_CHECKING:
    import numpy.typing as npt

    from ..scenario import Scenario
    from .parallel import Executor, Progress

#: thresholds and scores tried for the greedy attacker's comparison
GREEDY_THRESHOLDS = (0.0, 0.25, 0.5, 0.75, 0.9)


GREEDY_SCORES = ("state", "E")


#: the batch fields an evaluation needs
_EVAL_FIELDS = ("x_final", "status", "max_norm", "state_final")


# ============================================================================ the loop and its candidates
@dataclass(frozen=True)
class Loop:
    """The closed loop whose attacks are searched: plant, gain, quantizer, N samples, escape test.

    ``plant`` is the true plant the state follows; ``model`` (default ``plant``) the plant
    model of the encoder's and decoder's predictions (a scenario's ``[model]``).  ``criterion``
    decides escape (default ``EscapeCriterion.for_loop(model, qp, tol)``).
    """

    plant: Plant
    K: np.ndarray
    qp: QuantizerParams   # E_0 per initial state is given separately
    n_steps: int
    tol: float = 1e-4
    flow: FlowOptions = DEFAULT_FLOW
    model: Plant | None = None
    criterion: EscapeCriterion | None = None

    @property
    def T(self) -> float:
        return float(self.qp.T)

    @property
    def nominal(self) -> Plant:
        """The plant model of the predictions."""
        return self.plant if self.model is None else self.model

    @property
    def escape(self) -> EscapeCriterion:
        """The escape criterion (``testbed.sim.batch.EscapeCriterion``)."""
        return self.criterion or EscapeCriterion.for_loop(self.nominal, self.qp, self.tol)

    @classmethod
    def from_scenario(cls, sc: Scenario) -> Loop:
        return cls(sc.make_plant(), np.asarray(sc.K, dtype=float), sc.quantizer, sc.n_steps, sc.run.converge_tol,
                   sc.flow, sc.make_model())


def e0_for(loop: Loop, X0: npt.ArrayLike) -> np.ndarray:
    """E_0 per initial state: max(quantizer E_0, ||x_0||_inf) (Assumption 5: x_0 in Q(0, E_0))."""
    X0 = np.atleast_2d(X0)
    return np.maximum(float(loop.qp.E0), np.max(np.abs(X0), axis=1))


def runs_to_intervals(runs: Iterable[tuple[int, int]], T: float) -> list[list[float]]:
    """[(k0, L), ...] -> [[start, length], ...] in seconds (a scenario's ``[attack] intervals``)."""
    return [[round(k0 * T, 12), round((L - 1) * T, 12)] for k0, L in sorted(runs)]


def duration_samples(runs: Iterable[tuple[int, int]]) -> int:
    """Total duration of the runs, each one attack, in sampling periods: sum (L_i - 1)."""
    return int(sum(L - 1 for _k0, L in runs))


def samples_lost(runs: Iterable[tuple[int, int]]) -> int:
    """S: the lost samples of the runs."""
    return int(sum(L for _k0, L in runs))


def least_duration_samples(S: int, attacks: int) -> int:
    """The least total duration, in sampling periods, of at most ``attacks`` attacks that lose a given
    set of S samples (in at most ``attacks`` runs): S - min(attacks, S) (module docstring)."""
    return int(S - min(int(attacks), int(S)))


def realize(runs: Sequence[tuple[int, int]], attacks: int) -> tuple:
    """Attacks (k0, L) that lose exactly the samples of ``runs`` with the least total duration.

    ``len(runs) <= attacks``.  min(attacks, S) attacks in all: runs are split into pieces
    that sit back to back (piece i ends at sample k, piece i + 1 starts at k + 1: the gap
    between their intervals, ((k T, (k + 1) T), holds no sampling instant), longest runs
    first, pieces as equal as possible.  Total duration (S - min(attacks, S)) T.
    """
    runs = sorted(runs)
    if len(runs) > attacks:
        raise ValueError(f"{len(runs)} runs need at least {len(runs)} attacks, got {attacks}")
    extra = min(int(attacks), samples_lost(runs)) - len(runs)
    pieces = {r: 1 for r in runs}
    for r in sorted(runs, key=lambda r: (-r[1], r[0])):
        add = min(extra, r[1] - 1)
        pieces[r] += add
        extra -= add
    out = []
    for k0, L in runs:
        j = pieces[(k0, L)]
        base, rem = divmod(L, j)
        k = k0
        for i in range(j):
            ell = base + (1 if i < rem else 0)
            out.append((k, ell))
            k += ell
    return tuple(out)


def runs_of(theta: npt.ArrayLike) -> tuple:
    """The runs (k0, L) of lost samples of a 0/1 sequence."""
    th = np.asarray(theta, dtype=np.int8)
    d = np.diff(np.concatenate(([0], th, [0])))
    starts = np.flatnonzero(d == 1)
    ends = np.flatnonzero(d == -1)
    return tuple((int(a), int(b - a)) for a, b in zip(starts, ends))


def theta_table(runs_list: Sequence[Iterable[tuple[int, int]]], n_steps: int) -> np.ndarray:
    """(C, N) uint8 table: row c has theta_k = 1 on every run (k0, L) of candidate c."""
    tab = np.zeros((len(runs_list), n_steps), dtype=np.uint8)
    for c, runs in enumerate(runs_list):
        for k0, L in runs:
            tab[c, k0:k0 + L] = 1
    return tab


def single_table(k0: npt.ArrayLike, L: npt.ArrayLike, n_steps: int) -> np.ndarray:
    """theta table of single runs (k0[c], L[c])."""
    ar = np.arange(n_steps)
    k0 = np.asarray(k0)[:, None]
    return ((ar >= k0) & (ar < k0 + np.asarray(L)[:, None])).astype(np.uint8)


def evaluate(loop: Loop, X0: np.ndarray, E0: np.ndarray, tab: np.ndarray, sched_idx: np.ndarray, *,
             executor: Executor | None = None, progress: Progress | None = None,
             stages: Stages | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(escaped, peak ||x_k||_inf) of each candidate row: trajectory b starts at X0[b] with E0[b]
    under row sched_idx[b] of ``tab``; escape by ``loop.escape`` (``sweep.classify``)."""
    st = stages or Stages(progress, [n_chunks(len(sched_idx), loop.n_steps, executor), 1])
    out = run_batch(loop.plant, loop.K, loop.qp, X0, loop.n_steps, E0=E0, theta=tab, sched_idx=sched_idx,
                    flow=loop.flow, fields=_EVAL_FIELDS, executor=executor, progress=st.next(), model=loop.nominal)
    _, esc = classify(loop.plant, loop.K, loop.qp, out, loop.escape, model=loop.nominal, flow=loop.flow,
                      executor=executor, progress=st.next())
    return esc, out["max_norm"]


# ============================================================================ one attack, exact
@dataclass
class SingleResult:
    """Least single attack per initial state: L (samples, 0: the loop escapes unattacked, -1: none
    up to ``max_len``) and its start k0; ``evaluated`` candidates, and the non-escaping ones kept
    for the beam (state, k0, L, peak norm)."""

    L: np.ndarray
    k0: np.ndarray
    evaluated: int = 0
    traj_steps: int = 0
    pool: list = field(default_factory=list)


def least_single(loop: Loop, X0: npt.ArrayLike, *, E0: npt.ArrayLike | None = None, max_len: int | None = None,
                 executor: Executor | None = None, progress: Progress | None = None,
                 keep_pool: bool = False) -> SingleResult:
    """The shortest single sample-aligned attack that makes the loop escape, for each initial state.

    Exhaustive over start and length (see the module docstring); exact.

    Parameters
    ----------
    loop : the closed loop (N = ``loop.n_steps`` samples).
    X0 : (S, n) initial states; E0 : (S,) (default :func:`e0_for`).
    max_len : longest attack tried, in samples (default N).
    keep_pool : keep the non-escaping candidates shorter than the answer (for the beam search).
    """
    X0 = np.atleast_2d(np.asarray(X0, dtype=float))
    S = X0.shape[0]
    N = int(loop.n_steps)
    E0 = e0_for(loop, X0) if E0 is None else np.broadcast_to(np.asarray(E0, dtype=float), (S,))
    Lmax = N if max_len is None else max(1, min(int(max_len), N))
    L = np.full(S, -1, dtype=np.int64)
    k0 = np.full(S, -1, dtype=np.int64)
    res = SingleResult(L, k0)
    stages = Stages(progress, [1, 1, n_chunks(S * Lmax, N, executor), 1]
                    + [n_chunks(S * N * 4, N, executor), 1] * 4)

    def run(states, starts, lengths):
        tab = single_table(starts, lengths, N)
        esc, peak = evaluate(loop, X0[states], E0[states], tab, np.arange(len(states)), executor=executor,
                             stages=stages)
        res.evaluated += len(states)
        res.traj_steps += len(states) * N
        return esc, peak

    try:
        return _least_single(loop, X0, E0, Lmax, res, run, keep_pool)
    finally:
        stages.finish()


def _least_single(loop, X0, E0, Lmax, res, run, keep_pool):
    S = X0.shape[0]
    N = int(loop.n_steps)
    L, k0 = res.L, res.k0
    # 0. no attack at all
    esc, _ = run(np.arange(S), np.zeros(S, dtype=np.int64), np.zeros(S, dtype=np.int64))
    L[esc] = 0
    k0[esc] = 0
    active = np.flatnonzero(~esc)
    if active.size == 0:
        return res
    # A. a bound U per state: the attack from k0 = 0, by increasing length in growing blocks, until
    #    it escapes (few escaping runs are simulated: they are the slow ones, the flow stiffens)
    U = np.full(S, Lmax + 1, dtype=np.int64)   # shortest escaping length at k0 = 0 (Lmax + 1: none)
    pool = []
    lo, block = 1, 8
    todo = active
    while todo.size and lo <= Lmax:
        ells = np.arange(lo, min(lo + block, Lmax + 1))
        st = np.repeat(todo, ells.size)
        ln = np.tile(ells, todo.size)
        esc, peak = run(st, np.zeros_like(st), ln)
        found = []
        for s in todo:
            m = st == s
            hit = np.flatnonzero(esc[m])
            if hit.size:
                U[s] = int(ln[m][hit[0]])
                found.append(s)
            if keep_pool:
                pool += [(int(s), 0, int(ell), float(p)) for ell, p, e in zip(ln[m], peak[m], esc[m])
                         if not e and ell < U[s]]
        todo = np.array([s for s in todo if s not in set(found)], dtype=np.int64)
        lo += block
        block *= 2
    # B. every start for every length below the bound, by increasing length, in blocks
    lo = 1
    block = 4
    while active.size and lo <= Lmax:
        rows = []
        for s in active:
            for ell in range(lo, min(lo + block, U[s], Lmax + 1)):
                ks = np.arange(1, N - ell + 1)  # k0 = 0 was done in A
                rows.append((np.full(ks.size, s), ks, np.full(ks.size, ell)))
        if not rows:
            break
        st = np.concatenate([r[0] for r in rows])
        ks = np.concatenate([r[1] for r in rows])
        ln = np.concatenate([r[2] for r in rows])
        esc, peak = run(st, ks, ln)
        done = []
        for s in active:
            m = st == s
            e = m & esc
            if e.any():
                # shortest escaping length, then the earliest start; the start k0 = 0 ties at U only
                ells = ln[e]
                best = int(ells.min())
                k = int(ks[e][ells == best].min())
                L[s], k0[s] = best, k
                done.append(s)
                if keep_pool:
                    sel = m & ~esc & (ln < best)
                    pool += [(int(s), int(a), int(b), float(p)) for a, b, p in zip(ks[sel], ln[sel], peak[sel])]
            elif keep_pool:
                sel = m & ~esc
                pool += [(int(s), int(a), int(b), float(p)) for a, b, p in zip(ks[sel], ln[sel], peak[sel])]
        lo += block
        block *= 2
        active = np.array([s for s in active if s not in set(done) and lo < U[s]], dtype=np.int64)
    # states whose bound from k0 = 0 stands: no shorter attack anywhere escapes
    for s in range(S):
        if L[s] == -1 and U[s] <= Lmax:
            L[s], k0[s] = U[s], 0
    res.pool = pool
    return res


# ============================================================================ several attacks
def count_schedules(m: int, extra: int, n_steps: int) -> int:
    """Schedules of exactly m runs with total duration ``extra`` samples in N samples.

    Lengths: C(extra + m - 1, m - 1) compositions; placements of m runs covering
    S = m + extra samples with gaps >= 1 between them: C(N - S + 1, m).
    """
    S = m + extra
    if S + (m - 1) > n_steps:
        return 0
    return comb(extra + m - 1, m - 1) * comb(n_steps - S + 1, m)


def _compositions(total: int, m: int):
    if m == 1:
        yield (total,)
        return
    for a in range(total + 1):
        for rest in _compositions(total - a, m - 1):
            yield (a,) + rest


def _placements(lengths, n_steps: int, start: int = 0):
    """Start samples of runs with these lengths, in order, separated by >= 1 sample."""
    if not lengths:
        yield ()
        return
    L0, rest = lengths[0], lengths[1:]
    need = sum(rest) + len(rest)  # the later runs and their gaps
    for k in range(start, n_steps - L0 - need + 1):
        for tail in _placements(rest, n_steps, k + L0 + 1):
            yield (k,) + tail


def all_schedules(m: int, extra: int, n_steps: int) -> Iterator[tuple[tuple[int, int], ...]]:
    """Every schedule of m runs with total duration ``extra`` samples, as tuples of (k0, L)."""
    for ext in _compositions(extra, m):
        lengths = tuple(e + 1 for e in ext)
        for ks in _placements(lengths, n_steps):
            yield tuple(zip(ks, lengths))


def _neighbours(runs, n_steps: int, attacks: int) -> set:
    """Schedules near ``runs`` for the local descent: one lost sample fewer (a run shortened at
    either end, or split by a delivered sample inside it), and each of those with one run moved
    by one sample; at most ``attacks`` runs, inside the horizon."""
    theta = np.zeros(n_steps, dtype=np.int8)
    for k0, L in runs:
        theta[k0:k0 + L] = 1
    out = set()
    for k in np.flatnonzero(theta):
        th = theta.copy()
        th[k] = 0
        r = runs_of(th)
        if 0 < len(r) <= attacks:
            out.add(r)
            for i, (a, L) in enumerate(r):
                for d in (-1, 1):
                    if 0 <= a + d and a + d + L <= n_steps:
                        moved = r[:i] + r[i + 1:]
                        if _valid_add(moved, a + d, L):
                            out.add(tuple(sorted(moved + ((a + d, L),))))
    return out


def _valid_add(runs, k0: int, L: int) -> bool:
    """Run (k0, L) neither overlaps nor touches any run of ``runs``."""
    for a, b in runs:
        if k0 <= a + b and a <= k0 + L:  # [k0, k0+L-1] within one sample of [a, a+b-1]
            return False
    return True


@dataclass
class WorstAttack:
    """Result of :func:`worst_attack` (``to_dict`` is the JSON of ``testbed worst-attack``).

    ``front[n - 1]`` is the answer for at most n attacks (n = 1..``attacks``): S*(n), the
    least duration, the attacks that realize it, whether it is proven; ``proof[n - 1]`` what
    was shown exhaustively for n.
    """

    x0: np.ndarray
    E0: float
    T: float
    n_steps: int
    attacks: int
    front: list            # per n: {"attacks", "samples_lost", "total_duration", "intervals", "exact", "escaped"}
    proof: list            # per n: {"attacks", "samples_lost_below", "horizon_samples", "schedules"}
    search: str
    unattacked_escapes: bool
    criterion: dict
    single: dict | None = None
    greedy: dict | None = None
    evaluated: int = 0
    traj_steps: int = 0
    wall: float = 0.0
    max_len: int = 0
    runs: tuple = ()       # the answer's runs of lost samples (k0, L) for ``attacks``

    @property
    def answer(self) -> dict:
        return self.front[-1]

    @property
    def escaped(self) -> bool:
        return bool(self.answer["escaped"])

    @property
    def exact(self) -> bool:
        return bool(self.answer["exact"])

    @property
    def total_duration(self) -> float:
        return float(self.answer["total_duration"] or 0.0)

    @property
    def intervals(self) -> list:
        return self.answer["intervals"]

    def to_dict(self) -> dict:
        a = self.answer
        return {"x0": self.x0.tolist(), "E0": self.E0, "T": self.T, "n_steps": self.n_steps,
                "horizon": round(self.n_steps * self.T, 12), "attacks": self.attacks,
                "intervals": a["intervals"], "total_duration": a["total_duration"],
                "samples_lost": a["samples_lost"], "escaped": a["escaped"], "exact": a["exact"],
                "search": self.search, "front": self.front, "proof": self.proof,
                "escape_criterion": self.criterion,
                "unattacked_escapes": self.unattacked_escapes, "max_length_samples": self.max_len,
                "single_attack": self.single, "greedy": self.greedy, "candidates": self.evaluated,
                "traj_steps": self.traj_steps, "wall_s": self.wall}


def _entry(n: int, runs, escaped: bool, exact: bool, T: float) -> dict:
    if not escaped:
        return {"attacks": n, "samples_lost": None, "total_duration": None, "intervals": [], "exact": exact,
                "escaped": False}
    S = samples_lost(runs)
    return {"attacks": n, "samples_lost": S, "total_duration": round(least_duration_samples(S, n) * T, 12),
            "intervals": runs_to_intervals(realize(runs, n), T), "exact": exact, "escaped": True}


def worst_attack(loop: Loop, x0: npt.ArrayLike, *, attacks: int = 1, E0: float | None = None,
                 max_len: int | None = None, beam: int = 16, exhaustive_limit: int = 100_000, greedy: bool = True,
                 executor: Executor | None = None, progress: Progress | None = None) -> WorstAttack:
    """The fewest lost samples S*(n), and the least duration, with which at most n = 1..``attacks``
    attacks make the loop from ``x0`` escape (the module docstring: pricing, search, exactness).

    Parameters
    ----------
    loop : the closed loop; x0 : (n,) initial state; E0 : default :func:`e0_for`.
    attacks : the most attack intervals (the front is computed for 1..attacks).
    max_len : most lost samples tried (default N, the whole horizon).
    beam : beam width of the search where the enumeration stops.
    exhaustive_limit : schedules enumerated per number of attacks (n >= 2) before the beam
        search takes over.
    greedy : also search the greedy online attacker's least duration budget (for comparison).
    """
    t0 = time.perf_counter()
    if int(attacks) < 1:
        raise ValueError(f"attacks must be >= 1, got {attacks}")
    A = int(attacks)
    x0 = np.asarray(x0, dtype=float).ravel()
    X0 = x0[None, :]
    e0 = float(e0_for(loop, X0)[0] if E0 is None else E0)
    N = int(loop.n_steps)
    T = loop.T
    Lmax = N if max_len is None else max(1, min(int(max_len), N))
    crit = loop.escape.to_dict()
    sr = least_single(loop, X0, E0=[e0], max_len=Lmax, executor=executor, progress=progress, keep_pool=A >= 2)
    ev, steps = sr.evaluated, sr.traj_steps
    L1, k1 = int(sr.L[0]), int(sr.k0[0])
    gr = _greedy(loop, x0, e0, A, executor) if greedy else None
    if L1 == 0:
        front = [{"attacks": n, "samples_lost": 0, "total_duration": 0.0, "intervals": [], "exact": True,
                  "escaped": True} for n in range(1, A + 1)]
        proof = [{"attacks": n, "samples_lost_below": 0, "horizon_samples": N, "schedules": 0}
                 for n in range(1, A + 1)]
        return WorstAttack(x0, e0, T, N, A, front, proof, "no attack needed: the quantized loop escapes alone",
                           True, crit, None, gr, ev, steps, time.perf_counter() - t0, Lmax, ())

    def run(cands):
        nonlocal ev, steps
        esc, peak = evaluate(loop, np.repeat(X0, len(cands), 0), np.full(len(cands), e0), theta_table(cands, N),
                             np.arange(len(cands)), executor=executor, progress=progress)
        ev += len(cands)
        steps += len(cands) * N
        return esc, peak

    best: tuple[tuple[int, int], ...] | None = ((k1, L1),) if L1 > 0 else None  # the answer for n attacks so far (runs)
    proven = L1 if L1 > 0 else Lmax + 1              # every schedule of <= n attacks below this fails
    enumerated = 0
    single = _entry(1, best, best is not None, L1 > 0 or Lmax == N, T)
    front = [single]
    proof = [{"attacks": 1, "samples_lost_below": proven, "horizon_samples": N, "schedules": sr.evaluated}]
    notes = ["n = 1: every start and length"]
    # beam level: non-escaping schedules of n - 1 runs, highest peak first
    level = [((k, ell),) for _p, k, ell in sorted(((p, k, ell) for _s, k, ell, p in sr.pool), reverse=True)]
    seen = set()
    for n in range(2, A + 1):
        U = samples_lost(best) if best is not None else Lmax + 1   # look strictly below U
        # ---- exhaustive: exactly n runs, S = n, n + 1, ... < U
        s, spent, hit = n, 0, None
        while s < U:
            cnt = count_schedules(n, s - n, N)
            if spent + cnt > exhaustive_limit:
                break
            cands = list(all_schedules(n, s - n, N))
            spent += cnt
            if cands:
                seen.update(cands)
                esc, _ = run(cands)
                if esc.any():
                    hit = cands[int(np.flatnonzero(esc)[0])]
                    break
            s += 1
        enumerated += spent
        if hit is not None:
            best, U = hit, s
        proven_n = s if s < U or hit is not None else U   # exactly n runs: none below this escapes
        note = f"n = {n}: every schedule of {n} runs with fewer than {proven_n} lost samples ({spent})"
        # ---- beyond the enumeration: beam search and local descent
        if hit is None and s < U:
            used = []
            nxt = []
            for prefix in level[:beam]:
                S0 = samples_lost(prefix)
                for ell in range(1, U - S0):
                    if S0 + ell < s:
                        continue
                    for k in range(0, N - ell + 1):
                        if _valid_add(prefix, k, ell):
                            c = tuple(sorted(prefix + ((k, ell),)))
                            if c not in seen:
                                seen.add(c)
                                nxt.append(c)
            if nxt:
                esc, peak = run(nxt)
                used.append(len(nxt))
                Ss = np.array([samples_lost(c) for c in nxt])
                if esc.any():
                    i = min(np.flatnonzero(esc), key=lambda j: (Ss[j], nxt[j]))
                    if Ss[i] < U:
                        best, U = nxt[i], int(Ss[i])
                order = [j for j in np.argsort(-peak, kind="stable") if not esc[j]]
                level = [nxt[j] for j in order[:beam]]
            else:
                level = []
            while best is not None:
                cands = sorted(c for c in _neighbours(best, N, n) if c not in seen)
                if not cands:
                    break
                seen.update(cands)
                esc, _ = run(cands)
                used.append(len(cands))
                hits = [c for c, e in zip(cands, esc) if e and samples_lost(c) < U]
                if not hits:
                    break
                best = min(hits, key=lambda c: (samples_lost(c), c))
                U = samples_lost(best)
            note += f", then beam search (width {beam}) and local descent ({sum(used)})"
        proven = min(proven, proven_n)
        found = best is not None
        exact = proven >= samples_lost(best) if best is not None else (proven > Lmax and Lmax == N)
        front.append(_entry(n, best, found, exact, T))
        proof.append({"attacks": n, "samples_lost_below": proven, "horizon_samples": N,
                      "schedules": sr.evaluated + enumerated})
        notes.append(note)
    search = ("least lost samples per number of attacks, priced (S - min(n, S)) T: " + "; ".join(notes))
    return WorstAttack(x0, e0, T, N, A, front, proof, search, False, crit, single, gr, ev, steps,
                       time.perf_counter() - t0, Lmax, tuple(best) if best is not None else ())


# ============================================================================ the greedy attacker, for comparison
def _greedy(loop: Loop, x0, e0: float, attacks: int, executor) -> dict:
    """Least duration budget kappa_D (on the sample grid) with which the greedy online attacker
    (kappa_F = A attacks, rho_F = rho_D = 0; thresholds ``GREEDY_THRESHOLDS``, scores
    ``GREEDY_SCORES``) makes the loop escape; its realized intervals."""
    from ..sim.batch import simulate_batch

    N = int(loop.n_steps)
    T = loop.T
    best = None
    lo, block = 0, 8
    while best is None and lo < N:  # kappa_D = d T by increasing d, in growing blocks
        ds = range(lo, min(lo + block, N))
        sel = [(d, th, sc) for sc in GREEDY_SCORES for th in GREEDY_THRESHOLDS for d in ds]
        gp = np.array([[attacks, 0.0, d * T, 0.0, th] for d, th, _ in sel])
        for sc in GREEDY_SCORES:
            idx = [j for j, c in enumerate(sel) if c[2] == sc]
            out = run_batch(loop.plant, loop.K, loop.qp, np.repeat(x0[None, :], len(idx), 0), N,
                            E0=np.full(len(idx), e0), greedy_params=gp[idx], score=sc, flow=loop.flow,
                            fields=_EVAL_FIELDS, executor=executor, model=loop.nominal)
            _, esc = classify(loop.plant, loop.K, loop.qp, out, loop.escape, model=loop.nominal, flow=loop.flow,
                              executor=executor)
            for j in np.flatnonzero(esc):
                d, th, _ = sel[idx[j]]
                if best is None or (d, th) < (best[0], best[1]):
                    best = (d, th, sc, gp[idx[j]])
        lo += block
        block *= 2
    if best is None:
        return {"escaped": False, "kappa_F": attacks, "searched_kappa_D_max": (N - 1) * T,
                "thresholds": list(GREEDY_THRESHOLDS), "scores": list(GREEDY_SCORES)}
    d, th, sc, gp = best
    res = simulate_batch(loop.plant, loop.K, replace(loop.qp, E0=e0), x0[None, :], N, greedy_params=gp, score=sc,
                         record=True, flow=loop.flow, model=loop.nominal)
    from attackers.schedule import Schedule

    assert res.theta is not None  # record=True
    sch = Schedule.from_theta(res.theta[0], T)
    return {"escaped": True, "kappa_F": attacks, "kappa_D": round(d * T, 12), "threshold": th, "score": sc,
            "intervals": [[round(a, 12), round(t, 12)] for a, t in sch.intervals],
            "total_duration": round(sch.total_duration, 12)}
