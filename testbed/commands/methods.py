"""``testbed methods [--json]`` and ``testbed versus SCENARIO --methods A,B,...``."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from ..common import cliargs, validate
from ..record.tracereader import read_recording_trace


# ============================================================================ methods
def add_arguments_methods(p: argparse.ArgumentParser) -> None:
    cliargs.add_json(p, "the methods (name, description, bits per sample, where each runs)")


def method_table() -> list[dict]:
    """Every bundled, registered and installed method: ``name``, ``description``, ``source``, ``bits``
    (per sample on the paper's example: n = 2, M = 6), ``runs`` (where it runs)."""
    from .. import methods, scenario

    sc = scenario.load("paper")
    out: list[dict[str, Any]] = []
    refs = list(methods.names()) + [n for n in methods.entry_points() if n not in methods.names()]
    for ref in refs:
        try:
            m = methods.make(ref)
            bits = m.bits(2, sc.quantizer)
        except Exception as e:  # noqa: BLE001 - a broken installed method is listed with its error
            out.append({"name": ref, "description": f"cannot be loaded: {e}", "source": "", "bits": None, "runs": []})
            continue
        runs = ["per-sample", "live"] + (["batch"] if m.kernel_code(sc.quantizer) is not None else [])
        out.append({"name": ref, "description": m.description, "source": m.source, "bits": bits, "runs": runs,
                    "uses": ["T", *m.uses], "params": dict(m.defaults)})
    return out


def main_methods(args: argparse.Namespace) -> int:
    rows = method_table()
    if args.json:
        print(json.dumps({"methods": rows, "bits_for": "the paper's example (n = 2, M = 6)"}))
        return 0
    w = max(len(r["name"]) for r in rows)
    print(f"{'name':<{w}}  bits  runs                      description")
    for r in rows:
        print(f"{r['name']:<{w}}  {str(r['bits']):>4}  {', '.join(r['runs']):<24}  {r['description']}")
    print("bits: per sample on the paper's example (n = 2, M = 6); a method's own: testbed simulate --method NAME")
    return 0


# ============================================================================ versus
def add_arguments_versus(p: argparse.ArgumentParser) -> None:
    cliargs.add_scenario(p)
    p.add_argument("--methods", required=True, metavar="A,B,...",
                   help="the methods to compare (names or module:Class), the first is the reference of the "
                        "paired differences")
    p.add_argument("--seeds", type=int, metavar="N",
                   help="random attack: run seeds S..S+N-1 (--seed S) for every method, and summarize")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="first seed with --seeds (default 0)")
    p.add_argument("--live", action="store_true", help="run them live (testbed run), one after the other, each "
                                                       "recorded")
    p.add_argument("--out", metavar="DIR", help="--live: the folder of the recordings (default recordings/versus-"
                                                "<scenario>)")
    cliargs.add_json(p, "rows (one per method and seed) and, with --seeds, the summary")
    cliargs.add_plot(p, "overlay the trajectories ||x_k||_inf and log E_k of every method")


def _methods_arg(v: str) -> list[str]:
    from ..common.errors import BadInput

    ms = [m.strip() for m in (v or "").split(",") if m.strip()]
    if not ms:
        raise BadInput("--methods: give at least one method (e.g. --methods paper,zoom,unquantized)")
    if len(set(ms)) != len(ms):
        raise BadInput(f"--methods: a method is named twice in {v!r}")
    return ms


def main_versus(args: argparse.Namespace) -> int:
    from .. import scenario
    from ..campaign import engine

    names = _methods_arg(args.methods)
    if args.seeds is not None:
        validate.flag("--seeds", args.seeds, integer=True, lo=1)
    sc = scenario.load(args.scenario, read_recording_trace=read_recording_trace)
    if args.seeds is None:  # with --seeds the rows use seeds S..S+N-1: nothing is drawn
        sc, over = scenario.with_seed(sc, {})
        if over:
            print(f"testbed versus: the random attack has no seed; drew seed = {over['seed']} (every method faces "
                  "it)", file=sys.stderr)
    seeds = engine.seeds_for(sc, args.seeds, args.seed)
    points = [engine.Point(sc, m, s) for s in seeds for m in names]
    notes = set()
    for p in points[:len(names)]:  # validate every method before anything runs
        psc = p.scenario()
        if psc.method_note:
            notes.add(psc.method_note)
    for n in sorted(notes):
        print(f"testbed versus: {n}", file=sys.stderr)
    if args.live:
        rows, series = _live(args, sc, points)
    else:
        done = engine.run_points(points, keep=bool(args.plot))
        rows = [d[0] for d in done] if args.plot else done
        series = [(d[0], d[2]) for d in done] if args.plot else []
    out: dict[str, Any] = {"scenario": sc.name, "methods": names, "rows": [{k: r[k] for k in engine.ROW_KEYS} for r in rows]}
    if args.live:
        for o, r in zip(out["rows"], rows):
            o["recording"] = r.get("recording")
    if args.seeds is not None:
        out["summary"] = engine.summarize_rows(rows, names)
        out["seeds"] = seeds
    if args.plot:
        _plot(args.plot, sc, series, args.figsize)
        out["figure"] = str(args.plot)
    if args.json:
        print(json.dumps(out))
    else:
        print(f"scenario {sc.name}: {len(names)} methods x {len(seeds)} attack realization(s)")
        print(f"{'method':<18} {'seed':>6} {'converged':>9} {'escaped':>7} {'final':>10} {'max':>9} {'sat':>5} "
              f"{'lost':>5} {'bits':>5} {'settle':>6}")
        for r in out["rows"]:
            print(f"{r['method']:<18} {str(r['seed']):>6} {str(r['converged']):>9} {str(r['escaped']):>7} "
                  f"{r['final_norm']:>10.3e} {r['max_norm']:>9.3g} {r['saturations']:>5} {r['samples_lost']:>5} "
                  f"{r['bits']:>5} {str(r['settle_samples']):>6}")
        for line in _summary_lines(out.get("summary", {})):
            print(line)
    return 0


