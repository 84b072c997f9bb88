"""``testbed analyze`` and ``testbed roa`` (and the options and output helpers that
``testbed.commands.search`` shares: sweep, worst-attack, vulnerability).

    testbed analyze SCENARIO [--json] [--plot PATH.png] [--full] [--gamma G] [--budget KF RF KD RD]
    testbed roa SCENARIO [--grid N] [--plot PATH.png] [--json] [--vulnerable] [--budget ...]
    testbed sweep SCENARIO [--grid NF ND] [--rho-F-max R] [--rho-D-max R] [--seeds S] [--plot PATH.png] [--json]
    testbed worst-attack SCENARIO [--attacks N] [--x0 X1 X2 ...] [--scenario-out PATH [--force]] [--json]
    testbed vulnerability SCENARIO [--grid N] [--attacks N] [--show samples|duration] [--plot PATH.png] [--json]

Every command that runs batches takes --workers N (default: every core) and --scheduler tcp://HOST:PORT
(a Dask cluster); the results do not depend on either (testbed.analysis.parallel).

The figures and numbers of docs/analysis.md come from ``python docs/make_numbers.py`` (see there)."""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..common import cliargs
from ..common.progress import Progress
from ..record.tracereader import read_recording_trace

if TYPE_CHECKING:
    from plants.base import Plant

    from ..scenario import Scenario


# ============================================================================ shared options
def _add_scenario(p):
    p.add_argument("scenario", help="scenario file (.toml) or bundled name (see 'testbed scenarios')")


def _add_method(p: argparse.ArgumentParser) -> None:
    p.add_argument("--method", metavar="NAME",
                   help="the coding-and-control method to analyse instead of the scenario's [method] (a bundled "
                        "one: the batch kernel runs it; testbed methods lists them)")


def _with_method(sc, args, prog: str):
    """``sc`` with ``--method`` swapped in (a note on stderr for the keys it ignores), its quantizer carrying
    the method for the batch kernel; a method without a kernel (a user's) is one clear line."""
    import dataclasses

    from .. import scenario
    from ..common.errors import BadInput
    from ..methods.base import MethodQuantizerParams

    note_not_modelled(sc, prog)
    name = getattr(args, "method", None)
    if name:
        sc = scenario.with_overrides(sc, {"method": name})
        if sc.method_note:
            print(f"{prog}: {sc.method_note}", file=sys.stderr)
    m = sc.make_method()
    if sc.method.name == "paper" or (prog == "testbed roa" and not getattr(args, "vulnerable", False)):
        return sc   # the nominal region of attraction has no method
    if m.kernel_code(sc.quantizer) is None:
        raise BadInput(f"method {sc.method.name!r} has no batch kernel: {prog.split()[-1]} runs the bundled methods "
                       "only (a user's method runs in testbed simulate, run and versus)")
    qp = MethodQuantizerParams(**{f.name: getattr(sc.quantizer, f.name) for f in dataclasses.fields(sc.quantizer)},
                               method=m)
    return dataclasses.replace(sc, quantizer=qp)


def _add_budget(p, help_=None):
    p.add_argument("--budget", nargs=4, type=float, metavar=("KAPPA_F", "RHO_F", "KAPPA_D", "RHO_D"),
                   help=help_ or "DoS budget of Assumptions 3 and 4 (default: the scenario's, see README)")


def _write_json(obj) -> None:
    json.dump(obj, sys.stdout, indent=1, allow_nan=False)
    sys.stdout.write("\n")


