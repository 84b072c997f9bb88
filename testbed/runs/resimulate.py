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
of ||x_k(live) - x_k(resimulated)||_inf; 0 on the recorded plant, whose x_k the re-run takes as they are:
there the plant's step error against the model is ``plant_model_error``),
``symbols_identical``, ``E_identical``, ``theta_identical``, ``first_divergence`` (k, or null),
``verdict`` and ``tolerance``.

Exit codes: 0 the run is reproduced, 1 it is not, 2 an unreadable recording.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:

    from ..scenario import Scenario
    from ..sim.loop import Replay, SimResult

#: physical timing: the largest state error that still counts as reproduced (on the model)
PHYSICAL_TOLERANCE = 1e-9

#: ``--plant``: what the loop is re-run on
PLANTS = ("auto", "model", "recorded")


def recorded_run(run: Any, limit: int | None = None) -> dict:  # run: a Run (runs/run.py imports this module)
    """The per-sample record a resimulation needs, from a recording's ``testbed.Run``
    (``testbed.runs.run.run_of_recording``): the values from its arrays, which samples each node recorded
    and what the controller and the plant said happened from its columns.

    ``limit``: ``compare(..., limit=limit)`` checks samples 0 .. limit - 1 only, so the values it compares
    (``live``) are kept for those and the one after (``plant_model_error`` reads x_k+1), not for the whole
    run: a report of a long recording holds a dozen per-sample columns fewer.  ``N`` and ``replay`` (its
    counts are the whole run's) stay whole.
    """
    from ..sim.loop import Replay
    from ..wire import messages as msg

    cols, sc, a = run.recorded_columns, run.scenario, run.arrays
    assert cols is not None  # a recording's Run (run_of_recording)
    N = min(run.N, sc.n_steps)
    L = N if limit is None else max(0, min(N, int(limit) + 1))   # the rows of ``live``
    he = cols.has("encoder")[:N]
    silent = he & (cols.get("encoder", "silent")[:N] != 0)
    hp_all, hc_all = cols.has("plant")[:N], cols.has("controller")[:N]
    reason = np.where(hc_all, cols.get("controller", "reason")[:N], -1).astype(np.int64)
    u_missing = hp_all & ((cols.get("plant", "flags")[:N].astype(np.int64) & msg.PlantTelemetry.FLAG_NO_U) != 0)
    physical = sc.run.timing == "physical"
    delays = np.where(hp_all, cols.get("plant", "delay_ns")[:N], 0).astype(np.int64) if physical else None
    replay = Replay(reason=reason, sensed=he.copy(), withheld=silent, u_missing=u_missing, delays=delays)
    hp, hc = hp_all[:L], hc_all[:L]
    have_sym = he[:L] & ~silent[:L]
    live = {
        "x": np.where(hp[:, None], a["x"][:L], np.nan),
        "symbols": np.where(have_sym, a["symbols"][:L], -1).astype(np.int64),
        "E": np.where(have_sym, a["E"][:L], np.nan),
        "E_dec": np.where(hc, a["E_dec"][:L], np.nan),
        "theta": np.where(hc, a["theta"][:L], -1).astype(np.int64),  # the controller's where it recorded
        "have_x": hp.copy(), "have_sym": have_sym, "have_dec": hc.copy(),
    }
    g = cols.get
    live.update({  # what the loop computed, each where its node recorded it (NaN elsewhere)
        "xi": np.where(have_sym[:, None], g("encoder", "xi")[:L], np.nan),
        "q_enc": np.where(have_sym[:, None], g("encoder", "q")[:L], np.nan),
        "saturated": have_sym & (g("encoder", "saturated")[:L] != 0),
        "xi_dec": np.where(hc[:, None], g("controller", "xi")[:L], np.nan),
        "q": np.where(hc[:, None], g("controller", "q")[:L], np.nan),
        "u": np.where(hc[:, None], g("controller", "u")[:L], np.nan),
        "u_acted": np.where(hp[:, None], g("plant", "u")[:L], np.nan),  # the input the plant applied
    })
    xm = g("plant", "x_meas")[:N] if ("plant", "x_meas") in cols.lay.cols else None
    live["x_meas"] = None if xm is None or not np.isfinite(xm).any() else \
        np.where(np.isfinite(xm[:L]), xm[:L], live["x"])
    final = cols.final
    x_final = None if final is None else np.asarray(final["x"], dtype=float)
    fault_at = run.summary.get("method_fault_at")
    fault_at = None if fault_at is None or fault_at < 0 or fault_at != N or N >= sc.n_steps else int(fault_at)
    if fault_at is not None:  # the method raised at sample N: the resimulation runs into it too
        xf = run.summary.get("x_final")  # x_N, where the run ended (the plant may have run on until the Stop)
        replay, x_final = _through_fault(cols, sc, replay, N), None if xf is None else np.asarray(xf, dtype=float)
    nodes = (cols.summaries.get("launcher") or {}).get("nodes") or {}
    external = bool(isinstance(nodes.get("plant"), dict) and nodes["plant"].get("external"))
    return {"scenario": sc, "N": N, "replay": replay, "live": live, "x_final": x_final, "method_fault_at": fault_at,
            "external_plant": external}


