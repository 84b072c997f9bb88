"""The parallel map under the analysis: chunks of a batch on local processes or a Dask cluster.

Every analysis job (region of attraction, sweep, vulnerable states, worst
attack) is a batch of independent closed-loop runs.  :func:`run_batch` splits
the batch into chunks of trajectories, runs each chunk with the batch
simulator (``testbed.sim.batch.simulate_batch``, the cached specialized kernel)
and reassembles the per-trajectory results in input order.  A trajectory's
result does not depend on the chunk it ran in, so the output is bit-identical
whatever the number of workers.

Where the chunks run (:class:`Executor`):

* ``workers=1``: in this process, one chunk after the other (no pool);
* ``workers=N`` (default: every core this process may use): N local worker
  processes (forked on Linux, else spawned); the parent compiles or loads the
  kernel first, so the workers only load it (concurrent first compilations of
  one numba cache can crash), and every worker runs numba with one thread;
* ``scheduler="tcp://HOST:PORT"``: an existing Dask distributed cluster (the
  optional extra ``dask``).  The kernel is warmed on one worker, then on one
  worker per other host, before the chunks go out; a worker that dies has its
  chunks rerun elsewhere by the scheduler (and a chunk that raises is retried
  twice).

Only data travels: the chunk function is a module-level function that every
worker imports (a pickled jitted function would recompile in each worker).
"""

from __future__ import annotations

import atexit
import math
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from ..common import validate
from ..common.errors import BadInput
from ..loop.flow import DEFAULT_FLOW, FlowOptions
from ..loop.params import QuantizerParams

if TYPE_CHECKING:
    import numpy.typing as npt
    from distributed import Client

    from plants.base import Plant

#: environment of every worker process: one thread for numba and the BLAS libraries
WORKER_ENV = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
              "MKL_NUM_THREADS": "1"}

#: per-trajectory outputs of :func:`run_batch`
#: a progress callback: ``progress(done, total)``
Progress = Callable[[int, int], object]

FIELDS = ("x_final", "E_final", "status", "stop_k", "saturations", "mismatch", "max_norm", "attacked", "state_final")

#: trajectory-steps per chunk: at least this much work, so that a chunk costs far more than its
#: shipping (local pools: ~0.2 s of work; Dask: ~2 s, which keeps the scheduler light)
MIN_CHUNK_STEPS = 2e5
DASK_CHUNK_STEPS = 2e6