def true_plant(sc: Scenario, what: str) -> Plant:
    """The true plant ([plant]) for the batch simulator, or one line (exit 2) when it is an FMU.

    The experiments (sweeps, vulnerable states, the worst attack, escape searches) run
    the true plant with the model's predictions; the batch kernel integrates equation (1)
    plants only, so an FMU true plant cannot run there.
    """
    from ..common.errors import BadInput

    if sc.plant.fmu is not None:
        assert sc.model is not None  # an FMU plant needs a [model]
        raise BadInput(f"the true plant is the FMU {Path(sc.plant.fmu.path).name}, which the batch simulator of "
                       f"{what} cannot run (it integrates equation (1) plants only): run {what} on a copy of the "
                       f"scenario whose [plant] is its [model] (name = \"{sc.model.name}\"), or the FMU itself with "
                       "testbed simulate or testbed run")
    return sc.make_plant()


def plant_and_model(sc: Scenario) -> dict:
    """``plant``, ``model`` and their parameters for the JSON outputs (``testbed.sim.batch.plant_and_model``),
    and ``not_modelled``: what of the scenario the analysis leaves out (:func:`not_modelled`)."""
    from ..sim.batch import plant_and_model as names

    return {**names(sc), "not_modelled": not_modelled(sc)}


def not_modelled(sc: Scenario) -> list[str]:
    """The tables of ``sc`` that the analysis leaves out: it runs the paper's loop (Assumptions 3 and 4: the
    attacker is the only cause of loss; the plant's state is measured and its input applied exactly), so a
    ``[network]`` channel and a device around the plant (``[plant.sensor]``, ``[plant.actuator]``,
    ``[plant.disturbance]``) are not in it.  ``testbed simulate`` and ``testbed run`` model them."""
    from ..loop.device import TABLES

    out = ["[network]"] if sc.network is not None else []
    dev = sc.plant.device
    return out + ([f"[plant.{t}]" for t in TABLES if getattr(dev, t) is not None] if dev is not None else [])


def note_not_modelled(sc: Scenario, prog: str) -> None:
    """One line on stderr when the analysis leaves part of the scenario out (:func:`not_modelled`)."""
    left = not_modelled(sc)
    if left:
        print(f"{prog}: note: the analysis runs the paper's loop (the attacker the only loss, the plant measured and "
              f"driven exactly); it leaves out this scenario's {', '.join(left)}, which testbed simulate and "
              "testbed run model", file=sys.stderr)


def _mismatch_line(d: dict) -> str | None:
    """'  true plant P {...}, model M {...}' when the true plant is not the model, else None."""
    if (d.get("plant"), d.get("plant_params")) == (d.get("model"), d.get("model_params")):
        return None
    return f"  true plant {d['plant']} {d['plant_params']}, model {d['model']} {d['model_params']}"


def _fmt(v, spec=".4g"):
    if v is None:
        return "n/a"
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    return format(v, spec)


# ============================================================================ analyze
def add_arguments_analyze(p: argparse.ArgumentParser) -> None:
    _add_scenario(p)
    cliargs.add_json(p, "the analysis (Theorems 1 and 2)")
    p.add_argument("--plot", metavar="PATH.png",
                   help="draw the allowable DoS region (Theorem 1, with the empirical map under --full) into PATH.png "
                        "and the other figures beside it as PATH-time-series.png, PATH-phase-portrait.png, "
                        "PATH-delta.png (and PATH-vulnerable.png under --full); .pdf or .svg for those formats; "
                        "a folder instead writes them there as <scenario>-<figure>.png")
    cliargs.add_figsize(p)
    p.add_argument("--full", action="store_true",
                   help="also the 201 x 201 region of attraction, the budget sweep and the vulnerable states "
                        "(figures 3 and 4 with the experiment; about a minute)")
    p.add_argument("--gamma", default="auto",
                   help="gamma of Lemma 2, or 'auto' to maximize the E0 bound (default)")
    p.add_argument("--rule", choices=["paper", "tight"], default="paper",
                   help="mu constants of the headline certificate and Theorem 2: 'paper' = (mu0), (mu1) "
                        "(default), 'tight' = smallest constants of (mu)")
    p.add_argument("--share", type=float, default=0.5,
                   help="part of Theorem 1's decay margin given to nonlinearity and quantization (default 0.5)")
    _add_budget(p)
    p.add_argument("--escape-x0", nargs="+", metavar="X",
                   help="also draw, in the phase portrait, a trajectory under the scenario's attacks from this "
                        "initial state, or 'auto': the first state along the ray through the scenario's x0 from "
                        "which it escapes (default: only the scenario's own trajectory)")
    cliargs.add_batch_options(p)


