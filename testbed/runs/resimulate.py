"""``testbed resimulate RUN.mcap [--json]``: re-run a recorded run in the simulator and compare.

Its arguments and text output are ``testbed.commands.resimulate``; this module is what it computes.

The simulator (``testbed.sim.loop.simulate_loop``) runs the very protocol objects
the live nodes ran, fed with what the recording says happened and nothing else:

* theta_k as the controller decided it (received, lost at the deadline, an invalid
  payload, superseded), so the attacker's drops and every corrupted payload are
  replayed;
* the samples the encoder withheld (a late or lost ack) and the ones it never saw;
* u_k that never reached the plant in time (deadline misses);
* under physical timing, the actuation delay delta_k the plant measured (in ns).

Everything else (the symbols, xi_k, E_k at both ends, the OVERFLOW codewords, the
state) the simulator computes itself, and the result is compared sample by sample
with the recording.  Ideal timing reproduces a run bit for bit; physical timing
reproduces it to round-off at most (the plant integrates the same flow map with
the same delays).

JSON keys: ``samples``, ``checked`` (how many were resimulated: all, here), ``max_state_error`` (max over k
of ||x_k(live) - x_k(resimulated)||_inf),
``symbols_identical``, ``E_identical``, ``theta_identical``, ``first_divergence`` (k, or null),
``verdict`` and ``tolerance``.

Exit codes: 0 the run is reproduced, 1 it is not, 2 an unreadable recording.
"""

from __future__ import annotations

import numpy as np

from .run import run_of_recording

#: physical timing: the largest state error that still counts as reproduced
PHYSICAL_TOLERANCE = 1e-9


def recorded_run(run) -> dict:
    """The per-sample record a resimulation needs, from a recording's ``testbed.Run``
    (``testbed.runs.run.run_of_recording``): the values from its arrays, which samples each node recorded
    and what the controller and the plant said happened from its columns."""
    from ..sim.loop import Replay
    from ..wire import messages as msg

    cols, sc, a = run._columns, run.scenario, run.arrays
    N = min(run.N, sc.n_steps)
    hp, he, hc = cols.has("plant")[:N], cols.has("encoder")[:N], cols.has("controller")[:N]
    silent = he & (cols.get("encoder", "silent")[:N] != 0)
    have_sym = he & ~silent
    live = {
        "x": np.where(hp[:, None], a["x"][:N], np.nan),
        "symbols": np.where(have_sym, a["symbols"][:N], -1).astype(np.int64),
        "E": np.where(have_sym, a["E"][:N], np.nan),
        "E_dec": np.where(hc, a["E_dec"][:N], np.nan),
        "theta": np.where(hc, a["theta"][:N], -1).astype(np.int64),  # the controller's where it recorded
        "have_x": hp.copy(), "have_sym": have_sym, "have_dec": hc.copy(),
    }
    reason = np.where(hc, cols.get("controller", "reason")[:N], -1).astype(np.int64)
    u_missing = hp & ((cols.get("plant", "flags")[:N].astype(np.int64) & msg.PlantTelemetry.FLAG_NO_U) != 0)
    delays = np.where(hp, cols.get("plant", "delay_ns")[:N], 0).astype(np.int64)
    physical = sc.run.timing == "physical"
    replay = Replay(reason=reason, sensed=he.copy(), withheld=silent, u_missing=u_missing,
                    delays=delays if physical else None)
    final = cols.final
    x_final = None if final is None else np.asarray(final["x"], dtype=float)
    return {"scenario": sc, "N": N, "replay": replay, "live": live, "x_final": x_final}