def _summary_lines(summary: dict) -> list[str]:
    """``versus --seeds``' summary as text: per method its rate and outcomes, then its paired comparison."""
    from ..campaign.tables import fmt_ci, fmt_p

    lines = []
    for m, d in summary.items():
        w = d["wilson95"]
        lines.append(f"{m}: success {d['successes']}/{d['n']} (95 % Wilson [{w[0]:.2f}, {w[1]:.2f}]); "
                     f"{d['converged']} converged, {d['bounded']} bounded, {d['escaped']} escaped")
        if "paired_difference" in d:
            pd, pe = d["paired_difference"], d["paired_escaped"]
            lines.append(f"  minus {pd['vs']} on the same seeds ({pd['n']} pairs): converged "
                         f"{fmt_ci(pd['difference'], pd['ci95'])} (McNemar {fmt_p(pd['mcnemar_p'])}), escaped "
                         f"{fmt_ci(pe['difference'], pe['ci95'])} "
                         f"({fmt_p(pe['mcnemar_p'])})")
            for k, c in d["paired_continuous"].items():
                lines.append(f"  {k}: median difference {fmt_ci(c['median_difference'], c['ci95'], '+.3g')} over "
                             f"{c['n']} pairs (Wilcoxon {fmt_p(c['wilcoxon_p'])})")
    return lines


def _live(args, sc, points):
    """Each point live (``testbed run``), one after the other, each recorded; rows from the reports."""
    import os
    import subprocess
    from pathlib import Path

    from ..common.errors import BadInput

    folder = Path(args.out or Path("recordings") / f"versus-{sc.name}")
    folder.mkdir(parents=True, exist_ok=True)
    rows, series = [], []
    for p in points:
        rec = folder / f"{p.method}{'' if p.seed is None else f'-seed{p.seed}'}.mcap".replace(":", "_")
        if rec.exists():
            raise BadInput(f"--live: {rec} exists (a recording is never overwritten): remove it or give --out")
        cmd = [sys.executable, "-m", "testbed.cli", "run", args.scenario, "--method", p.method, "--out", str(rec)]
        if p.seed is not None:
            cmd += ["--seed", str(p.seed)]
        elif sc.attack.kind == "random":
            cmd += ["--seed", str(sc.attack.params_dict["seed"])]
        r = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy())
        if r.returncode not in (0, 1) or not rec.exists():
            raise RuntimeError(f"live run of {p.method} failed (exit {r.returncode}): "
                               f"{(r.stderr.strip().splitlines() or [''])[-1]}")
        row, d = _row_from_recording(rec, p)
        rows.append(row)
        if args.plot:
            series.append((row, _Series(d, sc.T)))
    return rows, series


class _Series:
    """The per-sample arrays ``_plot`` draws, from a recording's report."""

    def __init__(self, d: dict, T: float):
        import numpy as np

        self.x = np.asarray(d.get("x") or [], dtype=float)
        self.t = np.arange(len(self.x)) * T
        self.E_enc = np.asarray([np.nan if v is None else v for v in (d.get("E") or [])], dtype=float)
        self.theta = np.asarray(d.get("theta") or [], dtype=int)


def _row_from_recording(rec, p):
    from ..campaign import engine
    from ..runs.report import report

    d = report(str(rec), resimulate=None)
    x = d.get("x") or []
    import numpy as np

    xf = np.asarray(d.get("x_final") or (x[-1] if x else [0.0]), dtype=float)
    tol = (d.get("escape_criterion") or {}).get("x_tol", 1e-4)
    row = {"method": d.get("method", p.method), "seed": p.seed, "converged": bool(d.get("converged")),
            "escaped": bool(d.get("escaped")), "final_norm": d.get("final_norm"), "max_norm": d.get("max_norm"),
            "saturations": d.get("saturations"), "samples_lost": d.get("samples_lost", d.get("packets_dropped")),
            "bits": d.get("bits"), "settle_samples": engine.settle_samples(np.asarray(x, dtype=float), xf, tol),
            "recording": str(rec)}
    return row, d


def _plot(path, sc, series, size) -> None:
    import numpy as np

    from ..common.figstyle import pyplot, subplots

    plt = pyplot()
    fig, axs = subplots(size, 2, 1, sharex=True)
    a1, a2 = axs[0, 0], axs[1, 0]
    for row, res in series:
        lab = row["method"] + ("" if row["seed"] is None else f" (seed {row['seed']})")
        a1.semilogy(res.t, np.maximum(np.max(np.abs(res.x), axis=1), 1e-16), label=lab)
        E = np.asarray(res.E_enc, dtype=float)
        if np.any(E > 0):
            a2.semilogy(res.t, np.where(E > 0, E, np.nan), label=lab)
    th = series[0][1].theta if series else []
    for k in np.flatnonzero(np.asarray(th) == 1):
        a1.axvspan(k * sc.T, (k + 1) * sc.T, color="0.85", lw=0)
    a1.set_ylabel("||x_k||_inf")
    a2.set_ylabel("E_k")
    a2.set_xlabel("t [s]")
    a1.legend(fontsize=7)
    a1.set_title(f"{sc.name}: methods on the same attack")
    fig.savefig(path)
    plt.close(fig)