def main_analyze(args: argparse.Namespace) -> int:
    from .. import scenario
    from ..analysis.summary import analyze, to_json

    sc = scenario.load(args.scenario, read_recording_trace=read_recording_trace)
    note_not_modelled(sc, "testbed analyze")
    if args.full or args.plot:
        true_plant(sc, "testbed analyze --full / --plot")
    if args.plot:
        figure_paths(args.plot, sc.name, create=False)  # a bad --plot fails before the work
    args.escape_x0 = _escape_arg(args.escape_x0, sc)
    gamma = args.gamma if args.gamma == "auto" else float(args.gamma)
    res = analyze(sc, budget=args.budget, gamma=gamma, share=args.share, rule=args.rule)
    res["paper_example"] = is_paper_example(sc)
    res["not_modelled"] = not_modelled(sc)
    extra = {}
    if args.full:
        with _executor(args) as ex:
            extra = _full(sc, res, args, ex)
            extra["parallel"] = ex.describe()
    if args.plot:
        res["figures"] = _analyze_plots(sc, res, extra, Path(args.plot), args)
    for k, v in extra.items():
        if not k.startswith("_"):
            res[k] = v
    if args.json:
        _write_json(to_json(res))
    else:
        _print_analysis(res)
        for k in ("roa", "sweep", "sweep_zoom", "vulnerable", "vulnerable_baseline"):
            if k in res:
                print(f"  {k}: " + ", ".join(f"{a}={_fmt(b) if isinstance(b, float) else b}"
                                             for a, b in res[k].items()
                                             if isinstance(b, (int, float)) and a in (
                                                 "fraction_inside", "area", "wall_s", "traj_steps_per_s", "runs",
                                                 "fraction_vulnerable", "escaped", "states_in_region",
                                                 "empirical_rho_D_max_at_rho_F_0",
                                                 "empirical_rho_F_max_at_rho_D_0")))
        if "figures" in res:
            if res.get("escape_note"):
                print(f"  {res['escape_note']}")
            for f in res["figures"]:
                print(f"  wrote {f}")
    return 0