def _through_fault(cols, sc, replay, N: int):
    """``replay`` with sample N, the one the method raised at, appended: as its records say (the encoder
    sent or withheld it, the attacker dropped it), else sensed and received unless the scenario's
    schedule attacks t_N (a simulated recording holds nothing of the faulted sample)."""
    from ..loop.protocol import DEADLINE, RECEIVED
    from ..sim.loop import Replay

    def at(role, field, default):
        return cols.get(role, field)[N] if N < cols.rows and cols.has(role)[N] else default

    sensed = N >= cols.rows or not cols.has("plant")[N] or bool(N < cols.rows and cols.has("encoder")[N])
    withheld = bool(at("encoder", "silent", 0))
    dropped = at("attacker", "dropped", None)
    if dropped is None:
        sched = sc.attack.schedule(sc.T, (N + 1) * sc.T)
        dropped = 0 if sched is None else int(np.asarray(sched.theta_samples(sc.T, N + 1))[N])
    reason = DEADLINE if dropped or withheld or not sensed else RECEIVED

    def add(a, v):
        return np.concatenate([np.asarray(a), np.asarray([v], dtype=np.asarray(a).dtype)])

    return Replay(reason=add(replay.reason, reason), sensed=add(replay.sensed, sensed),
                  withheld=add(replay.withheld, withheld), u_missing=add(replay.u_missing, False),
                  delays=None if replay.delays is None else add(replay.delays, 0))


def plant_choice(run: dict, plant: str = "auto") -> tuple[str, str]:
    """Which plant ``--plant`` re-runs the loop on, and why: ("model" | "recorded", reason).  ``auto``:
    the recorded plant when the plant was a node from outside (``--external plant``, ``TESTBED_JOIN``) or
    the scenario declares it a device ([plant.sensor], [plant.actuator], [plant.disturbance]), else the model."""
    if plant not in PLANTS:
        raise ValueError(f"--plant {plant!r}: expected one of {', '.join(PLANTS)}")
    if plant != "auto":
        return plant, f"--plant {plant}"
    if run.get("external_plant"):
        return "recorded", "auto: the plant was an external node"
    if run["scenario"].plant.device is not None:
        return "recorded", "auto: the scenario declares the plant a device"
    return "model", "auto: the plant was the testbed's own"


class _NoPlant:
    """The process of a loop on the recorded plant: x_k comes from the recording, so nothing integrates."""

    def __init__(self, n: int, m: int):
        self.n, self.m = n, m
        self.x = np.zeros(n)

    def reset(self, x0) -> None:
        pass

    def advance(self, u, dt: float) -> int:
        return 0

    def perturb(self, w) -> None:
        pass

    def close(self) -> None:
        pass


def _steps_known(run: dict, n: int, res) -> np.ndarray | None:
    """phi_T(x_k, u_k) of the model for k = 0 .. n - 1 where a kernel re-run (``kernel_replay``) already
    computed it, NaN elsewhere; None when ``res`` is not such a re-run.  Its x_k+1 is phi_T of the same
    function (the true plant is the model: same class, parameters and flow options) at the same
    arguments, bit for bit: x_k as recorded, and the input the plant applied (the recorded u_k, clamped
    to u_max, as the kernel's u_k is): so it is what integrating again would give, at no cost."""
    if res is None or res.simulator != "batch" or len(res.t) != n or res.flow_status != 0:
        return None
    sc, live = run["scenario"], run["live"]
    plant, model = sc.make_plant(), sc.make_model()
    if type(plant) is not type(model) or not np.array_equal(np.asarray(plant.p), np.asarray(model.p)):
        return None
    u_max = sc.controller.u_max
    x, ua = live["x"][:n], np.clip(live["u_acted"][:n], -u_max, u_max)
    same = np.all(x == res.x[:n], axis=1) & np.all(ua == np.clip(res.u[:n], -u_max, u_max), axis=1)
    same &= np.all(np.isfinite(ua), axis=1)
    nxt = np.vstack([res.x[1:n], np.asarray(res.x_final, dtype=float)[None]])
    return np.where(same[:, None], nxt, np.nan)