def default_workers() -> int:
    """Every core this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _init_worker() -> None:
    os.environ.update(WORKER_ENV)
    # Ctrl-C reaches the workers too (they share the terminal's process group); it is the parent's to
    # handle: it cancels the chunks not started and says what was interrupted, and the running chunks end
    # before the process exits.  (An idle worker interrupted would print a traceback from multiprocessing's
    # bootstrap; a worker that ended itself would make Python 3.11's pool set a result on a cancelled
    # future: another traceback.)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


# ============================================================================ executors
class Executor:
    """Where chunks run: this process, a local process pool, or a Dask cluster.

    Parameters
    ----------
    workers : processes (None: every core); 1 runs in this process.  Ignored with ``scheduler``.
    scheduler : address of a Dask scheduler, e.g. ``tcp://10.0.0.5:8786``.
    """

    def __init__(self, workers: int | None = None, scheduler: str | None = None):
        if workers is not None:
            validate.flag("--workers", int(workers), integer=True, lo=1)
        self.scheduler = scheduler
        self.workers = default_workers() if workers is None else int(workers)
        self._client: Client | None = None
        self._warm: set = set()
        if scheduler:
            self._client = _dask_client(scheduler)
            self.workers = max(1, _dask_nthreads(self._client))

    @property
    def client(self) -> Client | None:
        """The ``distributed.Client`` of the Dask cluster (None off Dask), for work the executor's maps do
        not cover (a campaign's live runs, one per host)."""
        return self._client

    @property
    def kind(self) -> str:
        return "dask" if self._client is not None else ("local" if self.workers > 1 else "serial")

    def describe(self) -> dict:
        """JSON-friendly description (``parallel`` in the commands' output)."""
        d = {"kind": self.kind, "workers": self.workers}
        if self.scheduler:
            d["scheduler"] = self.scheduler
        return d

    def chunk_steps(self) -> float:
        return DASK_CHUNK_STEPS if self.kind == "dask" else MIN_CHUNK_STEPS

    def map(self, fn: Callable[[Any], Any], items: list, *, warm: Any = None, progress: Progress | None = None) -> list:
        """[fn(item) for item in items], in order, on this executor.

        ``warm`` is an item (a small one) run first, once per kind of job, where the
        workers' numba cache lives, before the chunks are sent; ``progress(done, total)``
        is called as chunks finish.
        """
        total = len(items)
        if total == 0:
            return []
        if self.kind == "serial" or total == 1:
            out = []
            for i, it in enumerate(items):
                out.append(fn(it))
                if progress is not None:
                    progress(i + 1, total)
            return out
        if self.kind == "local":
            if warm is not None:
                fn(warm)  # compile or load the kernel here, before any worker does
            return _local_map(fn, items, self.workers, progress)
        return _dask_map(self._client, fn, items, warm, self._warm, progress)

    def imap(self, fn: Callable[[Any], Any], items: list, *, warm: Any = None) -> Iterator[tuple[int, Any]]:
        """(index, fn(item)) for every item, as each finishes (in order on one process): a caller that
        stores every result as it arrives (a campaign's journal) loses only the items in flight."""
        if not items:
            return
        if self.kind == "serial" or len(items) == 1:
            for i, it in enumerate(items):
                yield i, fn(it)
            return
        if self.kind == "local":
            from concurrent.futures import as_completed

            if warm is not None:
                fn(warm)
            pool = _pool(self.workers)
            futs = {pool.submit(fn, it): i for i, it in enumerate(items)}
            try:
                for f in as_completed(futs):
                    yield futs[f], f.result()
            finally:
                for f in futs:
                    f.cancel()
            return
        distributed = _import_distributed()
        client = self._client
        assert client is not None  # kind "dask"
        if warm is not None:
            _dask_warm(client, fn, warm, self._warm)
        dfuts = [client.submit(fn, it, pure=False, retries=2) for it in items]
        index = {f.key: i for i, f in enumerate(dfuts)}
        try:
            for f in distributed.as_completed(dfuts, loop=client.loop):
                yield index[f.key], f.result()
        finally:
            client.cancel(dfuts)

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None


# ---------------------------------------------------------------------------- local processes
_pools: dict = {}
_pool_lock = threading.Lock()


def _context():
    import multiprocessing as mp

    # fork is instant and the children inherit the kernels the parent just loaded; with other
    # threads running (a Dask client, a viewer) forking is unsafe, so spawn then
    if sys.platform.startswith("linux") and threading.active_count() == 1:
        return mp.get_context("fork")
    return mp.get_context("spawn")


def _pool(workers: int):
    from concurrent.futures import ProcessPoolExecutor

    with _pool_lock:
        pool = _pools.get(workers)
        if pool is None:
            pool = ProcessPoolExecutor(workers, mp_context=_context(), initializer=_init_worker)
            _pools[workers] = pool
        return pool


@atexit.register
def shutdown() -> None:
    """Stop the local worker processes (also at exit)."""
    with _pool_lock:
        for p in _pools.values():
            p.shutdown(wait=True, cancel_futures=True)
        _pools.clear()


def _local_map(fn, items, workers, progress):
    from concurrent.futures import as_completed
    from concurrent.futures.process import BrokenProcessPool

    pool = _pool(workers)
    futs = {pool.submit(fn, it): i for i, it in enumerate(items)}
    out = [None] * len(items)
    try:
        for done, f in enumerate(as_completed(futs), 1):
            out[futs[f]] = f.result()
            if progress is not None:
                progress(done, len(items))
    except BrokenProcessPool:
        with _pool_lock:
            _pools.pop(workers, None)
        raise RuntimeError("a worker process died (out of memory?); rerun, or use fewer --workers") from None
    except BaseException:
        for f in futs:
            f.cancel()
        raise
    return out


# ---------------------------------------------------------------------------- Dask
def _import_distributed():
    try:
        import distributed
    except ImportError:
        raise BadInput("--scheduler needs Dask: pip install -e '.[dask]' (the optional extra 'dask')") from None
    return distributed


def _dask_client(address: str):
    distributed = _import_distributed()
    try:
        return distributed.Client(address, timeout="10s", set_as_default=False)
    except (OSError, TimeoutError, ValueError) as e:
        raise BadInput(f"cannot connect to the Dask scheduler at {address}: {e}") from None


def _dask_nthreads(client) -> int:
    info = client.scheduler_info()
    return sum(int(w.get("nthreads", 1)) for w in info.get("workers", {}).values())


def _dask_warm(client, fn, warm, done: set) -> None:
    """Run ``warm`` on one worker, then on one worker of every other host (each host's numba cache)."""
    key = getattr(fn, "__qualname__", str(fn)), _warm_key(warm)
    if key in done:
        return
    workers = client.scheduler_info().get("workers", {})
    by_host: dict = {}
    for addr, w in sorted(workers.items()):
        by_host.setdefault(w.get("host", addr), addr)
    first, *others = list(by_host.values()) or [None]
    kw = {"workers": [first], "allow_other_workers": True} if first else {}
    client.submit(fn, warm, pure=False, **kw).result()
    if others:
        futs = [client.submit(fn, warm, pure=False, workers=[a], allow_other_workers=True) for a in others]
        client.gather(futs)
    done.add(key)


def _warm_key(warm):
    return getattr(warm, "warm_key", None) or type(warm).__name__


def _dask_map(client, fn, items, warm, warmed: set, progress):
    distributed = _import_distributed()
    if warm is not None:
        _dask_warm(client, fn, warm, warmed)
    futs = [client.submit(fn, it, pure=False, retries=2) for it in items]
    index = {f.key: i for i, f in enumerate(futs)}
    out = [None] * len(items)
    try:
        for done, f in enumerate(distributed.as_completed(futs, loop=client.loop), 1):
            out[index[f.key]] = f.result()
            if progress is not None:
                progress(done, len(items))
    except BaseException:
        client.cancel(futs)
        raise
    return out


# ============================================================================ batches of runs
@dataclass(frozen=True)
class BatchChunk:
    """One chunk of a batch: everything a worker needs to run it (data only)."""

    plant: Plant
    K: np.ndarray
    qp: QuantizerParams
    X0: np.ndarray
    E0: np.ndarray
    n_steps: int
    theta: np.ndarray | None
    sched_idx: np.ndarray | None
    greedy_params: np.ndarray | None
    score: str
    mode: str | None
    flow: FlowOptions
    fields: tuple
    specialize: bool = True
    model: Plant | None = None     # the predictions' model (rule (xi)); None: the plant itself
    init_state: np.ndarray | None = None  # (B, W) both ends' state to continue from (``simulate_batch``)
    stop: tuple | None = None             # (x_tol, E_tol, x_out) early stop (``simulate_batch``)

    @property
    def warm_key(self) -> tuple:
        m = self.model if self.model is not None else self.plant
        return (type(self.plant).__module__, type(self.plant).__name__, type(m).__module__, type(m).__name__,
                self.mode, self.theta is None, self.greedy_params is None)


def run_chunk(c: BatchChunk) -> dict:
    """Run one chunk (one simulator call per distinct E_0); per-trajectory fields in chunk order."""
    from ..sim.batch import simulate_batch

    B = c.X0.shape[0]
    out: dict = {}
    for e in np.unique(c.E0):
        sel = np.flatnonzero(c.E0 == e)
        kw: dict[str, Any] = {}
        if c.theta is not None:
            assert c.sched_idx is not None  # made with theta (run_batch)
            kw["theta"] = c.theta
            kw["sched_idx"] = c.sched_idx[sel]
        if c.greedy_params is not None:
            kw["greedy_params"] = c.greedy_params[sel]
        if c.init_state is not None:
            kw["init_state"] = c.init_state[sel]
        res = simulate_batch(c.plant, c.K, replace(c.qp, E0=float(e)), c.X0[sel], c.n_steps, score=c.score,
                             mode=c.mode, flow=c.flow, specialize=c.specialize, model=c.model,
                             stop=c.stop, **kw)
        for k in c.fields:
            v = getattr(res, k)
            if k not in out:
                out[k] = np.zeros((B,) + v.shape[1:], dtype=v.dtype)
            out[k][sel] = v
    return out


def run_batch(plant: Plant, K: npt.ArrayLike, qp: QuantizerParams, X0: npt.ArrayLike, n_steps: int, *,
              E0: npt.ArrayLike | None = None, theta: npt.ArrayLike | None = None,
              sched_idx: npt.ArrayLike | None = None, greedy_params: npt.ArrayLike | None = None,
              score: str = "state", mode: str | None = None, flow: FlowOptions = DEFAULT_FLOW,
              fields: Sequence[str] = FIELDS, executor: Executor | None = None, progress: Progress | None = None,
              chunk: int | None = None, specialize: bool = True, model: Plant | None = None,
              init_state: npt.ArrayLike | None = None, stop: tuple[float, float, float] | None = None) -> dict:
    """Run B closed loops in chunks on ``executor``; per-trajectory ``fields`` in input order.

    Parameters
    ----------
    plant, K, qp, n_steps, score, mode, flow : as for ``testbed.sim.batch.simulate_batch``.
    model : the model of the encoder's and decoder's predictions (default: ``plant``), as for
        ``simulate_batch``: ``plant`` is the true plant the state follows.
    X0 : (B, n) initial states.
    E0 : (B,) E_0 per trajectory (default: ``qp.E0`` for all).
    theta, sched_idx : an (S, N) attack table and the row of each trajectory (default row 0).
    greedy_params : (5,) or (B, 5) budgets of the online greedy attacker.
    fields : the ``BatchResult`` fields to return (see ``FIELDS``).
    executor : where the chunks run (None: this process).
    chunk : trajectories per chunk (default: from the executor, see ``MIN_CHUNK_STEPS``).
    init_state, stop : (B, W) states to continue from and the early stop, as for ``simulate_batch``.

    Returns
    -------
    dict field -> array with B rows, identical for every executor and chunk size.
    """
    X0 = np.ascontiguousarray(np.atleast_2d(np.asarray(X0, dtype=np.float64)))
    B = X0.shape[0]
    E0 = np.full(B, float(qp.E0)) if E0 is None else np.broadcast_to(np.asarray(E0, dtype=np.float64), (B,))
    tab = None if theta is None else np.ascontiguousarray(np.atleast_2d(np.asarray(theta, dtype=np.uint8)))
    if tab is not None:
        sidx = (np.zeros(B, dtype=np.int64) if sched_idx is None
                else np.broadcast_to(np.asarray(sched_idx, dtype=np.int64), (B,)))
        if sidx.size and (sidx.min() < 0 or sidx.max() >= tab.shape[0]):
            raise ValueError("sched_idx points outside the theta table")
    gp = None
    if greedy_params is not None:
        gp = np.asarray(greedy_params, dtype=np.float64)
        gp = np.broadcast_to(gp, (B, 5)) if gp.ndim == 1 else gp
        if gp.shape != (B, 5):
            raise ValueError(f"greedy_params must have shape (5,) or ({B}, 5), got {gp.shape}")
    fields = tuple(fields)
    ist = None if init_state is None else np.ascontiguousarray(np.asarray(init_state, dtype=np.float64))
    Kc = np.ascontiguousarray(np.asarray(K, dtype=np.float64))
    if B == 0:
        n = plant.n
        shapes = {"x_final": (0, n), "state_final": (0, 2 * (n + 1 + plant.m))}
        return {k: np.zeros(shapes.get(k, (0,))) for k in fields}
    chunk = chunk_size(B, n_steps, executor) if chunk is None else max(1, int(chunk))

    def make(sl) -> BatchChunk:
        t, s = None, None
        if tab is not None:
            rows, inv = np.unique(sidx[sl], return_inverse=True)
            t, s = np.ascontiguousarray(tab[rows]), inv.astype(np.int64).ravel()
        return BatchChunk(plant, Kc, qp, X0[sl], np.array(E0[sl]), int(n_steps), t, s,
                          None if gp is None else np.ascontiguousarray(gp[sl]), score, mode, flow, fields,
                          specialize, None if model is plant else model,
                          None if ist is None else np.ascontiguousarray(ist[sl]), None if stop is None else tuple(stop))

    # strided chunks (chunk j holds trajectories j, j + C, j + 2 C, ...): neighbouring trajectories
    # often cost alike (an escaping one stiffens the flow), so this balances the workers
    C = math.ceil(B / chunk)
    sets = [np.arange(j, B, C) for j in range(C)]
    items = [make(ix) for ix in sets]
    warm = None
    if executor is not None and len(items) > 1:
        warm = replace(make(np.arange(1)), n_steps=2, stop=None)
    parts = (executor.map(run_chunk, items, warm=warm, progress=progress) if executor is not None
             else [_serial(run_chunk, it, i, len(items), progress) for i, it in enumerate(items)])
    out = {}
    for k in fields:
        v = parts[0][k]
        out[k] = np.zeros((B,) + v.shape[1:], dtype=v.dtype)
        for ix, p in zip(sets, parts):
            out[k][ix] = p[k]
    return out


def chunk_size(B: int, n_steps: int, executor: Executor | None = None) -> int:
    """Trajectories per chunk: 4 chunks per worker (10 in one process, for the progress bar),
    never less work than ``MIN_CHUNK_STEPS`` (``DASK_CHUNK_STEPS`` on a cluster)."""
    workers = 1 if executor is None else executor.workers
    steps = executor.chunk_steps() if executor is not None else MIN_CHUNK_STEPS
    per = max(1, math.ceil(steps / max(int(n_steps), 1)))
    return max(1, per, math.ceil(B / (4 * workers if workers > 1 else 10)))


def n_chunks(B: int, n_steps: int, executor: Executor | None = None) -> int:
    """How many chunks :func:`run_batch` makes of B trajectories (for progress totals)."""
    return math.ceil(B / chunk_size(B, n_steps, executor)) if B > 0 else 0


class Stages:
    """One progress bar over several batches run one after the other.

    ``Stages(progress, [n1, n2, ...])`` with the expected chunk count of each batch;
    ``next()`` is the callback of the next batch (its real count replaces the estimate).
    """

    def __init__(self, progress: Progress | None, expected: Iterable[int]) -> None:
        self.progress = progress
        self.counts = [max(int(n), 1) for n in expected]
        self.i = -1

    def next(self) -> Callable[[int, int], None] | None:
        self.i += 1
        progress = self.progress
        if progress is None:
            return None
        i = self.i
        if i >= len(self.counts):
            self.counts.append(1)

        def cb(done: int, total: int) -> None:
            self.counts[i] = max(int(total), 1)
            progress(sum(self.counts[:i]) + done, sum(self.counts))

        return cb

    def finish(self) -> None:
        """The bar at its end (stages that were not needed are dropped)."""
        if self.progress is not None:
            self.counts = self.counts[:max(self.i + 1, 1)]
            self.progress(sum(self.counts), sum(self.counts))


def _serial(fn, it, i, total, progress):
    r = fn(it)
    if progress is not None:
        progress(i + 1, total)
    return r
