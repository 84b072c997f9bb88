"""Batch-simulator throughput on the paper's Lienard example, against a naive solve_ivp loop.

One trajectory-step = one sample: the plant's flow phi_T(x_k, u_k) plus the
encoder's and the decoder's predictions (update rule (xi)), with quantization,
attack lookup and the (E) update.  The batch simulator runs on one core (numba,
no threads).  The baseline, measured in the same run, is what one would write
without it: per trajectory, per sample, the same quantizer logic in numpy and
three scipy.integrate.solve_ivp(DOP853) calls at comparable tolerances.

Two kernels are timed: the generic one (the plant's right-hand side is a
function pointer; compiled once and cached on disk) and the specialized one
(``simulate_batch(..., specialize=True)``: right-hand side inlined, generated
per plant by ``testbed.sim.kernelcache`` and cached on disk too).  Their results are
identical, which the script checks.  The first call of each is timed in a fresh
process (after this process has filled the caches), which is what a command pays.

Also prints the flow-map error against a tight-tolerance solve_ivp reference on
states of the nominal region of attraction.

    python benchmarks/bench_simulator.py [--batch 20000] [--steps 300] [--repeat 3]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
import warnings

import numpy as np
from scipy.integrate import solve_ivp

from testbed import scenario
from testbed.loop.flow import phi_T
from testbed.sim.batch import in_nominal_roa, simulate_batch


def naive_loop(plant, K, qp, x0, theta, n_steps, rtol=1e-10, atol=1e-12):
    """The baseline: plain Python + solve_ivp, one trajectory, sample by sample."""
    M, Lam = qp.M, qp.Lambda
    f = plant.f

    def flow(x, u):
        return solve_ivp(lambda t, y: f(y, u), (0.0, qp.T), x, method="DOP853", rtol=rtol, atol=atol).y[:, -1]

    def quantize(x, xi, E):
        c = np.clip(np.floor((x - xi + E) / (2 * E) * M), 0, M - 1)
        return xi - E + (2 * c + 1) * E / M

    x = np.array(x0, float)
    xi_e = np.zeros_like(x)
    xi_d = np.zeros_like(x)
    E_e = E_d = qp.E0
    for k in range(n_steps):
        q_e = quantize(x, xi_e, E_e)
        th = theta[k]
        if th == 0:
            q_d = q_e.copy()  # the symbol arrived
            u = K @ q_d
            xi_e, E_e = flow(q_e, K @ q_e), Lam / M * E_e
            xi_d, E_d = flow(q_d, u), Lam / M * E_d
        else:
            u = np.zeros(K.shape[0])
            xi_e, E_e = flow(xi_e, u), Lam * E_e
            xi_d, E_d = flow(xi_d, u), Lam * E_d
        x = flow(x, u)
    return x


FRESH = """
import time
import numpy as np
from testbed import scenario
from testbed.sim.batch import simulate_batch
sc = scenario.load("paper")
plant = sc.make_plant()
t0 = time.perf_counter()
simulate_batch(plant, sc.K, sc.quantizer, np.zeros((2, 2)), 5, theta=sc.theta(5)[None], specialize={spec})
print(time.perf_counter() - t0)
"""


def first_call_fresh(spec: bool) -> float:
    """Seconds of the first simulate_batch call in a new Python process (imports not included)."""
    p = subprocess.run([sys.executable, "-c", FRESH.format(spec=spec)], capture_output=True, text=True,
                       timeout=600, check=True)
    return float(p.stdout.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=20000, help="trajectories in the batch run")
    ap.add_argument("--steps", type=int, default=300, help="samples per trajectory (300 = 30 s)")
    ap.add_argument("--repeat", type=int, default=3, help="batch repetitions (best is reported)")
    ap.add_argument("--baseline", type=int, default=3, help="trajectories in the naive baseline")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")

    sc = scenario.load("paper")
    plant, K, qp, N = sc.make_plant(), sc.K, sc.quantizer, args.steps
    theta = sc.theta(N)
    rng = np.random.default_rng(0)
    X0 = rng.uniform(-0.1, 0.1, (args.batch, 2))

    rates = {}
    for spec in (False, True):
        t0 = time.perf_counter()
        simulate_batch(plant, K, qp, X0[:4], 5, theta=theta[None], specialize=spec)  # compile/load
        compile_s = time.perf_counter() - t0
        best = np.inf
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            res = simulate_batch(plant, K, qp, X0, N, theta=theta[None], specialize=spec)
            best = min(best, time.perf_counter() - t0)
        assert np.all(res.mismatch == 0)
        rates[spec] = (args.batch * N / best, best, first_call_fresh(spec), res.x_final.copy(), compile_s)
    assert np.array_equal(rates[False][3], rates[True][3]), "specialized kernel must give identical results"
    batch_rate, best = rates[True][0], rates[True][1]

    t0 = time.perf_counter()
    for i in range(args.baseline):
        xb = naive_loop(plant, K, qp, X0[i], theta, N)
    naive_s = time.perf_counter() - t0
    naive_rate = args.baseline * N / naive_s
    # the baseline computes the same loop: compare the final states it reached
    dev = np.max(np.abs(xb - rates[True][3][args.baseline - 1]))

    # flow-map accuracy on the nominal region of attraction
    g = np.linspace(-2.5, 2.5, 61)
    G = np.array(np.meshgrid(g, g)).reshape(2, -1).T
    roa = G[in_nominal_roa(plant, K, sc.T, G)]
    pick = roa[rng.choice(len(roa), size=min(300, len(roa)), replace=False)]
    U = np.concatenate([pick @ K.T, np.zeros((len(pick), 1))])
    Xf = np.concatenate([pick, pick])
    Y, _ = phi_T(plant, Xf, U, sc.T)
    err = 0.0
    for i in range(len(Xf)):
        ref = solve_ivp(lambda t, y, i=i: plant.f(y, U[i]), (0, sc.T), Xf[i], method="DOP853",
                        rtol=1e-14, atol=1e-16).y[:, -1]
        err = max(err, float(np.max(np.abs(ref - Y[i]))))

    print(f"Lienard paper example, T = {sc.T}, M = {qp.M}, {N} samples per trajectory")
    for spec, label in ((False, "generic (cached)"), (True, "specialized (cached)")):
        r, b, c, _, here = rates[spec]
        print(f"batch simulator, {label:20s}: {args.batch} x {N} samples in {b:.3f} s (best of {args.repeat})"
              f" = {r:,.0f} trajectory-steps/s on one core; first call {c:.2f} s in a fresh process"
              f" ({here:.2f} s in this one)")
    r, _, c, _, _ = rates[True]
    print(f"cached specialized kernel: {r:,.0f} trajectory-steps/s per core, first call {c:.2f} s in a fresh "
          f"process (goal >= 1e6 steps/s and < 1 s: {'met' if r >= 1e6 and c < 1.0 else 'NOT met'})")
    print(f"naive solve_ivp : {args.baseline} trajectories x {N} samples in {naive_s:.3f} s"
          f" = {naive_rate:,.0f} trajectory-steps/s")
    print(f"speed-up        : specialized {batch_rate / naive_rate:,.0f}x, generic {rates[False][0] / naive_rate:,.0f}x"
          "  (goal >= 100x; goal >= 1e6 steps/s)")
    print(f"baseline vs batch final state: max |diff| = {dev:.1e}")
    print(f"flow-map error  : max {err:.2e} over {len(Xf)} (x, u) on the nominal region of attraction"
          f" (goal <= 1e-9)")


if __name__ == "__main__":
    main()