def plant_model_error(run: dict, n: int | None = None, res: SimResult | None = None) -> dict | None:
    """e_k = ||x_k+1 - phi_T(x_k, u_k)||_inf over samples 0 .. n - 1 of a recording: the plant's reported
    x_k+1 against the scenario's model (its flow map, as the simulator runs it) from the reported x_k with
    the input that acted (the plant's recorded u_k; under physical timing u_k-1 held for the recorded
    delta_k first).  x_N is the final record's.  {"max", "at", "mean"}; None when no step is known
    (no two consecutive plant records) or the model has no right-hand side (an FMU)."""
    from ..loop.protocol import OdeProcess

    sc, N, live = run["scenario"], run["N"], run["live"]
    n = N if n is None else min(N, n)
    model = sc.make_model()
    if not hasattr(type(model), "rhs"):
        return None
    x, have, u = live["x"], live["have_x"], live["u_acted"]
    delays = run["replay"].delays
    known = None if delays is not None else _steps_known(run, n, res)
    x_next = np.vstack([x[1:], (np.full(x.shape[1], np.nan) if run["x_final"] is None else run["x_final"])[None]])
    have_next = np.append(have[1:], run["x_final"] is not None)
    u_max = sc.controller.u_max
    proc = OdeProcess(model, sc.flow)
    T = sc.T
    steps = have[:n] & have_next[:n]
    e_all = np.full(n, np.nan)
    todo = steps.copy()
    if known is not None:  # the steps the kernel re-run integrated already (``_steps_known``)
        done = steps & ~np.isnan(known[:, 0])
        if done.any():
            e_all[done] = np.max(np.abs(x_next[:n][done] - known[done]), axis=1)
        todo &= ~done
    for k in np.flatnonzero(todo):
        proc.reset(x[k])
        u_k = np.clip(u[k], -u_max, u_max)
        if delays is None:
            st = proc.advance(u_k, T)
        else:  # as ``protocol.PlantProtocol.step``: u_k-1 for delta_k, then u_k
            d = int(delays[k]) / 1e9
            u_prev = np.clip(u[k - 1], -u_max, u_max) if k > 0 and have[k - 1] else np.zeros_like(u_k)
            st = proc.advance(u_prev, d)
            if st == 0:
                st = proc.advance(u_k, T - d)
        e_all[k] = float(np.max(np.abs(x_next[k] - proc.x))) if st == 0 else float("inf")
    at = np.flatnonzero(steps)
    errs = e_all[at]
    if not len(errs):
        return None
    e = errs
    i = int(np.argmax(e))
    return {"max": float(e[i]), "at": int(at[i]), "mean": float(e.mean())}


#: what the loop computed, compared bit for bit by ``loop_differences`` (NaN equals NaN)
LOOP_QUANTITIES = ("symbols", "saturated", "E", "xi", "q_enc", "theta", "E_dec", "xi_dec", "q", "u")


def loop_differences(live: dict, res: SimResult, M: int) -> dict[str, np.ndarray]:
    """Per quantity of ``LOOP_QUANTITIES``: the samples (of 0 .. M - 1) where the recording and the re-run
    ``res`` (``sim.loop.SimResult``) differ, each where its node recorded it."""
    def same(a, b):
        a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
        eq = (a == b) | (np.isnan(a) & np.isnan(b))
        return eq if eq.ndim == 1 else eq.all(axis=1)

    hs, hd = live["have_sym"][:M], live["have_dec"][:M]
    ours = {"symbols": res.symbols, "saturated": res.saturated, "E": res.E_enc, "xi": res.xi_enc,
            "q_enc": res.q_enc, "theta": res.theta, "E_dec": res.E_dec, "xi_dec": res.xi_dec, "q": res.q,
            "u": res.u}
    out = {}
    for name in LOOP_QUANTITIES:
        where = hs if name in ("symbols", "saturated", "E", "xi", "q_enc") else hd
        out[name] = np.nonzero(where & ~same(live[name][:M], ours[name][:M]))[0]
    return out


def is_reproduced(plant: str, *, loop_identical: bool, first_divergence: int | None, final_error: float | None,
                  tolerance: float) -> bool:
    """The one verdict "reproduced": on the recorded plant, the loop is identical (the plant's own error
    against the model is reported beside it, not judged); on the model, no sample differs in any
    compared quantity and x_N is within the tolerance."""
    if plant == "recorded":
        return bool(loop_identical)
    return first_divergence is None and (final_error is None or final_error <= tolerance)


