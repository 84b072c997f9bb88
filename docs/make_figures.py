"""Every figure of the docs, drawn by the commands that draw them, and the gallery page docs/figures.md.

    python docs/make_figures.py                  # run every command below: write the figures, their data, figures.md
    python docs/make_figures.py --check          # run them into a scratch folder and compare: exit 1 naming what is stale
    python docs/make_figures.py --only NAME ...  # only these jobs (see --list)

A figure is compared by the data it drew, not by its pixels: ``testbed.common.figstyle`` stores a digest of
every line, image, patch and text of a figure in the file's metadata (``figstyle.read_digest``),
and ``--check`` recomputes the figure and compares the digests. The data files beside the figures
(``docs/analysis/paper.json``, ``docs/figures/*.json``: what the command printed with ``--json``)
are compared value by value (to 9 significant digits), without what depends on the machine (wall
times, rates, worker counts) and without the figure paths. ``tests/analysis/test_figures.py`` runs the
check (slow tier) and shows that it fails on a stale copy (fast tier).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent

#: keys of a command's JSON that depend on the machine or on where it wrote (left out of the data files)
VOLATILE = {"wall_s", "traj_steps_per_s", "parallel", "figure", "figures"}
#: keys whose values are near-zero differences of O(1) numbers (a certificate's Lyapunov margins, ``verify``): their
#: last ~1e-14 is the machine's arithmetic (its BLAS), so they are compared to this absolute tolerance, not 9 digits
NEAR_ZERO = {"lyapunov0": 1e-12, "lyapunov1": 1e-12}


@dataclass(frozen=True)
class Job:
    """Commands (``testbed`` arguments; ``{out}``: the output folder, ``{tmp}``: a scratch folder) that draw
    ``figures`` (paths under the output folder); the last command's ``--json`` goes to ``data`` if given."""

    name: str
    commands: tuple[tuple[str, ...], ...]
    figures: tuple[str, ...]
    data: str | None = None
    title: str = ""
    about: str = ""
    captions: dict = field(default_factory=dict)


JOBS = (
    Job("simulate-paper", (("simulate", "paper", "--plot", "{out}/figures/simulate-paper.png", "--json"),),
        ("figures/simulate-paper.png",), data="figures/simulate-paper.json",
        title="A run: `testbed simulate --plot`",
        about="The paper's Fig. 2: states, input and the quantizer range E_k at the encoder (solid) and the "
              "decoder (dashed) over time, the DoS intervals shaded. `testbed report RUN.mcap --plot` and "
              "`Run.plot(PATH)` draw the same figure from a recording or a `Run`."),
    Job("simulate-paper-escape", (("simulate", "paper-escape", "--plot", "{out}/figures/simulate-paper-escape.png",
                                   "--figsize", "column"),),
        ("figures/simulate-paper-escape.png",), title="An escaping run, one column wide (`--figsize column`)",
        about="The same figure for `paper-escape` (x0 = [0.3, 0.3]), at the width of one IEEE column."),
    Job("report-paper", (("simulate", "paper-greedy", "--out", "{tmp}/greedy.mcap"),
                         ("report", "{tmp}/greedy.mcap", "--plot", "{out}/figures/report-paper-greedy.png")),
        ("figures/report-paper-greedy.png",), title="A recording: `testbed report --plot`",
        about="The post-mortem's figure of a recording (here of `testbed simulate paper-greedy --out`: the "
              "greedy online attacker); a live run's recording draws the same way."),
    Job("compare-paper-mismatch", (("compare", "paper", "paper-mismatch", "--plot",
                                    "{out}/figures/compare-paper-mismatch.png"),),
        ("figures/compare-paper-mismatch.png",), title="Two runs: `testbed compare --plot`",
        about="Run A solid, run B dashed, one hue per state component; below, ||x_A - x_B||_inf and the lost "
              "samples of each run; DoS shaded (hatched where only B was attacked)."),
    Job("roa-paper", (("roa", "paper", "--plot", "{out}/figures/roa-paper.png", "--no-progress"),),
        ("figures/roa-paper.png",), title="The region of attraction: `testbed roa --plot`",
        about="The nominal region of attraction (201 x 201 grid) with the scenario's trajectory."),
    Job("sweep-paper", (("sweep", "paper", "--plot", "{out}/figures/sweep-paper.png", "--no-progress", "--json"),),
        ("figures/sweep-paper.png",), data="figures/sweep-paper.json",
        title="Empirical DoS tolerance: `testbed sweep --plot`",
        about="The worst converged fraction over (rho_D, rho_F) (21 x 21 budgets, three attacker kinds), the "
              "empirical boundary of each kind, Theorem 1's boundaries, and a zoom on the theorem's region."),
    Job("noise-paper", (("noise", "docs/examples/paper-noisy.toml", "--plot", "{out}/figures/noise-paper.png",
                         "--no-progress", "--json"),),
        ("figures/noise-paper.png",), data="figures/noise-paper.json",
        title="E_min against sensor noise: `testbed noise --plot`",
        about="The paper's example read through a noisy sensor (uniform noise, three scales), over E_min / b (b: "
              "the noise's bound): the saturations (OVERFLOW recaptures) after the state settled, and the steady "
              "||x||_inf against the predicted ball (dotted; crosses: escaped), with the linearized estimate "
              "(dashed) and the guarantee (dash-dotted) of [the quantizer under sensor noise]"
              "(plants-and-quantizer.md#the-quantizer-under-sensor-noise)."),
    Job("analyze-paper", (("analyze", "paper", "--full", "--plot", "{out}/analysis", "--escape-x0", "0.3", "0.3",
                           "--no-progress", "--json"),),
        ("analysis/paper-allowable-region.png", "analysis/paper-delta.png", "analysis/paper-time-series.png",
         "analysis/paper-phase-portrait.png", "analysis/paper-vulnerable.png"), data="analysis/paper.json",
        title="The paper's bounds: `testbed analyze --full --plot`",
        about="Theorem 1's allowable region over the empirical map, delta(gamma) of Lemma 2 with Theorem 2's E_0 "
              "bound, the time series, the phase portrait (with the run from x0 = [0.3, 0.3] under the same "
              "attacks, asked for with `--escape-x0 0.3 0.3`) and the initial states the attacker defeats. "
              "These are the figures of [analysis](analysis.md)."),
    Job("campaign-methods", (("campaign", "docs/examples/campaign-methods.toml", "--out", "{tmp}/campaign", "--plot",
                              "{out}/figures/campaign-methods.png", "--no-progress"),),
        ("figures/campaign-methods.png",), title="A campaign: `testbed campaign --plot`",
        about="The worked example of [campaigns](campaigns.md#worked-example-the-papers-method-against-the-baselines): "
              "the fraction of converged and of escaped runs of each method (95 % Wilson intervals), one series "
              "per initial state, the attack seeds pooled; the values of an axis side by side, not joined."),
    Job("vulnerability-paper", (("vulnerability", "paper", "--grid", "41", "--plot",
                                 "{out}/analysis/paper-vulnerability.png", "--no-progress"),),
        ("analysis/paper-vulnerability.png",), title="The least attack per state: `testbed vulnerability --plot`",
        about="The least total DoS duration that drives the loop out, over the region of attraction, with "
              "Theorem 2's delta-ball."),
)