def _print_analysis(r: dict) -> None:
    b = r["budget"]
    print(f"scenario {r['scenario']}: plant {r['plant']} (n={r['n']}), T={r['T']}, M={r['M']}, L={r['L']}, "
          f"Lambda={r['Lambda']:.4f}, K={r['K']}")
    mismatch = _mismatch_line(r)
    if mismatch:
        print(mismatch + ": the theorems are the model's")
    print(f"  rho(A~+B~K) = {r['rho_Phi0']:.4f}, rho(A~) = {r['rho_Phi1']:.4f}")
    t1 = r["theorem1"]
    print("Theorem 1 (stability)")
    pl = t1["plain"]
    print(f"  plain choice (dlyap with I): phi0={pl['phi0']:.4f} phi1={pl['phi1']:.4f} mu0=mu1={pl['mu0']:.4g} "
          f"-> rho_D_max={pl['rho_D_max']:.4f}, rho_F_max={pl['rho_F_max']:.4f}")
    print(f"  optimized (min cond P, envelope over phi): rho_D_max={t1['paper']['rho_D_max']:.4f}, "
          f"rho_F_max={t1['paper']['rho_F_max']:.4f}, area={t1['paper']['area']:.3g}")
    if "tight" in t1:
        print(f"  optimized, smallest mu of (mu):            rho_D_max={t1['tight']['rho_D_max']:.4f}, "
              f"rho_F_max={t1['tight']['rho_F_max']:.4f}, area={t1['tight']['area']:.3g}")
    print(f"  certificate ({t1['choice']}): phi0={r['phi0']:.6g} phi1={r['phi1']:.6g} mu0={r['mu0']:.4g} "
          f"mu1={r['mu1']:.4g} nu0={r['nu0']:.4g} nu1={r['nu1']:.4g}")
    print(f"  budget ({r['budget_source']}): kappa_F={b['kappa_F']:g} rho_F={b['rho_F']:g} "
          f"kappa_D={b['kappa_D']:g} rho_D={b['rho_D']:g}")
    by = r["theorem1_holds_by_rule"]
    names = {"paper": "the paper's mu constants (mu0), (mu1)", "tight": "the smallest mu of (mu)"}
    held = [names.get(k, k) for k, v in by.items() if v]
    failed = [names.get(k, k) for k, v in by.items() if not v]
    if not failed:
        verdict = "holds"
    elif not held:
        verdict = "fails"
    else:
        verdict = f"holds with {' and '.join(held)}, fails with {' and '.join(failed)}"
    print(f"  Theorem 1's condition at this budget {verdict} (at its long-run rates rho_F, rho_D; its intercepts "
          f"kappa_F, kappa_D take a finite run's excess, which testbed report's realized rates include; "
          f"the headline certificate, rule {r['rule']}: {'holds' if r['theorem1_holds'] else 'fails'})")
    t2 = r["theorem2"]
    print(f"Theorem 2 (convergence), gamma={r['gamma']:.4g}, for the {r['theorem2_budget']}")
    print(f"  c0={t2['c0']:.4g} c1={t2['c1']:.4g} gamma0={t2['gamma0']:.4g} gamma1={t2['gamma1']:.4g} "
          f"d={_fmt(t2['d'])} delta={_fmt(r['delta'])}")
    print(f"  eps={t2['eps']:.4g} eta0={t2['eta0']:.4g} eta1={t2['eta1']:.4g} alpha={t2['alpha']:.4g} "
          f"beta={t2['beta']:.4g} omega0={t2['omega0']:.6g} omega1={t2['omega1']:.6g} omega={t2['omega']:.6g}")
    if not r["theorem2_holds"]:
        print("  Theorem 2's conditions (omega0 < 1, omega < 1, delta > 0) fail: it guarantees nothing here")
    elif r["E0_within_bound"]:
        print(f"  Theorem 2 guarantees convergence for E0 <= {_fmt(r['E0_bound'])}: it covers this scenario "
              f"(E0 = {r['E0']:g})")
    else:
        print(f"  Theorem 2's conditions hold, and guarantee convergence for E0 <= {_fmt(r['E0_bound'])}; this "
              f"scenario's E0 = {r['E0']:g} is above that bound, so the theorem does not cover it (a sufficient "
              "condition: the run may still converge, see testbed simulate)")
    if r.get("paper_example"):
        print(f"  the paper's delta = {PAPER_DELTA:g} (Section V) is gamma = {_fmt(r['gamma_for_paper_delta'])} here")


class _executor:
    """``with _executor(args) as ex``: the executor of --workers / --scheduler, closed afterwards."""

    def __init__(self, args):
        from ..analysis.parallel import Executor

        self.ex = Executor(getattr(args, "workers", None), getattr(args, "scheduler", None))

    def __enter__(self):
        return self.ex

    def __exit__(self, *exc):
        self.ex.close()
        return False