def compare(run: dict, limit: int | None = None) -> dict:
    """Resimulate ``recorded_run(...)`` and compare it with the recording, sample by sample.

    ``limit``: resimulate only samples 0 .. limit - 1 (``testbed report`` bounds its check so;
    ``checked`` in the result says how many were, and the verdict says so when not all).
    """
    from ..sim.loop import simulate_loop

    sc, N, live = run["scenario"], run["N"], run["live"]
    n = N if limit is None else max(0, min(N, int(limit)))
    process = sc.make_process()
    try:
        res = simulate_loop(None, sc.K, sc.quantizer, sc.x0, n, None, sc.flow, model=sc.make_model(),
                            process=process, timing=sc.timing_params, u_max=sc.controller.u_max,
                            replay=run["replay"], method=sc.make_method(), device=sc.plant.device)
    finally:
        process.close()
    M = len(res.t)  # the resimulation stops early if its flow diverged
    hx = live["have_x"][:M]
    err = np.zeros(M)
    err[hx] = np.max(np.abs(live["x"][:M][hx] - res.x[hx]), axis=1)
    hs = live["have_sym"][:M]
    sym_diff = hs & (live["symbols"][:M] != res.symbols)
    E_diff = hs & ~((live["E"][:M] == res.E_enc) | (np.isnan(live["E"][:M]) & np.isnan(res.E_enc)))
    hd = live["have_dec"][:M]
    E_diff |= hd & ~(live["E_dec"][:M] == res.E_dec)
    th_diff = hd & (live["theta"][:M] != res.theta)
    physical = sc.run.timing == "physical"
    tol = PHYSICAL_TOLERANCE if physical else 0.0
    state_bad = err > tol
    if run["x_final"] is not None and M == N:
        final_err = float(np.max(np.abs(run["x_final"] - res.x_final)))
    else:
        final_err = None
    bad = sym_diff | E_diff | th_diff | state_bad
    first = int(np.argmax(bad)) if bad.any() else (M if M < n else None)
    max_err = float(max(err.max(initial=0.0), final_err or 0.0))
    ok = first is None and (final_err is None or final_err <= tol)
    span = "" if n == N else f" (samples 0 to {n - 1} of {N}; testbed resimulate checks every sample)"
    return {
        "samples": N,
        "checked": n,
        "resimulated": M,
        "timing_mode": sc.run.timing,
        "tolerance": tol,
        "max_state_error": max_err,
        "final_state_error": final_err,
        "symbols_identical": not bool(sym_diff.any()),
        "E_identical": not bool(E_diff.any()),
        "theta_identical": not bool(th_diff.any()),
        "first_divergence": first,
        "symbols_differ_at": np.nonzero(sym_diff)[0][:50].tolist(),
        "state_differs_at": np.nonzero(state_bad)[0][:50].tolist(),
        "replayed": {"lost": int(np.sum(run["replay"].reason != 0)),
                     "withheld": int(run["replay"].withheld.sum()),
                     "u_missing": int(run["replay"].u_missing.sum()),
                     "delays_ns": None if run["replay"].delays is None else {
                         "min": int(run["replay"].delays[:N].min(initial=0)),
                         "max": int(run["replay"].delays[:N].max(initial=0))}},
        "reproduced": bool(ok),
        "verdict": ("reproduced bit for bit" if ok and max_err == 0.0 else
                    f"reproduced (state within {max_err:.2g} <= {tol:g})" if ok else
                    f"NOT reproduced: first divergence at sample {first}") + span,
    }


def resimulate(path, *, trust_code: bool = False) -> dict:
    """``testbed resimulate PATH --json`` as a dict.  ``trust_code``: run a plant's or method's source stored
    in the recording (``testbed.runs.run.open``); without it, when that code is needed,
    ``plants.refs.CodeNotTrusted`` (one line naming ``--trust-code``) and nothing is run."""
    from plants.refs import CodeNotTrusted

    from ..record.summary import load

    run = run_of_recording(*load(path, trust_code=trust_code, note=False))  # the error below is the line
    not_run = run.scenario.code_not_run()
    if not_run:
        raise CodeNotTrusted(f"{not_run[0]}: re-simulation needs it")
    return compare(recorded_run(run))