def command_line(args: tuple[str, ...]) -> str:
    """A job's command as the page shows it (paths as in the docs folder)."""
    shown = []
    for a in args:
        a = a.replace("{out}", "docs").replace("{tmp}", "recordings")
        shown.append(a)
    if shown[-1] == "--json":
        shown = shown[:-1]
    return "testbed " + " ".join(shown)


def run_job(job: Job, out: Path) -> dict | None:
    """Run ``job``'s commands with their outputs under ``out``; returns its data (the last ``--json``)."""
    with tempfile.TemporaryDirectory() as tmp:
        data = None
        for args in job.commands:
            argv = [a.replace("{out}", str(out)).replace("{tmp}", tmp) for a in args]
            for a in argv:
                if a.startswith(str(out)) and Path(a).suffix:
                    Path(a).parent.mkdir(parents=True, exist_ok=True)
            r = subprocess.run([sys.executable, "-m", "testbed.cli", *argv], capture_output=True, text=True,
                               cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT), MPLBACKEND="Agg"),
                               timeout=3600)
            if r.returncode not in (0, 1):
                raise SystemExit(f"{command_line(args)}: exit {r.returncode}\n{r.stderr[-3000:]}")
            if args[-1] == "--json":
                data = strip(json.loads(r.stdout))
    return data


def strip(d):
    """A command's JSON without what depends on the machine or on output paths (``VOLATILE``)."""
    if isinstance(d, dict):
        return {k: strip(v) for k, v in d.items() if k not in VOLATILE}
    if isinstance(d, list):
        return [strip(v) for v in d]
    return d


def _round(v, key: str | None = None):
    if isinstance(v, float) and math.isfinite(v) and v != 0:
        return round(v / NEAR_ZERO[key]) * NEAR_ZERO[key] if key in NEAR_ZERO else float(f"{v:.9g}")
    if isinstance(v, dict):
        return {k: _round(x, k) for k, x in v.items()}
    if isinstance(v, list):
        return [_round(x, key) for x in v]
    return v


def write_data(path: Path, data) -> None:
    path.write_text(json.dumps(data, indent=1, allow_nan=False) + "\n")