def _full(sc, res, args, ex=None) -> dict:
    """Region of attraction (201 x 201), sweep (21 x 21) and vulnerable states for --full."""
    from ..analysis.roa import nominal_roa
    from ..analysis.summary import sweep_kappas
    from ..analysis.sweep import sweep, vulnerable_states

    model, plant = sc.make_model(), true_plant(sc, "testbed analyze --full")
    out: dict[str, Any] = {}
    roa = nominal_roa(model, sc.K, sc.T, grid=201, horizon=30.0, tol=sc.run.converge_tol, flow=sc.flow,
                      progress=Progress("region of attraction", not args.no_progress), executor=ex)
    out["_roa"] = roa
    out["roa"] = roa.to_dict()
    kF, kD = sweep_kappas(sc)
    rF = np.linspace(0.0, 2.0, 21)
    rD = np.linspace(0.0, 0.5, 21)
    sw = sweep(plant, sc.K, sc.quantizer, sc.x0, rF, rD, kappa_F=kF, kappa_D=kD, seeds=4, horizon=60.0,
               tol=sc.run.converge_tol, flow=sc.flow, progress=Progress("sweep", not args.no_progress), executor=ex,
               model=model)
    out["_sweep"] = sw
    out["sweep"] = _sweep_summary(sw, res)
    t1 = res["theorem1"]
    hiF = 1.15 * max(t1.get("tight", t1["paper"])["rho_F_max"], t1["paper"]["rho_F_max"])
    hiD = 1.15 * t1["paper"]["rho_D_max"]
    swz = sweep(plant, sc.K, sc.quantizer, sc.x0, np.linspace(0.0, hiF, 12), np.linspace(0.0, hiD, 12),
                kappa_F=kF, kappa_D=kD, seeds=4, horizon=60.0, tol=sc.run.converge_tol, flow=sc.flow,
                progress=Progress("sweep (zoom)", not args.no_progress), executor=ex, model=model)
    out["_sweep_zoom"] = swz
    out["sweep_zoom"] = _sweep_summary(swz, res)
    t1 = res["theorem1"]
    reg = t1.get("tight") or t1["paper"]
    vb = _vulnerable_budget(sc, reg["rho_F_max"], reg["rho_D_max"])
    vu = vulnerable_states(plant, sc.K, sc.quantizer, vb, roa, stride=2, horizon=30.0, tol=sc.run.converge_tol,
                           flow=sc.flow, progress=Progress("vulnerable states", not args.no_progress), executor=ex,
                           model=model)
    out["_vulnerable"] = vu
    out["vulnerable"] = vu.to_dict()
    base = vulnerable_states(plant, sc.K, sc.quantizer, (0.0, 0.0, 0.0, 0.0), roa, stride=2, horizon=30.0,
                             tol=sc.run.converge_tol, flow=sc.flow, executor=ex, model=model)
    out["_vulnerable_baseline"] = base
    out["vulnerable_baseline"] = base.to_dict()
    return out


def _vulnerable_budget(sc, rho_F_max: float, rho_D_max: float) -> tuple:
    """Budget of the vulnerable-state map: the scenario's explicit budget, else DEFAULT_KAPPAS
    with rates at a quarter of Theorem 1's intercepts (well inside the allowable region)."""
    from ..analysis.summary import DEFAULT_KAPPAS

    if sc.attack.budget is not None:
        return tuple(sc.attack.budget)
    return (DEFAULT_KAPPAS[0], round(rho_F_max / 4, 4), DEFAULT_KAPPAS[1], round(rho_D_max / 4, 4))


def _sweep_summary(sw, res=None) -> dict:
    d = sw.to_dict()
    if res is not None:
        eb = sw.empirical_boundary()
        d["theory"] = {"rho_D_max": res["rho_D_max"], "rho_F_max": res["rho_F_max"]}
        if "tight" in res["theorem1"]:
            d["theory"]["tight"] = {k: res["theorem1"]["tight"][k] for k in ("rho_D_max", "rho_F_max")}
        ok0 = sw.all_converged()[0]
        bad0 = np.flatnonzero(~ok0)
        last = (bad0[0] - 1 if bad0.size else len(ok0) - 1)
        # largest rho_D such that every run converged for all rho_D' <= rho_D at rho_F = 0
        d["empirical_rho_D_max_at_rho_F_0"] = float(sw.rho_D[last]) if last >= 0 else None
        d["empirical_rho_F_max_at_rho_D_0"] = None if not np.isfinite(eb[0]) else float(eb[0])
    return d


