"""``testbed campaign CAMPAIGN.toml`` and ``testbed campaign --verify DIR`` (docs/campaigns.md)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..common import cliargs, validate


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("campaign", nargs="?", help="the campaign file (.toml; see docs/campaigns.md)")
    p.add_argument("--out", metavar="DIR", help="the campaign's folder (default recordings/campaign-<file stem>; "
                                                "the same command again resumes there)")
    cliargs.add_workers(p)
    cliargs.add_scheduler(p)
    cliargs.add_json(p, "the summary (and with --verify the comparison)")
    cliargs.add_plot(p, "the success rate over one or two axes, 95 %% Wilson intervals as error bars")
    cliargs.add_no_progress(p)
    p.add_argument("--table", choices=("latex", "markdown"),
                   help="print the paired comparison table (each value of an axis against the axis's first, on the "
                        "same seeds and initial states) instead of the text summary")
    p.add_argument("--verify", metavar="DIR", help="re-run the rows of a campaign's folder and compare them bit for "
                                                   "bit (live rows: re-simulated from their recordings)")
    p.add_argument("--sample", type=int, metavar="K", help="--verify: only K simulated rows, drawn with --seed")
    p.add_argument("--seed", type=int, metavar="S", help="--verify --sample: the draw's seed (default 0; a campaign's "
                                                         "own seed is in its file)")
    cliargs.add_trust_code(p, "the campaign's folder (--verify)")
    p.add_argument("--live-timeout", type=float, metavar="S", help=argparse.SUPPRESS)


def main(args: argparse.Namespace) -> int:
    from ..common.errors import BadInput

    if args.verify:
        if args.campaign:
            raise BadInput("give a campaign file or --verify DIR, not both")
        return _verify(args)
    if not args.campaign:
        raise BadInput("give a campaign file (testbed campaign FILE.toml) or --verify DIR")
    if args.sample is not None or args.seed is not None:
        raise BadInput("--sample and --seed apply to --verify (a campaign's seed is its file's 'seed')")
    if args.trust_code:
        raise BadInput("--trust-code applies to --verify (a campaign runs the code its file names)")
    from ..campaign import runner as campaignrun
    from ..campaign.folder import default_dir
    from ..campaign.spec import base_scenario, parse, plan

    if args.table and args.json:
        raise BadInput("give --json or --table, not both")
    c = parse(args.campaign)
    folder = Path(args.out) if args.out else default_dir(c)
    executor = None
    try:
        base = base_scenario(c)
        with _say_if_slow(None if args.no_progress else
                          f"campaign: resolving and validating every run of {c.path} (before anything runs) ..."):
            runs, notes = plan(c, base)  # every run validated before anything runs (or the folder is made)
        for n in notes:
            print(f"testbed campaign: note: {n}", file=sys.stderr)
        if c.runs == "simulated" or args.scheduler:
            from ..analysis import parallel

            executor = parallel.Executor(args.workers, args.scheduler)
        parallel_desc = executor.describe() if executor is not None else {"kind": "serial", "workers": 1}
        out = campaignrun.run(c, folder, executor=executor, progress=not args.no_progress,
                              live_timeout=args.live_timeout, planned=(base, runs, notes))
    except KeyboardInterrupt:
        _interrupted(args, folder)
        return 130
    finally:
        if executor is not None:
            executor.close()
    s = out["summary"]
    if args.plot:
        s = dict(s, folder=str(folder))
        campaignrun.plot(args.plot, c, s, args.figsize)
        s.pop("folder")
    failed = s["failed"]
    if args.table:
        from ..campaign import tables

        print(tables.latex(s, label=c.stem) if args.table == "latex" else tables.markdown(s), end="")
    elif args.json:
        print(json.dumps({"folder": str(folder), "ran": out["ran"], "skipped": out["skipped"],
                          "parallel": parallel_desc,
                          **({"figure": str(args.plot)} if args.plot else {}), "summary": s}))
    else:
        from ..campaign import tables

        t = s["total"]
        w = t["wilson95"]
        print(f"campaign {c.stem}: {s['done']} of {s['planned']} runs ({out['ran']} run now, {out['skipped']} "
              f"found done), {failed} failed")
        if t["n"]:
            print(f"  success {t['successes']}/{t['n']} = {t['success_rate']:.3f} (95 % Wilson [{w[0]:.3f}, "
                  f"{w[1]:.3f}]): {t['converged']} converged, {t['bounded']} bounded (neither converged nor "
                  f"escaped), {t['escaped']} escaped")
        for k, groups in s["by_axis"].items():
            if len(groups) > 1 and len(groups) <= 12:
                print(f"  by {k} (converged/bounded/escaped): "
                      + ", ".join(f"{json.dumps(g['value'])} {g['converged']}/{g['bounded']}/{g['escaped']}"
                                  for g in groups))
        for comp in s.get("comparisons", {}).values():
            for d in comp["values"]:
                pd = d["paired_difference"]
                print(f"  {json.dumps(d['value'])} minus {json.dumps(d['vs'])} ({d['pairs']} pairs): converged "
                      f"{tables.fmt_ci(pd['difference'], pd['ci95'])}, McNemar {tables.fmt_p(pd['mcnemar_p'])}")
        print("  the comparison table: the same command with --table markdown (or latex)")
        print(f"  table: {folder / 'runs.parquet'}; summary: {folder / 'summary.md'}")
        if args.plot:
            print(f"  figure: {args.plot}")
    return 1 if failed else 0


class _say_if_slow:
    """``with _say_if_slow(line):`` print ``line`` on stderr if the block still runs after ``after`` seconds
    (planning a large campaign takes seconds; a small one, or a bad value found at once, stays one line)."""

    def __init__(self, line: str | None, after: float = 1.0):
        self.line, self.after, self.timer = line, after, None

    def __enter__(self):
        if self.line:
            import threading

            self.timer = threading.Timer(self.after, lambda: print(self.line, file=sys.stderr, flush=True))
            self.timer.daemon = True
            self.timer.start()
        return self

    def __exit__(self, *exc):
        if self.timer is not None:
            self.timer.cancel()
            self.timer.join()  # no thread left: the local workers are then forked, not spawned
        return False


def _interrupted(args, folder: Path) -> None:
    """The line of a campaign stopped by Ctrl-C: what is stored, and the command that resumes."""
    from ..campaign.folder import read_journal

    stored, planned = 0, None
    if (folder / "campaign.toml").exists():
        stored = sum(1 for r in read_journal(folder).values() if r.get("status") == "ok")
        try:
            planned = len(json.loads((folder / "manifest.json").read_text()).get("runs", []))
        except (OSError, ValueError):
            planned = None
    if sys.stderr.isatty():
        sys.stderr.write("\n")
    again = " ".join(["testbed campaign", args.campaign] + ([] if not args.out else ["--out", str(folder)]))
    what = f"{stored} of {planned} runs are stored in {folder}" if planned else "no run is stored yet"
    print(f"testbed campaign: interrupted; {what}; the same command resumes: {again}", file=sys.stderr)


def _verify(args) -> int:
    from ..campaign import runner as campaignrun

    if args.sample is not None:
        validate.flag("--sample", args.sample, integer=True, lo=1)
    executor = None
    if args.workers or args.scheduler:
        from ..analysis import parallel

        executor = parallel.Executor(args.workers, args.scheduler)
    try:
        d = campaignrun.verify(Path(args.verify), sample=args.sample, seed=args.seed or 0,
                                    executor=executor, trust_code=args.trust_code)
    finally:
        if executor is not None:
            executor.close()
    if args.json:
        print(json.dumps(d, default=str))
    else:
        print(f"{d['folder']}: {d['rows']} rows of {d['planned']} planned; re-ran {d['checked_simulated']} simulated, "
              f"re-simulated {d['checked_live']} live")
        for p in d["problems"]:
            print(f"  PROBLEM: {p}")
        if d["not_run"]:
            print(f"  SKIPPED {len(d['not_run'])} row(s): {d['not_run_why']}")
        if d["missing"]:
            print(f"  not run yet: {len(d['missing'])} run(s) (the campaign command again finishes them)")
        for x in d["differences"]:
            print(f"  DIFFERS: run {x['run']} {x['why']}")
        for k, v in d["versions_differ"].items():
            print(f"  version: {k} {v['manifest']} in the manifest, {v['here']} here")
        if d["source_differs"]:
            print("  the testbed's source differs from the manifest's hash")
        if d["python_differs"]:
            print("  Python differs from the manifest's")
        print("  identical" if d["identical"] else "  NOT identical")
    return 0 if d["identical"] else 1
