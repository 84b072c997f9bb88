"""Scaling of the analysis over processes: 1 and 2 local workers and a local Dask cluster.

On the paper's Lienard example, each job runs with ``--workers 1`` (in this
process), ``--workers 2`` (a local pool) and on a ``distributed.LocalCluster``
with 2 worker processes (1 thread each), after a warm-up that fills the kernel
cache.  The script checks that every result is identical to the one-worker
result and prints the wall times and the speed-up of 2 workers over 1 (goal >= 1.6x
on 2 cores) and of the Dask cluster over 1.

Jobs: the nominal region of attraction (``testbed roa``, 201 x 201, 30 s), the
budget sweep (``testbed sweep``, 21 x 21 budgets, 4 seeds, 60 s) and the
vulnerability map (``testbed vulnerability``, 31 x 31, one attack).

    python benchmarks/bench_scaling.py [--quick] [--no-dask]
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np

from testbed import scenario
from testbed.analysis import parallel
from testbed.analysis.roa import nominal_roa
from testbed.analysis.sweep import sweep
from testbed.analysis.vulnerability import vulnerability_map
from testbed.analysis.worst import Loop


def jobs(sc, quick: bool):
    plant = sc.make_plant()
    g = 81 if quick else 201
    nb = 7 if quick else 21
    vg = 15 if quick else 31

    def roa(ex):
        r = nominal_roa(plant, sc.K, sc.T, grid=g, horizon=30.0, tol=sc.run.converge_tol, executor=ex)
        return r.inside, r.traj_steps

    def sw(ex):
        r = sweep(plant, sc.K, sc.quantizer, sc.x0, np.linspace(0, 2, nb), np.linspace(0, 0.5, nb), kappa_F=1.0,
                  kappa_D=0.2, seeds=4, horizon=60.0, tol=sc.run.converge_tol, executor=ex)
        return np.stack([r.converged[k] for k in r.kinds] + [r.escaped[k] for k in r.kinds]), r.traj_steps

    def vul(ex):
        r = nominal_roa(plant, sc.K, sc.T, grid=vg, tol=sc.run.converge_tol, executor=ex)
        v = vulnerability_map(Loop.from_scenario(sc), r, executor=ex)
        return v.samples, v.traj_steps

    return [(f"roa {g} x {g}", roa), (f"sweep {nb} x {nb}", sw), (f"vulnerability {vg} x {vg}", vul)]


def timed(fn, ex):
    t0 = time.perf_counter()
    out, steps = fn(ex)
    return out, steps, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (smoke test)")
    ap.add_argument("--no-dask", action="store_true", help="skip the local Dask cluster")
    args = ap.parse_args()
    sc = scenario.load("paper")
    todo = jobs(sc, args.quick)
    t0 = time.perf_counter()
    # warm-up: fill the kernel caches (compile or load)
    nominal_roa(sc.make_plant(), sc.K, sc.T, grid=3, horizon=1.0)
    sweep(sc.make_plant(), sc.K, sc.quantizer, sc.x0, [0.5], [0.1], seeds=1, horizon=1.0)
    print(f"warm-up (numba compile or cache load): {time.perf_counter() - t0:.1f} s; "
          f"{parallel.default_workers()} cores available")
    two = parallel.Executor(2)
    nominal_roa(sc.make_plant(), sc.K, sc.T, grid=41, horizon=1.0, executor=two, chunk=100)  # start the pool
    rows = []
    for name, fn in todo:
        ref, steps, t1 = timed(fn, None)
        out, _, t2 = timed(fn, two)
        assert np.array_equal(out, ref, equal_nan=True), f"{name}: 2 workers differ from 1"
        rows.append([f"{name}: {steps:,} trajectory-steps; 1 worker {t1:.2f} s; 2 workers {t2:.2f} s = "
                     f"{t1 / t2:.2f}x", ref, fn, t1])
    parallel.shutdown()
    if not args.no_dask:  # after the local pool: its client's threads would make the pool spawn, not fork
        import distributed

        with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                      env={"NUMBA_NUM_THREADS": "1"}, silence_logs=logging.ERROR) as cluster:
            ex = parallel.Executor(scheduler=cluster.scheduler_address)
            try:
                for row in rows:
                    out, _, t3 = timed(row[2], ex)
                    assert np.array_equal(out, row[1], equal_nan=True), f"{row[0]}: Dask differs from 1 worker"
                    row[0] += f"; Dask LocalCluster, 2 workers {t3:.2f} s = {row[3] / t3:.2f}x"
            finally:
                ex.close()
    for row in rows:
        print(row[0] + " (results identical)")
    print("goal: 2 workers >= 1.6x over 1 on 2 cores")


if __name__ == "__main__":
    main()