def _escape_arg(v, sc):
    """--escape-x0: None, "auto" or n floats (``BadInput`` otherwise)."""
    from ..common.errors import BadInput

    if not v:
        return None
    if v == ["auto"]:
        return "auto"
    try:
        x = np.array([float(a) for a in v])
    except ValueError:
        raise BadInput(f"--escape-x0 takes 'auto' or {len(sc.x0)} numbers, got {' '.join(v)}") from None
    if x.shape != sc.x0.shape or not np.all(np.isfinite(x)):
        raise BadInput(f"--escape-x0 takes 'auto' or {len(sc.x0)} finite numbers, got {' '.join(v)}")
    return x


def figure_paths(plot: str | Path, scenario_name: str, *, create: bool = True) -> Callable[[str], Path]:
    """``--plot`` of analyze: a figure path (the allowable region there, the rest beside it, in its format)
    or a folder (``<scenario>-<figure>.png`` there); an unknown extension is a ``BadInput``."""
    from ..common.errors import BadInput
    from ..common.figstyle import FORMATS

    plot = Path(plot)
    ext = plot.suffix.lower()
    if ext in FORMATS:
        if create:
            plot.parent.mkdir(parents=True, exist_ok=True)
        return lambda fig: plot if fig == "allowable-region" else plot.with_name(f"{plot.stem}-{fig}{plot.suffix}")
    if ext and not plot.is_dir():
        raise BadInput(f"--plot {plot}: a figure path ends in {', '.join(FORMATS)}; a folder has no extension")
    if create:
        plot.mkdir(parents=True, exist_ok=True)
    return lambda fig: plot / f"{scenario_name}-{fig}.png"


def _analyze_plots(sc, res, extra, plot: Path, args) -> list[str]:
    from ..analysis import figures
    from ..analysis.roa import nominal_roa
    from ..analysis.summary import find_escape, trajectory
    from ..sim.batch import simulate_scenario

    path = figure_paths(plot, sc.name)
    files = []
    sim = simulate_scenario(sc)
    ivs = None
    if not sc.attack.online:
        ivs = sc.attack.schedule(sc.T, sc.run.duration).intervals
    size = args.figsize
    files.append(figures.plot_time_series(sim, path("time-series"), intervals=ivs, title=figures.figure_title(sc),
                                          size=size))
    roa = extra.get("_roa")
    if roa is None:
        plant = sc.make_model()
        roa = nominal_roa(plant, sc.K, sc.T, grid=101, horizon=30.0, tol=sc.run.converge_tol, flow=sc.flow,
                          progress=Progress("region of attraction", not args.no_progress))
    trajs = [(f"the scenario's run from $x_0$ = {np.round(sc.x0, 3).tolist()}", sim.x, None)]
    esc: tuple[float | None, Any] | None = None
    if isinstance(args.escape_x0, str):  # "auto"
        esc = find_escape(sc)
        if esc is None:
            res["escape_x0"] = None
            res["escape_note"] = "no escaping initial state along the ray through x0 (--escape-x0 auto)"
    elif args.escape_x0 is not None:
        esc = (None, args.escape_x0)
    if esc is not None:
        X = trajectory(sc, esc[1])
        how = "found along the ray through $x_0$" if esc[0] is not None else "--escape-x0"
        trajs.append((f"from $x_0$ = {np.round(esc[1], 3).tolist()} under the same attacks ({how})", X, None))
        res["escape_x0"] = np.asarray(esc[1]).tolist()
        res["escape_note"] = (f"the phase portrait also shows the run from x0 = {np.round(esc[1], 4).tolist()} under "
                              "the scenario's attacks (--escape-x0)")
    zoom = ((roa.xs[-1] - roa.xs[0]) / 10, (roa.ys[-1] - roa.ys[0]) / 10)
    files.append(figures.plot_phase_portrait(roa, path("phase-portrait"), trajectories=trajs,
                                             title=f"{sc.name}: nominal region of attraction", zoom=zoom, size=size))
    vu = extra.get("_vulnerable")
    if vu is not None:
        files.append(figures.plot_phase_portrait(roa, path("vulnerable"), vulnerable=vu,
                                                 baseline=extra.get("_vulnerable_baseline"),
                                                 title=f"{sc.name}: initial states the attacker defeats",
                                                 zoom=zoom, size=size))
    bud = res["budget"]
    sw = extra.get("_sweep")
    files.append(figures.plot_allowable_region(path("allowable-region"), regions=res["_regions"],
                                               plain=res["_plain"], sweep=sw,
                                               sweep_zoom=extra.get("_sweep_zoom"),
                                               budget=(bud["kappa_F"], bud["rho_F"], bud["kappa_D"],
                                                       bud["rho_D"]),
                                               budget_label=budget_label(res), size=size,
                                               title=f"{sc.name}: allowable DoS (Theorem 1)"
                                                     + (" and the empirical map" if sw is not None else "")))
    files.append(figures.plot_delta(res["delta_table"], path("delta"), gamma_mark=res["gamma"],
                                    E0_mark=res.get("E0_bound"), size=size,
                                    delta_paper=PAPER_DELTA if is_paper_example(sc) else None,
                                    title=f"{sc.name}: Lemma 2's radius; Theorem 2's bound for $\\kappa_F$ = "
                                          f"{bud['kappa_F']:g}, $\\kappa_D$ = {bud['kappa_D']:g}"))
    return [str(f) for f in files]