def kernel_replay(sc: Scenario, replay: Replay, n: int) -> SimResult | None:
    """Samples 0 .. n - 1 of ``replay`` re-run on the batch kernel (``sim.trajectory.simulate_kernel``), where
    the kernel runs the scenario and the replay says nothing but theta_k: ideal timing, every sample
    sensed and sent, every u_k delivered.  There the kernel and the per-sample loop of the protocol
    objects compute the same numbers bit for bit (``tests/test_simbatch.py``; the lost samples are an
    offline schedule to both, whatever the controller's reason), and the kernel does so hundreds of
    times faster.  None where it does not apply (the loop runs)."""
    from ..loop.protocol import RECEIVED
    from ..sim.trajectory import _bundled, simulate_kernel

    if n <= 0 or replay.delays is not None or sc.timing_params[0] or sc.plant.device is not None \
            or sc.plant.fmu is not None:
        return None
    if not (replay.sensed[:n].all() and not replay.withheld[:n].any() and not replay.u_missing[:n].any()):
        return None
    try:  # what the kernel runs (``sim.trajectory.kernel_refusal``; the attacker and the channel are the replay's)
        if not (_bundled(sc.make_plant()) and _bundled(sc.make_model())) \
                or sc.make_method().kernel_code(sc.quantizer) is None:
            return None
    except Exception:  # noqa: BLE001 - the loop reports what makes the scenario fail
        return None
    return simulate_kernel(sc, n, theta=(np.asarray(replay.reason[:n]) != RECEIVED).astype(np.uint8))


