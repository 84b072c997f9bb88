"""The strongest attacker: the least DoS duration that drives the loop out of the region of attraction.

The paper ends on an open question: "there are vulnerable positions in the
state space from which it is easy for the attacker to make the state leave the
region of attraction".  This module answers it on the batch simulator.

A schedule of at most A *sample-aligned* attacks is a set of runs of lost
packets: theta_k = 1 exactly for k0_i <= k <= k0_i + L_i - 1 (L_i >= 1 samples),
the runs separated by at least one sample (touching runs would be one attack).
Run i is the attack interval [k0_i T, (k0_i + L_i - 1) T] of the paper
(Section II.C), of duration (L_i - 1) T: a single lost packet is an impulsive
attack of duration 0.  The *total duration* |A| = sum_i (L_i - 1) T is what
Assumption 4 budgets.

The loop from x_0 has *escaped* when, after the scenario's N samples, the flow
diverged or x_N is outside the nominal region of attraction (the nominal loop
from x_N does not reach ||x|| < tol within 60 s): the definition of
``testbed simulate`` (``testbed.simulate.summarize``).  A run that converged,
||x_N|| < tol, has not escaped (the nominal loop from there converges); only
the others are checked by the nominal loop (``sweep.classify``).

Search (:func:`least_single`, :func:`worst_attack`):

* A = 1, exact: every start k0 and length L, by increasing L.  First a bound:
  the attack at k0 = 0 of every length; then all starts for every shorter
  length, ascending, until one escapes.  The smallest escaping L (and, among
  its starts, the earliest) is the answer; every shorter single attack was
  simulated and did not escape.
* A >= 2: a beam search over sets of runs (beam width ``beam``): the
  non-escaping single attacks shorter than the best one, ranked by the peak
  ||x_k||_inf they cause, are extended by one more run anywhere (disjoint, not
  touching) with a total duration below the best found so far, A - 1 times.
  The answer is exact when it has duration 0, or when every schedule of 2..A
  runs with a smaller total duration could be enumerated (at most
  ``exhaustive_limit`` of them) and none escapes.

Every candidate schedule is one row of a theta table; a batch of them is one
``parallel.run_batch`` call, so the search runs on all cores or a Dask cluster.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from math import comb

import numpy as np

from ..flow import DEFAULT_FLOW, FlowOptions
from .parallel import Stages, n_chunks, run_batch
from .sweep import classify

#: horizon of the nominal check from x_N (as ``testbed.simulate.in_nominal_roa`` in ``summarize``)
ESCAPE_HORIZON = 60.0
#: thresholds and scores tried for the greedy attacker's comparison
GREEDY_THRESHOLDS = (0.0, 0.25, 0.5, 0.75, 0.9)
GREEDY_SCORES = ("state", "E")


# ============================================================================ the loop and its candidates
@dataclass(frozen=True)
class Loop:
    """The closed loop whose attacks are searched: plant, gain, quantizer, N samples, escape test.

    ``plant`` is the true plant the state follows; ``model`` (default ``plant``) the plant
    model of the encoder's and decoder's predictions (a scenario's ``[model]``) and of the
    escape test's nominal loop.
    """

    plant: object
    K: np.ndarray
    qp: object            # QuantizerParams (E_0 per initial state is given separately)
    n_steps: int
    tol: float = 1e-4
    flow: FlowOptions = DEFAULT_FLOW
    model: object = None

    @property
    def T(self) -> float:
        return float(self.qp.T)

    @property
    def nominal(self):
        """The plant model of the predictions and of the escape test."""
        return self.plant if self.model is None else self.model

    @classmethod
    def from_scenario(cls, sc) -> "Loop":
        return cls(sc.make_plant(), np.asarray(sc.K, dtype=float), sc.quantizer, sc.n_steps, sc.run.converge_tol,
                   sc.flow, sc.make_model())


def e0_for(loop: Loop, X0) -> np.ndarray:
    """E_0 per initial state: max(quantizer E_0, ||x_0||_inf) (Assumption 5: x_0 in Q(0, E_0))."""
    X0 = np.atleast_2d(X0)
    return np.maximum(float(loop.qp.E0), np.max(np.abs(X0), axis=1))


def runs_to_intervals(runs, T: float) -> list[list[float]]:
    """[(k0, L), ...] -> [[start, length], ...] in seconds (a scenario's ``[attack] intervals``)."""
    return [[round(k0 * T, 12), round((L - 1) * T, 12)] for k0, L in sorted(runs)]


def duration_samples(runs) -> int:
    """Total duration of the runs in sampling periods: sum (L_i - 1)."""
    return int(sum(L - 1 for _k0, L in runs))


def theta_table(runs_list, n_steps: int) -> np.ndarray:
    """(C, N) uint8 table: row c has theta_k = 1 on every run (k0, L) of candidate c."""
    tab = np.zeros((len(runs_list), n_steps), dtype=np.uint8)
    for c, runs in enumerate(runs_list):
        for k0, L in runs:
            tab[c, k0:k0 + L] = 1
    return tab


def single_table(k0, L, n_steps: int) -> np.ndarray:
    """theta table of single runs (k0[c], L[c])."""
    ar = np.arange(n_steps)
    k0 = np.asarray(k0)[:, None]
    return ((ar >= k0) & (ar < k0 + np.asarray(L)[:, None])).astype(np.uint8)


def evaluate(loop: Loop, X0, E0, tab, sched_idx, *, executor=None, progress=None, stages=None):
    """(escaped, peak ||x_k||_inf) of each candidate row: trajectory b starts at X0[b] with E0[b]
    under row sched_idx[b] of ``tab``."""
    st = stages or Stages(progress, [n_chunks(len(sched_idx), loop.n_steps, executor), 1])
    out = run_batch(loop.plant, loop.K, loop.qp, X0, loop.n_steps, E0=E0, theta=tab, sched_idx=sched_idx,
                    flow=loop.flow, fields=("x_final", "status", "max_norm"), executor=executor,
                    progress=st.next(), model=loop.nominal)
    _, esc = classify(loop.nominal, loop.K, loop.T, out["x_final"], out["status"], loop.tol,
                      escape_horizon=ESCAPE_HORIZON, flow=loop.flow, executor=executor, progress=st.next())
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


def least_single(loop: Loop, X0, *, E0=None, max_len: int | None = None, executor=None, progress=None,
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


def all_schedules(m: int, extra: int, n_steps: int):
    """Every schedule of m runs with total duration ``extra`` samples, as tuples of (k0, L)."""
    for ext in _compositions(extra, m):
        lengths = tuple(e + 1 for e in ext)
        for ks in _placements(lengths, n_steps):
            yield tuple(zip(ks, lengths))


def _splits(runs, n_steps: int):
    """Schedules with one more run: a run split by one delivered sample, each piece also shifted
    by one sample (within the horizon, keeping runs apart)."""
    out = set()
    for i, (k, L) in enumerate(runs):
        others = runs[:i] + runs[i + 1:]
        for j in range(1, L - 1):  # sample k + j is delivered: pieces (k, j), (k + j + 1, L - j - 1)
            for da in (-1, 0, 1):
                for db in (-1, 0, 1):
                    a, b = (k + da, j), (k + j + 1 + db, L - j - 1)
                    if a[0] < 0 or b[0] + b[1] > n_steps or b[0] <= a[0] + a[1]:
                        continue
                    if _valid_add(others, *a) and _valid_add(others + (a,), *b):
                        out.add(tuple(sorted(others + (a, b))))
    return out


def _valid_add(runs, k0: int, L: int) -> bool:
    """Run (k0, L) neither overlaps nor touches any run of ``runs``."""
    for a, b in runs:
        if k0 <= a + b and a <= k0 + L:  # [k0, k0+L-1] within one sample of [a, a+b-1]
            return False
    return True


@dataclass
class WorstAttack:
    """Result of :func:`worst_attack` (``to_dict`` is the JSON of ``testbed worst-attack``)."""

    x0: np.ndarray
    E0: float
    T: float
    n_steps: int
    attacks: int
    runs: tuple            # ((k0, L), ...) of the answer; () if none (or none needed)
    escaped: bool          # the answer's schedule makes the loop escape
    exact: bool
    method: str
    unattacked_escapes: bool = False
    single: dict | None = None
    greedy: dict | None = None
    evaluated: int = 0
    traj_steps: int = 0
    wall: float = 0.0
    max_len: int = 0

    @property
    def total_duration(self) -> float:
        return duration_samples(self.runs) * self.T

    def to_dict(self) -> dict:
        return {"x0": self.x0.tolist(), "E0": self.E0, "T": self.T, "n_steps": self.n_steps,
                "horizon": self.n_steps * self.T, "attacks": self.attacks,
                "intervals": runs_to_intervals(self.runs, self.T),
                "total_duration": round(self.total_duration, 12), "samples_lost": int(sum(L for _, L in self.runs)),
                "escaped": self.escaped, "exact": self.exact, "method": self.method,
                "unattacked_escapes": self.unattacked_escapes, "max_length_samples": self.max_len,
                "single_attack": self.single, "greedy": self.greedy, "candidates": self.evaluated,
                "traj_steps": self.traj_steps, "wall_s": self.wall}


def worst_attack(loop: Loop, x0, *, attacks: int = 1, E0: float | None = None, max_len: int | None = None,
                 beam: int = 16, exhaustive_limit: int = 100_000, greedy: bool = True, executor=None,
                 progress=None) -> WorstAttack:
    """The shortest total DoS duration, in at most ``attacks`` sample-aligned attacks, that makes
    the loop from ``x0`` escape (see the module docstring for the search and its exactness).

    Parameters
    ----------
    loop : the closed loop; x0 : (n,) initial state; E0 : default :func:`e0_for`.
    attacks : A >= 1, the most attack intervals.
    max_len : longest single attack tried, in samples (default N).
    beam : beam width of the search for A >= 2.
    exhaustive_limit : enumerate every schedule of 2..A runs below the beam's answer when there
        are at most this many (then the answer is exact).
    greedy : also search the greedy online attacker's least duration budget (for comparison).
    """
    t0 = time.perf_counter()
    if int(attacks) < 1:
        raise ValueError(f"attacks must be >= 1, got {attacks}")
    attacks = int(attacks)
    x0 = np.asarray(x0, dtype=float).ravel()
    X0 = x0[None, :]
    e0 = float(e0_for(loop, X0)[0] if E0 is None else E0)
    N = int(loop.n_steps)
    Lmax = N if max_len is None else max(1, min(int(max_len), N))
    sr = least_single(loop, X0, E0=[e0], max_len=Lmax, executor=executor, progress=progress,
                      keep_pool=attacks >= 2)
    ev, steps = sr.evaluated, sr.traj_steps
    L1, k1 = int(sr.L[0]), int(sr.k0[0])
    if L1 == 0:
        return WorstAttack(x0, e0, loop.T, N, attacks, (), True, True, "no attack needed", True,
                           evaluated=ev, traj_steps=steps, wall=time.perf_counter() - t0, max_len=Lmax,
                           greedy=_greedy(loop, x0, e0, attacks, executor) if greedy else None)
    runs = ((k1, L1),) if L1 > 0 else ()
    single = {"intervals": runs_to_intervals(runs, loop.T), "total_duration": duration_samples(runs) * loop.T,
              "escaped": L1 > 0, "exact": True}
    method = "exhaustive over start and length"
    exact = True
    escaped = L1 > 0
    if attacks >= 2:
        best_d = L1 - 1 if L1 > 0 else Lmax  # strictly below this (in samples) is an improvement
        best_runs = runs
        # ---- beam search
        pool = sorted(((p, (k, ell)) for _s, k, ell, p in sr.pool if ell - 1 < best_d), reverse=True)
        level = []
        seen = set()
        for _p, r in pool:
            if len(level) >= beam:
                break
            level.append(((r,), r[1] - 1))
            seen.add((r,))
        # ... and the shorter attacks near the best single one: a delivered packet in the middle of
        # an attack costs the attacker little and saves one T of duration (two runs of L_a + L_b
        # lost packets last L_a + L_b - 2 samples, one run L_a + L_b - 1)
        if L1 > 0:
            for _p, (k, ell) in pool:
                if abs(k - k1) <= 2 and L1 - 4 <= ell < L1 and ((k, ell),) not in seen:
                    level.append((((k, ell),), ell - 1))
                    seen.add(((k, ell),))
        for _m in range(2, attacks + 1):
            cands = []
            for prefix, d_used in level:
                room = best_d - 1 - d_used  # the new run may add at most this much duration
                for ell in range(1, room + 2):
                    for k in range(0, N - ell + 1):
                        if _valid_add(prefix, k, ell):
                            c = tuple(sorted(prefix + ((k, ell),)))
                            if c not in seen:
                                seen.add(c)
                                cands.append(c)
            if not cands:
                break
            esc, peak = evaluate(loop, np.repeat(X0, len(cands), 0), np.full(len(cands), e0),
                                 theta_table(cands, N), np.arange(len(cands)), executor=executor,
                                 progress=progress)
            ev += len(cands)
            steps += len(cands) * N
            ds = np.array([duration_samples(c) for c in cands])
            if esc.any():
                i = min(np.flatnonzero(esc), key=lambda j: (ds[j], cands[j]))
                if ds[i] < best_d:
                    best_d, best_runs = int(ds[i]), cands[i]
                    escaped = True
            keep = [j for j in np.argsort(-peak, kind="stable") if not esc[j] and ds[j] < best_d]
            level = [(cands[j], int(ds[j])) for j in keep[:beam]]
        # ---- local search: split a run of the best schedule (one delivered packet inside it) and
        #      shift the pieces by a sample, while it improves
        while escaped and len(best_runs) < attacks:
            cands = sorted(c for c in _splits(best_runs, N) if c not in seen and duration_samples(c) < best_d)
            if not cands:
                break
            seen.update(cands)
            esc, _ = evaluate(loop, np.repeat(X0, len(cands), 0), np.full(len(cands), e0), theta_table(cands, N),
                              np.arange(len(cands)), executor=executor, progress=progress)
            ev += len(cands)
            steps += len(cands) * N
            hits = [c for c, e in zip(cands, esc) if e]
            if not hits:
                break
            best_runs = min(hits, key=lambda c: (duration_samples(c), c))
            best_d = duration_samples(best_runs)
        method = f"beam search (width {beam}) and local search over 2..{attacks} attacks"
        exact = best_d == 0 and escaped
        # ---- certify: enumerate every schedule of 2..A runs below the answer, if few enough
        if not exact and escaped:
            total = sum(count_schedules(m, e, N) for m in range(2, attacks + 1) for e in range(best_d))
            if total <= exhaustive_limit:
                cands = [c for m in range(2, attacks + 1) for e in range(best_d) for c in all_schedules(m, e, N)]
                if cands:
                    esc, _ = evaluate(loop, np.repeat(X0, len(cands), 0), np.full(len(cands), e0),
                                      theta_table(cands, N), np.arange(len(cands)), executor=executor,
                                      progress=progress)
                    ev += len(cands)
                    steps += len(cands) * N
                    if esc.any():
                        ds = np.array([duration_samples(c) for c in cands])
                        i = min(np.flatnonzero(esc), key=lambda j: (ds[j], cands[j]))
                        best_d, best_runs = int(ds[i]), cands[i]
                exact = True
                method += f", then every schedule below it enumerated ({total} of them)"
            else:
                method += f" (not exact: {total} schedules below the answer, more than {exhaustive_limit})"
        runs = best_runs
    else:
        exact = L1 > 0  # with no escape up to max_len, "none" is exact only for max_len = N
        if L1 < 0:
            exact = Lmax == N
    return WorstAttack(x0, e0, loop.T, N, attacks, tuple(runs), escaped, exact, method, False, single,
                       _greedy(loop, x0, e0, attacks, executor) if greedy else None, ev, steps,
                       time.perf_counter() - t0, Lmax)


# ============================================================================ the greedy attacker, for comparison
def _greedy(loop: Loop, x0, e0: float, attacks: int, executor) -> dict:
    """Least duration budget kappa_D (on the sample grid) with which the greedy online attacker
    (kappa_F = A attacks, rho_F = rho_D = 0; thresholds ``GREEDY_THRESHOLDS``, scores
    ``GREEDY_SCORES``) makes the loop escape; its realized intervals."""
    from ..simulate import simulate_batch

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
                            fields=("x_final", "status"), executor=executor, model=loop.nominal)
            _, esc = classify(loop.nominal, loop.K, T, out["x_final"], out["status"], loop.tol,
                              escape_horizon=ESCAPE_HORIZON, flow=loop.flow, executor=executor)
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

    sch = Schedule.from_theta(res.theta[0], T)
    return {"escaped": True, "kappa_F": attacks, "kappa_D": round(d * T, 12), "threshold": th, "score": sc,
            "intervals": [[round(a, 12), round(t, 12)] for a, t in sch.intervals],
            "total_duration": round(sch.total_duration, 12)}


# ============================================================================ the vulnerability map
@dataclass
class VulnerabilityMap:
    """Least DoS duration per grid state of the nominal region of attraction.

    ``duration[iy, ix]`` in seconds for the state (xs[ix], ys[iy]): nan outside the region;
    ``samples[iy, ix]`` lost samples of the answer (0: the quantized loop escapes without any
    attack, -1: no schedule up to ``max_len`` samples escapes, -2: outside the region).
    """

    xs: np.ndarray
    ys: np.ndarray
    dims: tuple
    duration: np.ndarray
    samples: np.ndarray
    attacks: int
    exact: np.ndarray       # (ny, nx) bool: the state's answer is proven minimal
    T: float
    n_steps: int
    max_len: int
    delta: float | None = None
    wall: float = 0.0
    traj_steps: int = 0
    evaluated: int = 0

    def to_dict(self) -> dict:
        inside = self.samples > -2
        d = self.duration[inside & (self.samples > 0)]

        def clean(a):
            return [[None if not np.isfinite(v) else float(v) for v in row] for row in a]

        return {"grid": [len(self.xs), len(self.ys)], "dims": list(self.dims),
                "window": [[float(self.xs[0]), float(self.xs[-1])], [float(self.ys[0]), float(self.ys[-1])]],
                "attacks": self.attacks, "T": self.T, "n_steps": self.n_steps, "max_length_samples": self.max_len,
                "states_in_region": int(inside.sum()),
                "escape_unattacked": int(np.sum(self.samples == 0)),
                "no_escape_found": int(np.sum(self.samples == -1)),
                "all_exact": bool(np.all(self.exact[inside])),
                "least_duration": None if d.size == 0 else round(float(d.min()), 12),
                "median_duration": None if d.size == 0 else round(float(np.median(d)), 12),
                "largest_duration": None if d.size == 0 else round(float(d.max()), 12),
                "delta": self.delta, "xs": self.xs.tolist(), "ys": self.ys.tolist(),
                "duration": clean(self.duration), "samples": self.samples.tolist(),
                "wall_s": self.wall, "traj_steps": self.traj_steps, "candidates": self.evaluated}


def vulnerability_map(loop: Loop, roa, *, attacks: int = 1, max_len: int | None = None, beam: int = 16,
                      executor=None, progress=None, delta: float | None = None) -> VulnerabilityMap:
    """Least DoS duration (at most ``attacks`` sample-aligned attacks) over the states of a
    nominal region of attraction grid (``roa``: a ``RoaResult``); see :func:`worst_attack`.

    A = 1 is exact and batched over every state at once; A >= 2 runs :func:`worst_attack`'s
    beam search state by state (much slower).  E_0 = max(quantizer E_0, ||x_0||_inf) per state.
    """
    t0 = time.perf_counter()
    GX, GY = np.meshgrid(roa.xs, roa.ys, indexing="xy")
    inside = roa.inside
    X = np.tile(roa.center, (int(inside.sum()), 1))
    X[:, roa.dims[0]] = GX[inside]
    X[:, roa.dims[1]] = GY[inside]
    N = int(loop.n_steps)
    Lmax = N if max_len is None else max(1, min(int(max_len), N))
    samples = np.full(inside.shape, -2, dtype=np.int64)
    duration = np.full(inside.shape, np.nan)
    exact = np.zeros(inside.shape, dtype=bool)
    ev = steps = 0
    if attacks <= 1:
        sr = least_single(loop, X, max_len=Lmax, executor=executor, progress=progress)
        Ls = sr.L
        ex = np.ones(len(X), dtype=bool) if Lmax == N else Ls >= 0
        ev, steps = sr.evaluated, sr.traj_steps
        dur = np.where(Ls > 0, np.round((Ls - 1) * loop.T, 12), np.where(Ls == 0, 0.0, np.nan))
    else:
        Ls = np.zeros(len(X), dtype=np.int64)
        dur = np.zeros(len(X))
        ex = np.zeros(len(X), dtype=bool)
        for i, x in enumerate(X):
            w = worst_attack(loop, x, attacks=attacks, max_len=Lmax, beam=beam, greedy=False, executor=executor)
            ev += w.evaluated
            steps += w.traj_steps
            if w.unattacked_escapes:
                Ls[i], dur[i] = 0, 0.0
            elif w.escaped:
                Ls[i], dur[i] = int(sum(L for _, L in w.runs)), w.total_duration
            else:
                Ls[i], dur[i] = -1, np.nan
            ex[i] = w.exact
            if progress is not None:
                progress(i + 1, len(X))
    samples[inside] = Ls
    duration[inside] = dur
    exact[inside] = ex
    return VulnerabilityMap(roa.xs, roa.ys, tuple(roa.dims), duration, samples, int(attacks), exact, loop.T, N,
                            Lmax, delta, time.perf_counter() - t0, steps, ev)