def stale(job: Job, fresh: Path, committed: Path) -> list[str]:
    """What of ``job`` under ``committed`` differs from the freshly drawn ``fresh``: one line each."""
    from testbed.common.figstyle import read_digest

    out = []
    for f in job.figures:
        c = committed / f
        if not c.exists():
            out.append(f"{f}: missing")
            continue
        want, have = read_digest(fresh / f), read_digest(c)
        if have is None:
            out.append(f"{f}: carries no data digest (drawn by an older version)")
        elif have != want:
            out.append(f"{f}: drawn from other data (digest {have[:12]}, now {want[:12]})")
    if job.data:
        c = committed / job.data
        if not c.exists():
            out.append(f"{job.data}: missing")
        else:
            old, new = _round(json.loads(c.read_text())), _round(json.loads((fresh / job.data).read_text()))
            if old != new:
                keys = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k)) if isinstance(old, dict) \
                    else ["(whole file)"]
                out.append(f"{job.data}: other values than the command gives now ({', '.join(keys[:8])})")
    return out


def gallery() -> str:
    lines = ["# Figures", "",
             "Every figure the commands draw, made by the commands below (`python docs/make_figures.py` runs "
             "them all and writes this page; `python docs/make_figures.py --check` tells whether a figure or its "
             "data is stale). The style is one for all (`testbed/common/figstyle.py`):", "",
             "- **Sizes for IEEE papers**: `--figsize page` (both columns, 7.16 in wide, the default) or "
             "`--figsize column` (one column, 3.5 in); fonts of 8-9 pt at that size.",
             "- **Formats by the file's extension**: `--plot FIG.png` (300 dpi), `FIG.pdf` (fonts embedded), "
             "`FIG.svg`. Any other extension is refused (exit 2).",
             "- **Labels in math** ($x_1$, $E_k$, $\\rho_D$, $\\kappa_F$), **legends below the axes**, outside the "
             "data.",
             "- **A palette safe for colour-blind readers** (Okabe-Ito; the maps use cividis). Two runs A and B "
             "are one hue per quantity, A solid and B dashed.",
             "- **DoS intervals shaded gray on every time axis**, named in the legend.",
             "- Nothing is drawn that the command was not asked for: an extra trajectory in `analyze`'s phase "
             "portrait comes only with `--escape-x0`, and the legend and the console name it.", "",
             "In Python, `Run.plot(PATH, size=\"column\")` draws the figure of `testbed simulate --plot` for any "
             "run ([api](api.md)).", "",
             "Each figure file carries a digest of the data it drew (the PNG text chunk `testbed-data`, the "
             "PDF's Subject, the SVG's description): the check compares those digests, not pixels.", ""]
    for job in JOBS:
        lines += [f"## {job.title}", "", "```sh"]
        lines += [command_line(c) for c in job.commands]
        lines += ["```", "", job.about, ""]
        for f in job.figures:
            lines += [f"![{Path(f).stem}]({f})", ""]
        if job.data:
            lines += [f"The data: [{job.data}]({job.data}) (the command's `--json`, without wall times).", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="draw into a scratch folder and compare with the docs")
    ap.add_argument("--only", nargs="+", metavar="NAME", help="only these jobs")
    ap.add_argument("--list", action="store_true", help="list the jobs and their commands")
    ap.add_argument("--docs", type=Path, default=DOCS, help=argparse.SUPPRESS)  # the tests' stale copies
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    jobs = [j for j in JOBS if not args.only or j.name in args.only]
    if args.only and len(jobs) != len(args.only):
        raise SystemExit(f"unknown job(s): {set(args.only) - {j.name for j in JOBS}}")
    if args.list:
        for j in jobs:
            print(f"{j.name}: " + "; ".join(command_line(c) for c in j.commands))
        return 0
    if args.check:
        problems = []
        with tempfile.TemporaryDirectory() as d:
            fresh = Path(d)
            for job in jobs:
                data = run_job(job, fresh)
                if job.data:
                    write_data(fresh / job.data, data)
                problems += stale(job, fresh, args.docs)
        page = args.docs / "figures.md"
        if not args.only and (not page.exists() or page.read_text() != gallery() + "\n"):
            problems.append("figures.md: not the page make_figures.py writes")
        for p in problems:
            print(f"STALE {p}")
        print(f"{len(problems)} stale" if problems else f"every figure and its data is current ({len(jobs)} jobs)")
        return 1 if problems else 0
    for job in jobs:
        print(f"{job.name} ...", flush=True)
        with tempfile.TemporaryDirectory() as d:
            fresh = Path(d)
            data = run_job(job, fresh)
            for f in job.figures:
                (args.docs / f).parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(fresh / f, args.docs / f)
            if job.data:
                (args.docs / job.data).parent.mkdir(parents=True, exist_ok=True)
                write_data(args.docs / job.data, data)
    (args.docs / "figures.md").write_text(gallery() + "\n")
    print(f"wrote {sum(len(j.figures) for j in jobs)} figures and figures.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