def budget_label(res: dict) -> str:
    """The legend entry of the budget star: what the budget is and where it comes from."""
    b, src = res["budget"], res["budget_source"]
    at = f"$\\rho_F$ = {b['rho_F']:g}, $\\rho_D$ = {b['rho_D']:g}"
    if src == "scenario":
        return f"the scenario's declared budget ({at})"
    if src == "given":
        return f"the budget of --budget ({at})"
    if src.startswith("periodic"):
        return f"the scenario's periodic attack ({at})"
    return f"the scenario's finite attack (average rates {at})"


#: Lemma 2's delta the paper reports for its example (Section V)
PAPER_DELTA = 1.94e-7


def is_paper_example(sc: Scenario) -> bool:
    """The paper's example: the Lienard plant with the paper's parameters, T and K (the bundled ``paper*``)."""
    from .. import scenario

    ref = scenario.load("paper")
    return (sc.plant.name == ref.plant.name and sc.make_model().params_dict() == ref.make_model().params_dict()
            and sc.T == ref.T and sc.quantizer.M == ref.quantizer.M and np.shape(sc.K) == np.shape(ref.K)
            and np.allclose(sc.K, ref.K))


# ============================================================================ roa
def add_arguments_roa(p: argparse.ArgumentParser) -> None:
    _add_scenario(p)
    _add_method(p)
    p.add_argument("--grid", type=int, default=201, help="points per axis (default 201)")
    p.add_argument("--horizon", type=float, default=30.0, help="seconds simulated per state (default 30)")
    p.add_argument("--window", nargs=2, type=float, metavar=("WX", "WY"),
                   help="half-widths of the window (default per plant)")
    p.add_argument("--dims", nargs=2, type=int, metavar=("I", "J"), help="gridded coordinates (default 0 1)")
    cliargs.add_plot(p, "write the phase portrait with the scenario's trajectory")
    cliargs.add_json(p, "the region of attraction")
    p.add_argument("--vulnerable", action="store_true",
                   help="also map the states of the region from which the attacker defeats the loop")
    _add_budget(p, "budget of --vulnerable (default: the scenario's explicit budget, else "
                   "(1, rho_F, 0.2, rho_D) at a quarter of Theorem 1's intercepts)")
    p.add_argument("--kind", choices=["greedy", "random", "periodic"], default="greedy",
                   help="attacker of --vulnerable (default greedy)")
    p.add_argument("--threshold", type=float, default=0.0, help="greedy threshold (default 0)")
    p.add_argument("--stride", type=int, default=2, help="--vulnerable uses every STRIDE-th grid state (default 2)")
    cliargs.add_batch_options(p)


