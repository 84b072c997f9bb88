"""Analysis benchmarks on the paper's Lienard example.

1. Nominal region of attraction: a 201 x 201 grid over a 30 s horizon (300 samples
   per state, 12.1 M trajectory-steps), ``testbed.analysis.roa.nominal_roa``.
2. Empirical DoS tolerance: a 21 x 21 grid of budgets (rho_F, rho_D) with several
   schedules per point (random seeds, the periodic schedule, the greedy attacker),
   60 s of attacked operation each, ``testbed.analysis.sweep.sweep``; the escape
   check of failed runs (nominal loop from x_N) is included in the wall time but
   not in the trajectory-step count.
3. Theorem 1 region (both rules) and Theorem 2 with gamma = auto (pure numerics).

A warm-up call compiles (or loads from the numba cache) the simulator kernel
first; the compile time is printed separately.  Single core.

    python benchmarks/bench_analysis.py [--grid 201] [--budgets 21] [--seeds 4] [--quick]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from testbed import scenario
from testbed.analysis.roa import nominal_roa
from testbed.analysis.summary import analyze
from testbed.analysis.sweep import sweep


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grid", type=int, default=201, help="region-of-attraction grid per axis (default 201)")
    ap.add_argument("--horizon", type=float, default=30.0, help="region-of-attraction horizon [s] (default 30)")
    ap.add_argument("--budgets", type=int, default=21, help="budget points per axis (default 21)")
    ap.add_argument("--seeds", type=int, default=4, help="random schedules per budget point (default 4)")
    ap.add_argument("--sweep-horizon", type=float, default=60.0, help="attacked seconds per run (default 60)")
    ap.add_argument("--quick", action="store_true", help="small sizes (smoke test)")
    args = ap.parse_args()
    if args.quick:
        args.grid, args.budgets, args.seeds = 41, 5, 1

    sc = scenario.load("paper")
    plant = sc.make_plant()

    t0 = time.perf_counter()
    nominal_roa(plant, sc.K, sc.T, grid=3, horizon=1.0)
    sweep(plant, sc.K, sc.quantizer, sc.x0, [0.5], [0.1], seeds=1, horizon=1.0)
    print(f"warm-up (numba compile or cache load): {time.perf_counter() - t0:.1f} s")

    roa = nominal_roa(plant, sc.K, sc.T, grid=args.grid, horizon=args.horizon, tol=sc.run.converge_tol)
    print(f"region of attraction {args.grid} x {args.grid}, {args.horizon:g} s: {roa.traj_steps:,} trajectory-steps "
          f"in {roa.wall:.2f} s = {roa.rate:,.0f} trajectory-steps/s; {roa.fraction:.4f} of the window inside, "
          f"area {roa.area:.3f}")

    rF = np.linspace(0.0, 2.0, args.budgets)
    rD = np.linspace(0.0, 0.5, args.budgets)
    sw = sweep(plant, sc.K, sc.quantizer, sc.x0, rF, rD, kappa_F=1.0, kappa_D=0.2, seeds=args.seeds,
               horizon=args.sweep_horizon, tol=sc.run.converge_tol)
    per = sw.runs / (args.budgets ** 2)
    print(f"sweep {args.budgets} x {args.budgets} budgets, {per:.2f} schedules per point ({args.seeds} random, "
          f"periodic, greedy), {args.sweep_horizon:g} s: {sw.runs:,} runs, {sw.traj_steps:,} trajectory-steps in "
          f"{sw.wall:.2f} s = {sw.rate:,.0f} trajectory-steps/s (escape checks included in the time)")

    t0 = time.perf_counter()
    res = analyze(sc)
    print(f"analyze (Theorem 1 both rules, Theorem 2 gamma=auto, delta table): {time.perf_counter() - t0:.2f} s; "
          f"rho_D_max={res['rho_D_max']:.4f} rho_F_max={res['rho_F_max']:.4f} delta={res['delta']:.3g}")


if __name__ == "__main__":
    main()