def compare(run: dict, limit: int | None = None, plant: str = "model", why: str | None = None) -> dict:
    """Resimulate ``recorded_run(...)`` and compare it with the recording, sample by sample.

    ``limit``: resimulate only samples 0 .. limit - 1 (``testbed report`` bounds its check so;
    ``checked`` in the result says how many were, and the verdict says so when not all).
    ``plant``: "model", the whole loop re-simulated, the plant by the scenario's true plant; "recorded",
    the encoder, the attacker's decisions, the controller and the method re-run on the states the plant
    reported (up to its first missing record), everything they computed compared bit for bit.
    ``why``: the reason for the choice (``plant_choice``), said in the verdict line.
    """
    from ..sim.loop import simulate_loop

    sc, N, live = run["scenario"], run["N"], run["live"]
    n = N if limit is None else max(0, min(N, int(limit)))
    recorded = plant == "recorded"
    if recorded:  # the loop stops at the plant's first missing record: no x_k to give it
        missing = np.nonzero(~live["have_x"][:n])[0]
        n_loop = int(missing[0]) if len(missing) else n
        model = sc.make_model()
        process = _NoPlant(model.n, model.m)
        extra = {"states": live["x"], "measured": live["x_meas"]}
    else:
        n_loop, model, process, extra = n, sc.make_model(), sc.make_process(), {}
    fault_at = run.get("method_fault_at")
    # on the model, run into the sample the method raised at (on the recorded plant there is no x_N to give it)
    through = fault_at is not None and n == N and not recorded
    res = kernel = None if recorded or through else kernel_replay(sc, run["replay"], n_loop)
    try:
        if res is None:
            res = simulate_loop(None, sc.K, sc.quantizer, sc.x0, n_loop + through, None, sc.flow, model=model,
                                process=process, timing=sc.timing_params, u_max=sc.controller.u_max,
                                replay=run["replay"], method=sc.make_method(), device=sc.plant.device, **extra)
    finally:
        process.close()
    M = min(len(res.t), n_loop)  # the resimulation stops early if its flow diverged (or its method raised)
    diffs = loop_differences(live, res, M)
    loop_bad = np.zeros(M, dtype=bool)
    for d in diffs.values():
        loop_bad[d] = True
    loop_first = int(np.argmax(loop_bad)) if loop_bad.any() else (M if M < n_loop else None)
    loop_identical = loop_first is None
    pme = plant_model_error(run, n, kernel)
    hx = live["have_x"][:M]
    err = np.zeros(M)
    if not recorded:
        err[hx] = np.max(np.abs(live["x"][:M][hx] - res.x[:M][hx]), axis=1)
    sym_diff = np.zeros(M, dtype=bool)
    sym_diff[diffs["symbols"]] = True
    E_diff = np.zeros(M, dtype=bool)
    E_diff[np.concatenate([diffs["E"], diffs["E_dec"]])] = True
    th_diff = np.zeros(M, dtype=bool)
    th_diff[diffs["theta"]] = True
    physical = sc.run.timing == "physical"
    tol = PHYSICAL_TOLERANCE if physical and not recorded else 0.0
    state_bad = err > tol
    if recorded:
        final_err = None
        max_err = 0.0  # the re-run's x_k are the recorded ones; the plant's own error is plant_model_error
        first = loop_first
    else:
        if run["x_final"] is not None and M == N:
            final_err = float(np.max(np.abs(run["x_final"] - res.x_final)))
        else:
            final_err = None
        bad = sym_diff | E_diff | th_diff | state_bad
        first = int(np.argmax(bad)) if bad.any() else (M if M < n else None)
        if first is None and through and res.method_fault_at != fault_at:  # raised at N in the run, not here
            first = N
        max_err = float(max(err.max(initial=0.0), final_err or 0.0))
    ok = is_reproduced(plant, loop_identical=loop_identical, first_divergence=first, final_error=final_err,
                       tolerance=tol)
    span = "" if n == N else f" (samples 0 to {n - 1} of {N}; testbed resimulate checks every sample)"
    if recorded and n_loop < n:
        span += f" (the plant's records end at sample {n_loop})"
    if through and ok:
        span += f" up to the method fault at sample {fault_at} (the method raised there in the resimulation too)"
    elif through and res.method_fault_at != fault_at:
        span += (f" (the method raised at sample {fault_at} in the run, "
                 + ("not" if res.method_fault is None else f"at sample {res.method_fault_at}")
                 + " in the resimulation)")
    which = [name for name, d in diffs.items() if len(d) and d[0] == loop_first]
    pm = "" if pme is None else f"; plant vs model: max e_k {pme['max']:.3g} at sample {pme['at']}"
    if recorded:
        verdict = ("reproduced: the loop is identical on the recorded plant" if ok else
                   f"NOT reproduced: the loop on the recorded plant differs from sample {loop_first}"
                   + (f" ({', '.join(which)})" if which else " (the re-run stopped)")) + pm
    else:
        verdict = ("reproduced bit for bit" if ok and max_err == 0.0 else
                   f"reproduced (state within {max_err:.2g} <= {tol:g})" if ok else
                   f"NOT reproduced: first divergence at sample {first}")
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
        "method_fault_at": fault_at,
        "symbols_differ_at": np.nonzero(sym_diff)[0][:50].tolist(),
        "state_differs_at": np.nonzero(state_bad)[0][:50].tolist(),
        "replayed": {"lost": int(np.sum(run["replay"].reason[:N] != 0)),
                     "withheld": int(run["replay"].withheld[:N].sum()),
                     "u_missing": int(run["replay"].u_missing[:N].sum()),
                     "delays_ns": None if run["replay"].delays is None else {
                         "min": int(run["replay"].delays[:N].min(initial=0)),
                         "max": int(run["replay"].delays[:N].max(initial=0))}},
        "plant": plant,
        "plant_why": why or f"--plant {plant}",
        "plant_line": f"re-run {'on the recorded plant' if recorded else 'on the model'} ({why or '--plant ' + plant})",
        "loop_identical": loop_identical,
        "loop_first_divergence": loop_first,
        "loop_differs_in": which,
        "plant_model_error": pme,
        "reproduced": bool(ok),
        "verdict": verdict + span,
    }


def resimulation(run: Any, *, plant: str = "auto",  # run: a Run (runs/run.py imports this module)
                 limit: int | None = None) -> dict:
    """The re-run of a recording's ``testbed.Run`` (``run_of_recording``) on the plant ``plant_choice`` picks:
    the dict of ``testbed resimulate --json`` (``plant``, ``loop_identical``, ``loop_first_divergence``,
    ``plant_model_error``, ``reproduced``, ...).  The conformance kit's ``loop_equals_replay`` and
    ``plant_follows_model`` read it.  Raises ``plants.refs.CodeNotTrusted`` when the scenario's code is
    not run (``Run.scenario.code_not_run()``): the re-run needs the method's and the model's code."""
    from plants.refs import CodeNotTrusted

    not_run = run.scenario.code_not_run()
    if not_run:
        raise CodeNotTrusted(f"{not_run[0]}: re-simulation needs it")
    rr = recorded_run(run, limit)
    mode, why = plant_choice(rr, plant)
    return compare(rr, limit=limit, plant=mode, why=why)