def main_roa(args: argparse.Namespace) -> int:
    from .. import scenario

    sc = _with_method(scenario.load(args.scenario, read_recording_trace=read_recording_trace), args, "testbed roa")
    if args.vulnerable:
        true_plant(sc, "testbed roa --vulnerable")
    plant = sc.make_model()
    with _executor(args) as ex:
        return _roa(sc, plant, args, ex)


def _roa(sc, plant, args, ex) -> int:
    """``plant``: the model, whose nominal loop the region is; --vulnerable runs the true plant."""
    from ..analysis import figures
    from ..analysis.roa import nominal_roa
    from ..sim.batch import simulate_scenario

    roa = nominal_roa(plant, sc.K, sc.T, grid=args.grid, window=args.window, dims=args.dims, horizon=args.horizon,
                      tol=sc.run.converge_tol, flow=sc.flow,
                      progress=Progress("region of attraction", not args.no_progress), executor=ex)
    out = {"scenario": sc.name, **plant_and_model(sc), "roa": roa.to_dict(), "parallel": ex.describe()}
    vu = None
    if args.vulnerable:
        from ..analysis.sweep import vulnerable_states

        if args.budget:
            vb = tuple(args.budget)
        else:
            from ..analysis.region import allowable_region
            from ..analysis.theorem1 import Loop

            reg = allowable_region(Loop.from_scenario(sc), "tight", n_phi0=16, n_phi1=3)
            vb = _vulnerable_budget(sc, reg.rho_F_max, reg.rho_D_max)
        vu = vulnerable_states(true_plant(sc, "testbed roa --vulnerable"), sc.K, sc.quantizer, vb, roa,
                               stride=args.stride, kind=args.kind, threshold=args.threshold, tol=sc.run.converge_tol,
                               flow=sc.flow, progress=Progress("vulnerable states", not args.no_progress), executor=ex,
                               model=plant)
        out["vulnerable"] = vu.to_dict()
    if args.plot:
        sim = simulate_scenario(sc)
        figures.plot_phase_portrait(roa, args.plot, vulnerable=vu, title=f"{sc.name}: nominal region of attraction",
                                    trajectories=[(f"the scenario's run from $x_0$ = {np.round(sc.x0, 3).tolist()}",
                                                   sim.x, None)], size=args.figsize)
        out["figure"] = args.plot
    if args.json:
        from ..analysis.summary import to_json

        _write_json({**to_json(out), "method": sc.method.name})
    else:
        r = out["roa"]
        print(f"scenario {sc.name}: nominal region of attraction on a {r['grid'][0]} x {r['grid'][1]} grid, "
              f"window {r['window']}, horizon {r['horizon']:g} s")
        if (mismatch := _mismatch_line(out)):
            print(mismatch + ": the region is the model's nominal loop"
                  + ("; --vulnerable runs the true plant" if vu is not None else ""))
        print(f"  inside: {r['fraction_inside']:.4f} of the grid, area {r['area']:.4g}")
        print(f"  {r['traj_steps']} trajectory-steps in {r['wall_s']:.2f} s = {r['traj_steps_per_s']:.3g} per s")
        if vu is not None:
            v = out["vulnerable"]
            print(f"  vulnerable under {v['kind']} DoS {v['budget']}: {v['bounded'] + v['escaped']} of "
                  f"{v['states_in_region']} states fail ({v['escaped']} escape), "
                  f"fraction {_fmt(v['fraction_vulnerable'])}")
        if args.plot:
            print(f"  wrote {args.plot}")
    return 0
