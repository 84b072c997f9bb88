"""``testbed sweep``, ``testbed worst-attack``, ``testbed vulnerability``: the searches over attacks
(their flags, their text output; the computations are in ``testbed.analysis``)."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from ..common import cliargs, validate
from ..common.progress import Progress
from ..record.tracereader import read_recording_trace
from .analyze import (
    _add_method,
    _add_scenario,
    _executor,
    _fmt,
    _mismatch_line,
    _with_method,
    _write_json,
    plant_and_model,
    true_plant,
)


# ============================================================================ sweep
def add_arguments_sweep(p: argparse.ArgumentParser) -> None:
    _add_scenario(p)
    _add_method(p)
    p.add_argument("--grid", nargs=2, type=int, default=[21, 21], metavar=("NF", "ND"),
                   help="budget points along rho_F and rho_D (default 21 21)")
    p.add_argument("--rho-F-max", type=float, default=2.0, help="largest rho_F [1/s] (default 2)")
    p.add_argument("--rho-D-max", type=float, default=0.5, help="largest rho_D (default 0.5)")
    p.add_argument("--kappa-F", type=float, help="kappa_F (default: the scenario's budget, else 1)")
    p.add_argument("--kappa-D", type=float, help="kappa_D (default: the scenario's budget, else 0.2)")
    p.add_argument("--seeds", type=int, default=4, help="random schedules per budget point (default 4)")
    p.add_argument("--seed", type=int, default=0, help="first seed (default 0)")
    p.add_argument("--kinds", nargs="+", default=["random", "periodic", "greedy"],
                   choices=["random", "periodic", "greedy"], help="attackers (default all three)")
    p.add_argument("--threshold", type=float, default=0.0, help="greedy threshold (default 0: attack asap)")
    p.add_argument("--horizon", type=float, default=60.0, help="attacked seconds per run (default 60)")
    p.add_argument("--states", type=int, default=0,
                   help="extra initial states drawn uniformly with ||x0||_inf <= --state-radius (default 0)")
    p.add_argument("--state-radius", type=float, default=None,
                   help="radius of the extra initial states (default 3 ||x0||_inf)")
    cliargs.add_plot(p, "write the allowable-region figure over the empirical map")
    cliargs.add_json(p, "the sweep")
    cliargs.add_batch_options(p)


def main_sweep(args: argparse.Namespace) -> int:
    from .. import scenario
    from ..analysis import figures
    from ..analysis.region import allowable_region
    from ..analysis.summary import sweep_kappas, to_json
    from ..analysis.sweep import sweep
    from ..analysis.theorem1 import Loop, plain_certificate

    sc = _with_method(scenario.load(args.scenario, read_recording_trace=read_recording_trace), args, "testbed sweep")
    model, plant = sc.make_model(), true_plant(sc, "testbed sweep")
    kF0, kD0 = sweep_kappas(sc)
    kF = kF0 if args.kappa_F is None else args.kappa_F
    kD = kD0 if args.kappa_D is None else args.kappa_D
    if not 0 <= args.rho_D_max < 1:
        print("testbed sweep: --rho-D-max must be in [0, 1)", file=sys.stderr)
        return 2
    states = [sc.x0]
    if args.states > 0:
        r = args.state_radius or 3.0 * float(np.max(np.abs(sc.x0)))
        rng = np.random.default_rng(args.seed)
        states.extend(rng.uniform(-r, r, (args.states, plant.n)))
    X0 = np.array(states)
    rF = np.linspace(0.0, args.rho_F_max, args.grid[0])
    rD = np.linspace(0.0, args.rho_D_max, args.grid[1])
    with _executor(args) as ex:
        sw = sweep(plant, sc.K, sc.quantizer, X0, rF, rD, kappa_F=kF, kappa_D=kD, seeds=args.seeds, seed=args.seed,
                   horizon=args.horizon, kinds=tuple(args.kinds), threshold=args.threshold,
                   tol=sc.run.converge_tol, flow=sc.flow, progress=Progress("sweep", not args.no_progress),
                   executor=ex, model=model)
        par = ex.describe()
    loop = Loop.from_scenario(sc)
    regions = {rule: allowable_region(loop, rule) for rule in ("paper", "tight")}
    plain = plain_certificate(loop)
    theory: dict[str, Any] = {"rho_D_max": regions["paper"].rho_D_max, "rho_F_max": regions["paper"].rho_F_max,
              "tight": {"rho_D_max": regions["tight"].rho_D_max, "rho_F_max": regions["tight"].rho_F_max},
              "plain": {"rho_D_max": plain.rho_D_max, "rho_F_max": plain.rho_F_max}}
    d = sw.to_dict()
    d["theory"] = theory
    d["scenario"] = sc.name
    d.update(plant_and_model(sc))
    d["parallel"] = par
    # budget points where the theorem holds but some run failed (the theorem is local: x0 may be too large)
    th = regions["tight"].holds(rF[:, None], rD[None, :]) | regions["paper"].holds(rF[:, None], rD[None, :])
    d["theorem_holds_but_failed"] = int(np.sum(th & ~sw.all_converged()))
    d["theorem_holds_points"] = int(np.sum(th))
    if args.plot:
        figures.plot_allowable_region(args.plot, regions=regions, plain=plain, sweep=sw, size=args.figsize,
                                      title=f"{sc.name}: Theorem 1 and the empirical map "
                                            f"($\\kappa_F$ = {kF:g}, $\\kappa_D$ = {kD:g})")
        d["figure"] = args.plot
    if args.json:
        _write_json({**to_json(d), "method": sc.method.name})
    else:
        print(f"scenario {sc.name}: {len(rF)} x {len(rD)} budgets (rho_F <= {args.rho_F_max:g}, rho_D <= "
              f"{args.rho_D_max:g}), kappa_F={kF:g}, kappa_D={kD:g}, {len(X0)} initial state(s), "
              f"kinds {', '.join(sw.kinds)}, {args.seeds} random seeds, horizon {args.horizon:g} s")
        if (mismatch := _mismatch_line(d)):
            print(mismatch + ": the runs integrate the true plant, the quantizer predicts with the model")
        print(f"  {sw.runs} runs, {sw.traj_steps} trajectory-steps in {sw.wall:.2f} s = {sw.rate:.3g} per s")
        w = sw.worst()
        print(f"  budget points where every run converged: {int(np.sum(sw.all_converged()))} of {w.size}")
        for k in sw.kinds:
            eb = sw.empirical_boundary(k)
            print(f"  {k:8s}: converged fraction {np.nanmean(sw.converged[k]):.3f}, escaped "
                  f"{np.nanmean(sw.escaped[k]):.3f}; all converge up to rho_F = {_fmt(float(eb[0]))} at rho_D = 0")
        print(f"  Theorem 1: rho_D_max = {theory['rho_D_max']:.4f}, rho_F_max = {theory['rho_F_max']:.4f} "
              f"(tight mu: {theory['tight']['rho_D_max']:.4f}, {theory['tight']['rho_F_max']:.4f}); "
              f"{d['theorem_holds_but_failed']} of {d['theorem_holds_points']} grid budgets inside the theorem "
              "had a failing run")
        if args.plot:
            print(f"  wrote {args.plot}")
    return 0


# ============================================================================ worst-attack
def _add_search(p) -> None:
    p.add_argument("--attacks", type=int, default=1, metavar="N",
                   help="at most N attack intervals, back to back where that saves duration (default 1); the "
                        "answer is given for every n = 1..N (the front), exact where proven")
    p.add_argument("--max-length", type=float, metavar="SECONDS",
                   help="most lost samples tried, as the duration of one attack losing them (default: the "
                        "whole run)")
    p.add_argument("--beam", type=int, default=16,
                   help="beam width of the search beyond the enumeration, for --attacks >= 2 (default 16)")
    p.add_argument("--exhaustive-limit", type=int, default=100_000, metavar="K",
                   help="schedules enumerated per number of attacks >= 2 before the beam search takes over "
                        "(default 100000; more proves more)")


def _search_args(args, sc) -> dict:
    from ..common.errors import BadInput

    validate.flag("--attacks", args.attacks, integer=True, lo=1)
    validate.flag("--beam", args.beam, integer=True, lo=1)
    validate.flag("--exhaustive-limit", args.exhaustive_limit, integer=True, lo=0)
    max_len = None
    if args.max_length is not None:
        if not (math.isfinite(args.max_length) and args.max_length >= 0):
            raise BadInput(f"--max-length must be >= 0 seconds, got {args.max_length}")
        max_len = int(round(args.max_length / sc.T)) + 1
    return {"attacks": args.attacks, "max_len": max_len, "beam": args.beam,
            "exhaustive_limit": args.exhaustive_limit}


def add_arguments_worst_attack(p: argparse.ArgumentParser) -> None:
    _add_scenario(p)
    _add_method(p)
    _add_search(p)
    p.add_argument("--x0", nargs="+", type=float, metavar="X",
                   help="initial state (default: the scenario's); E0 = max(scenario E0, ||x0||_inf)")
    p.add_argument("--no-greedy", action="store_true",
                   help="skip the greedy online attacker's least budget (reported for comparison)")
    p.add_argument("--scenario-out", metavar="PATH.toml",
                   help="write the answer as a scenario (x0, E0, the attack intervals, the simulated duration) "
                        "that testbed simulate and testbed run accept; exit 1 and nothing written when no "
                        "schedule escapes")
    p.add_argument("--force", action="store_true", help="replace an existing --scenario-out file")
    cliargs.add_json(p, "the result (intervals, total_duration, samples_lost, escaped, exact, front, proof, "
                        "greedy, ...)")
    cliargs.add_batch_options(p)


def main_worst_attack(args: argparse.Namespace) -> int:
    from .. import scenario
    from ..analysis.worst import Loop, worst_attack
    from ..common.errors import BadInput

    sc = _with_method(scenario.load(args.scenario, read_recording_trace=read_recording_trace), args, "testbed worst-attack")
    kw = _search_args(args, sc)
    plant = true_plant(sc, "testbed worst-attack")
    x0 = sc.x0 if args.x0 is None else np.asarray(args.x0, dtype=float)
    if x0.shape != (plant.n,) or not np.all(np.isfinite(x0)):
        raise BadInput(f"--x0 needs {plant.n} finite numbers, got {args.x0}")
    sc_out = None
    if args.scenario_out:
        sc_out = Path(args.scenario_out)
        if sc_out.exists() and not args.force:
            raise BadInput(f"{sc_out} exists (--force replaces it)")
        if not sc_out.parent.is_dir():
            raise BadInput(f"--scenario-out: no folder {sc_out.parent}")
    with _executor(args) as ex:
        w = worst_attack(Loop.from_scenario(sc), x0, greedy=not args.no_greedy, executor=ex,
                         progress=Progress("worst attack", not args.no_progress), **kw)
        out = {"scenario": sc.name, **plant_and_model(sc), **w.to_dict(), "parallel": ex.describe()}
    code = 0
    if sc_out is not None:
        if out["escaped"]:
            out["scenario_out"] = _write_scenario_out(sc, out, sc_out)
        else:
            out["scenario_out"] = None
            code = 1
            print(f"testbed worst-attack: no schedule escapes: {sc_out} not written", file=sys.stderr)
    if args.json:
        _write_json({**out, "method": sc.method.name})
        return code
    print(f"scenario {sc.name}: x0 = {out['x0']}, E0 = {out['E0']:g}, {out['n_steps']} samples of "
          f"T = {out['T']:g} s, at most {out['attacks']} attack(s)")
    if (mismatch := _mismatch_line(out)):
        print(mismatch + ": the runs integrate the true plant, the quantizer predicts with the model")
    if out["unattacked_escapes"]:
        print("  the quantized loop escapes without any attack")
    else:
        for f in out["front"]:
            if f["escaped"]:
                print(f"  at most {f['attacks']} attack(s): {f['samples_lost']} lost samples, least duration "
                      f"{f['total_duration']:g} s, intervals {f['intervals']} (start, length in s; "
                      f"{'exact' if f['exact'] else 'not proven minimal'})")
            else:
                print(f"  at most {f['attacks']} attack(s): no schedule escapes (up to "
                      f"{out['max_length_samples']} lost samples; "
                      f"{'every schedule simulated' if f['exact'] else 'not every schedule simulated'})")
        for p in out["proof"]:
            print(f"  proven for at most {p['attacks']} attack(s): no schedule losing fewer than "
                  f"{p['samples_lost_below']} samples in {p['horizon_samples']} escapes")
    c = out["escape_criterion"]
    print(f"  escape: {c['kind']} for {c['horizon_s']:g} s (x_tol {c['x_tol']:g}, E_tol {c['E_tol']:g})")
    g = out.get("greedy")
    if g:
        if g["escaped"]:
            print(f"  greedy attacker: escapes with kappa_D = {g['kappa_D']:g} s (threshold {g['threshold']:g}, "
                  f"score {g['score']}), intervals {g['intervals']}, total duration {g['total_duration']:g} s")
        else:
            print("  greedy attacker: no escape with any duration budget")
    print(f"  {out['candidates']} schedules, {out['traj_steps']} trajectory-steps in {out['wall_s']:.2f} s "
          f"({out['parallel']['kind']}, {out['parallel']['workers']} workers)")
    if out.get("scenario_out"):
        print(f"  wrote {out['scenario_out']} (testbed simulate / testbed run it)")
    return code


def _write_scenario_out(sc, out: dict, path: Path) -> str:
    """The answer of ``worst-attack`` as a scenario file (``scenariowrite.with_attack``), checked by loading it."""
    import os
    import tempfile

    from .. import scenario
    from ..scenario import write as scenariowrite

    iv = out["intervals"]
    desc = (f"testbed worst-attack {sc.name}: at most {out['attacks']} attack(s) from x0 = {out['x0']}, "
            f"{out['samples_lost']} lost samples, total duration {out['total_duration']:g} s")
    budget = {"kappa_F": len(iv), "rho_F": 0.0, "kappa_D": out["total_duration"], "rho_D": 0.0} if iv else None
    text = scenariowrite.with_attack(sc, x0=out["x0"], E0=out["E0"], intervals=iv, duration=out["horizon"],
                                name=f"{sc.name}-worst-attack", description=desc, out_dir=path.parent,
                                budget=budget)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".worst-", suffix=".toml")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        scenario.load(tmp)  # what testbed simulate will read: it must load
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return str(path)


# ============================================================================ vulnerability
def add_arguments_vulnerability(p: argparse.ArgumentParser) -> None:
    _add_scenario(p)
    _add_method(p)
    p.add_argument("--grid", type=int, default=41, help="grid points per axis (default 41)")
    p.add_argument("--window", nargs=2, type=float, metavar=("WX", "WY"),
                   help="half-widths of the window (default per plant, as testbed roa)")
    p.add_argument("--dims", nargs=2, type=int, metavar=("I", "J"), help="gridded coordinates (default 0 1)")
    _add_search(p)
    p.add_argument("--show", choices=["samples", "duration"], default="duration",
                   help="what the map shows: the fewest lost samples S* with which at most --attacks attacks "
                        "escape, or their least total duration (S* - min(N, S*)) T (default)")
    cliargs.add_plot(p, "draw the heat map (--show per state, the region's outline, Theorem 2's "
                        "delta-ball)")
    cliargs.add_json(p, "the map (least duration per grid state, counts, delta)")
    cliargs.add_batch_options(p)


def main_vulnerability(args: argparse.Namespace) -> int:
    from .. import scenario
    from ..analysis.roa import nominal_roa
    from ..analysis.summary import analyze
    from ..analysis.vulnerability import vulnerability_map
    from ..analysis.worst import Loop
    from ..common.errors import BadInput

    sc = _with_method(scenario.load(args.scenario, read_recording_trace=read_recording_trace), args, "testbed vulnerability")
    kw = _search_args(args, sc)
    if not 2 <= args.grid <= 1001:
        raise BadInput(f"--grid must be in 2..1001, got {args.grid}")
    true_plant(sc, "testbed vulnerability")
    plant = sc.make_model()  # the nominal region is the model's loop; the attacks run on the true plant
    if args.dims is not None and (len(set(args.dims)) != 2 or not all(0 <= d < plant.n for d in args.dims)):
        raise BadInput(f"--dims needs two different coordinates in 0..{plant.n - 1}, got {args.dims}")
    delta = analyze(sc)["delta"]
    with _executor(args) as ex:
        roa = nominal_roa(plant, sc.K, sc.T, grid=args.grid, window=args.window, dims=args.dims,
                          tol=sc.run.converge_tol, flow=sc.flow,
                          progress=Progress("region of attraction", not args.no_progress), executor=ex)
        vm = vulnerability_map(Loop.from_scenario(sc), roa, delta=delta, executor=ex,
                               progress=Progress("least attack per state", not args.no_progress), **kw)
        out = {"scenario": sc.name, **plant_and_model(sc), **vm.to_dict(), "show": args.show,
               "roa_inside_digest": roa.digest, "parallel": ex.describe()}
    if args.plot:
        from ..analysis import figures

        what = "fewest lost samples" if args.show == "samples" else "least DoS duration"
        figures.plot_vulnerability(vm, roa, args.plot, x0=sc.x0, show=args.show, size=args.figsize,
                                   title=f"{sc.name}: {what} that drives the loop out "
                                         f"(at most {vm.attacks} attack{'s' if vm.attacks > 1 else ''})")
        out["figure"] = str(args.plot)
    if args.json:
        from ..analysis.summary import to_json

        _write_json({**to_json(out), "method": sc.method.name})
        return 0
    print(f"scenario {sc.name}: {out['states_in_region']} states of the nominal region of attraction on a "
          f"{args.grid} x {args.grid} grid, at most {out['attacks']} attack(s), {out['n_steps']} samples")
    if (mismatch := _mismatch_line(out)):
        print(mismatch + ": the region is the model's, the attacks run on the true plant")
    print(f"  {out['escape_unattacked']} escape without any attack; {out['no_escape_found']} resist every "
          "schedule tried")
    ex_note = 'exact' if out['all_exact'] else f"{out['states_exact']} of {out['states_in_region']} proven minimal"
    if args.show == "samples":
        print(f"  fewest lost samples over the region: {_fmt(out['least_samples'])}, median "
              f"{_fmt(out['median_samples'])}, largest {_fmt(out['largest_samples'])} ({ex_note})")
    else:
        print(f"  least duration over the region: {_fmt(out['least_duration'])} s, median "
              f"{_fmt(out['median_duration'])} s, largest {_fmt(out['largest_duration'])} s ({ex_note})")
    print(f"  Theorem 2's delta = {_fmt(delta)}")
    print(f"  {out['candidates']} schedules, {out['traj_steps']} trajectory-steps in {out['wall_s']:.2f} s "
          f"({out['parallel']['kind']}, {out['parallel']['workers']} workers)")
    if args.plot:
        print(f"  wrote {args.plot}")
    return 0
