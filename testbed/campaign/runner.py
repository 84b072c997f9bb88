"""Running a campaign (resumable, over local workers or a Dask cluster), verifying a campaign's
folder, and its figure.  The campaign file, runs and seeds: ``spec``; a run's row: ``rows``; the journal,
table and summaries: ``folder``.
"""

from __future__ import annotations

import hashlib
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from ..common.errors import BadInput
from ..common.progress import RunsProgress as Progress
from . import code
from .folder import Journal, prepare, read_journal, read_parquet, source_hash, versions, write_results
from .rows import live_run, simulate_runs, simulate_runs_per_sample
from .spec import OUTCOME_KEYS, Campaign, PlannedRun, base_scenario, plan

if TYPE_CHECKING:

    from ..analysis.parallel import Executor


def chunks(items: list, workers: int, dask: bool) -> list[list]:
    """Chunks of runs: about 4 per worker, at most 16 runs each (a chunk is what a kill can lose)
    (on Dask at most 64: fewer, larger tasks keep the scheduler light)."""
    cap = 64 if dask else 16
    size = max(1, min(cap, math.ceil(len(items) / max(4 * workers, 1))))
    return [items[i:i + size] for i in range(0, len(items), size)]


def run(c: Campaign, folder: Path, *, executor: Executor | None = None, progress: bool = True,
        live_timeout: float | None = None, notes: list[str] | None = None, planned: tuple | None = None) -> dict:
    """Run every run of ``c`` not yet finished in ``folder``; write the table and summaries.  ``planned``:
    ``(base scenario, runs, notes)`` of ``plan`` when the caller has them already (planning validates
    every run: seconds for a large campaign).

    Returns ``{"rows", "summary", "folder", "ran", "skipped", "notes"}``.
    """
    if planned is None:
        base = base_scenario(c)
        runs, notes = plan(c, base)
    else:
        base, runs, notes = planned
    prepare(c, runs, folder, base)
    done = read_journal(folder)
    finished = {k for k, r in done.items() if r.get("status") == "ok"}
    todo = [r for r in runs if r.id not in finished]
    prog = Progress(len(runs), len(runs) - len(todo), progress)
    prog.say(f"{len(runs)} runs in {folder}" + (f", {len(runs) - len(todo)} found done" if len(todo) < len(runs)
                                                 else "") + f"; {len(todo)} to run")
    journal = Journal(folder)
    count = {"done": len(runs) - len(todo), "failed": 0}

    def store(row: dict) -> None:  # durably, as the run ends
        journal.write(row)
        done[row["run"]] = row
        count["done"] += 1
        count["failed"] += row["status"] != "ok"

    try:
        if c.runs == "live":
            if todo:
                prog.say("live runs, each a testbed run of its scenario, recorded"
                         + (" (on the Dask workers, one at a time per host)" if executor is not None
                            and executor.kind == "dask" else ", one at a time") + " ...")
            rows = (_live_on_dask(executor, todo, folder, live_timeout, _copies(folder))
                    if executor is not None and executor.kind == "dask"
                    else (live_run(r, folder / "recordings", timeout=live_timeout) for r in todo))
            for row in rows:
                store(row)
                prog(count["done"], count["failed"])
        elif todo:
            items = [(r.id, r.text, r.name, r.base_dir) for r in todo]
            first, rest = items[:1], items[1:]
            # the first run here: it loads (or compiles) the kernels before any worker does
            prog.say("the first run loads the simulator (compiled on first use, then cached) ...")
            for row in simulate_runs(first):
                store(row)
            prog(count["done"], count["failed"])
            dask = executor is not None and executor.kind == "dask"
            parts = chunks(rest, executor.workers if executor is not None else 1, dask)
            if rest:
                prog.say(f"the other {len(rest)} runs in {len(parts)} chunks on "
                         + (f"{executor.workers} {'Dask ' if dask else ''}worker(s)" if executor is not None
                            else "this process") + " ...")
            gen = (executor.imap(simulate_runs, parts, warm=first if dask else None) if executor is not None
                   else ((i, simulate_runs(p)) for i, p in enumerate(parts)))
            for _i, rows in gen:
                for row in rows:
                    store(row)
                prog(count["done"], count["failed"])
    finally:
        journal.close()
    prog(len([r for r in runs if r.id in done]), sum(1 for r in runs if r.id in done and done[r.id]["status"] != "ok"),
         final=True)
    prog.say("writing the table and the summaries (with the paired tests) ...")
    rows, s = write_results(folder, c, runs, done)
    return {"rows": rows, "summary": s, "folder": str(folder), "ran": len(todo), "skipped": len(runs) - len(todo),
            "notes": notes}


def _copies(folder: Path) -> list:
    """(path in the folder, text) of the user code copied beside the scenarios (``code``)."""
    try:
        stored = json.loads((folder / "manifest.json").read_text()).get("code") or []
    except (OSError, ValueError):
        return []
    return [(e["copy"], e["source"]) for e in stored if e.get("copy")]


def _live_on_dask(executor, todo: list, folder: Path, timeout, copies: Sequence = ()):
    """Live runs on a Dask cluster, one at a time per host (a live run needs the host's cores): each on a
    worker of a free host, its recording brought back into ``folder``; the rows as the runs end.  A worker
    lost mid-run has its run retried elsewhere by the scheduler (``retries=1``)."""
    import distributed

    client = executor.client
    by_host: dict = {}
    for addr, w in sorted(client.scheduler_info().get("workers", {}).items()):
        by_host.setdefault(w.get("host", addr), addr)
    queue = list(todo)
    running: dict = {}

    def submit(addr):
        r = queue.pop(0)
        f = client.submit(_remote_live, r.id, r.text, timeout, copies, pure=False, retries=1, workers=[addr],
                          allow_other_workers=True)
        running[f.key] = (r, addr)
        return f

    if not queue:
        return
    ac = distributed.as_completed([submit(a) for a in list(by_host.values())[:len(queue)]], loop=client.loop)
    for f in ac:
        r, addr = running.pop(f.key)
        try:
            row, data = f.result()
        except Exception as e:  # noqa: BLE001 - a run lost with its workers is a failed row (exit 1)
            row, data = {"run": r.id, **{k: None for k in OUTCOME_KEYS}, "status": "failed",
                         "error": f"{type(e).__name__}: {e}", "wall_s": None}, None
        if data is not None:
            rec = folder / row["recording"]
            rec.parent.mkdir(parents=True, exist_ok=True)
            rec.write_bytes(data)
        if queue:
            ac.add(submit(addr))
        yield row


def _remote_live(rid, text, timeout, copies=()):
    """On a worker: write the scenario (and the user code beside it) to a scratch folder, run it live,
    return the row and the recording."""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="testbed-campaign-") as d:
        d = Path(d)
        (d / "scenarios").mkdir()
        for rel, src in copies:
            (d / rel).parent.mkdir(parents=True, exist_ok=True)
            (d / rel).write_text(src)
        (d / "scenarios" / f"{rid}.toml").write_text(text)
        run = PlannedRun(rid, 0, 0, {}, {}, text, "scenario", "")
        row = live_run(run, d / "recordings", timeout=timeout)
        rec = d / row["recording"]
        return row, (rec.read_bytes() if rec.exists() else None)


# ============================================================================ verify
#: the columns --verify compares bit for bit
COMPARED = tuple(k for k in OUTCOME_KEYS)


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


def verify(folder: Path, *, sample: int | None = None, seed: int = 0, executor: Executor | None = None,
           trust_code: bool = False) -> dict:
    """Re-run the rows of a campaign's folder and compare: simulated rows bit for bit (every one, or
    ``sample`` drawn with ``seed``), live rows re-simulated from their recordings; the versions that
    differ from the manifest's.  Each row that differs is one entry saying why (``why``: the re-run's
    exception, or the first differing column with both values).  The user code the runs need comes from
    the folder (``code``): the module importable here with the stored sha256, else the stored source,
    only with ``trust_code`` (``BadInput`` naming --trust-code without it); a live row whose
    recording holds code that is not run without ``trust_code`` is skipped (``not_run``, ``not_run_why``) and
    the folder is not called identical."""
    import functools

    import numpy as np

    from plants.refs import CodeNotTrusted

    folder = Path(folder)
    for f in ("campaign.toml", "manifest.json", "runs.parquet"):
        if not (folder / f).is_file():
            raise BadInput(f"{folder}: no {f}: not a campaign's folder (testbed campaign FILE --out DIR makes one)")
    try:
        man = json.loads((folder / "manifest.json").read_text())
        rows = read_parquet(folder / "runs.parquet")
    except (OSError, ValueError) as e:
        raise BadInput(f"{folder}: {e}") from None
    differences, problems = [], []
    planned = {p["run"]: p for p in man.get("runs", [])}
    ids = [str(r.get("run")) for r in rows]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        problems.append(f"duplicate rows: {', '.join(dup[:5])}")
    unknown = sorted(set(ids) - set(planned))
    if unknown:
        problems.append(f"rows of no planned run: {', '.join(map(str, unknown[:5]))}")
    missing = sorted(set(planned) - set(ids))
    for r in rows:
        p = planned.get(r.get("run"))
        if p is None:
            continue
        text = (folder / p["scenario"]).read_text(encoding="utf-8")
        if hashlib.sha256(text.encode()).hexdigest() != p["scenario_sha256"]:
            problems.append(f"{p['scenario']}: differs from the manifest's hash")
    stored = man.get("code") or []
    problems += code.check(folder, stored)
    ok_rows = [r for r in rows if r.get("status") == "ok" and r.get("run") in planned]
    live = [r for r in ok_rows if r.get("recording")]
    sim = [r for r in ok_rows if not r.get("recording")]
    if sample is not None and sample < len(sim):
        idx = np.sort(np.random.default_rng(seed).choice(len(sim), size=sample, replace=False))
        sim = [sim[i] for i in idx]
    not_run, why = [], None
    base_dir = ""  # nothing is imported from the folder: its code only through code.load
    if sim and stored:
        need = code.untrusted(stored, folder)
        if need and not trust_code:
            raise BadInput(f"{folder}: {code.refusal(need)}")
        code.load(stored, folder, trust_code)  # here first: a stored source that fails is one line
    items = [(r["run"], (folder / planned[r["run"]]["scenario"]).read_text(encoding="utf-8"), "scenario", base_dir)
             for r in sim]
    parts = chunks(items, executor.workers if executor is not None else 1, False)
    got = {}
    # the simulator testbed simulate runs, whatever ran the campaign (the folder's code pinned in each worker)
    fn = functools.partial(rerun_chunk, stored=stored, folder=str(folder), trust_code=trust_code)
    results = executor.map(fn, parts) if executor is not None else map(fn, parts)
    for rs in results:
        for x in rs:
            got[x["run"]] = x
    for r in sim:
        x = got[r["run"]]
        if x.get("status") != "ok":
            differences.append({"run": r["run"], "column": "status", "table": r.get("status"),
                                "rerun": x.get("status"), "why": f"the re-run failed: {x.get('error')}"})
            continue
        d = _first_difference(r, x)
        if d:
            differences.append(d)
    for r in live:
        rec = folder / r["recording"]
        try:
            from ..runs.run import resimulate

            d = resimulate(str(rec), trust_code=trust_code)
            if not d.get("reproduced"):
                differences.append({"run": r["run"], "column": "recording", "table": str(rec),
                                    "rerun": d.get("verdict"), "why": f"{rec}: the re-simulation says "
                                                                      f"{d.get('verdict')}"})
                continue
            from ..runs.report import report

            d = _first_difference(r, report(str(rec), resimulate=0, trust_code=trust_code))
            if d:
                differences.append(d)
        except CodeNotTrusted as e:
            not_run.append(r["run"])
            why = why or str(e)
        except Exception as e:  # noqa: BLE001 - whatever stops the re-simulation is the row's reason
            differences.append({"run": r["run"], "column": "recording", "table": str(rec), "rerun": None,
                                "why": f"{rec}: the re-simulation failed: {type(e).__name__}: {e}"})
    if not_run and not sim and len(not_run) == len(ok_rows):
        raise BadInput(f"{folder}: nothing re-run: {why}")
    here = versions()
    vdiff = {k: {"manifest": v, "here": here.get(k)} for k, v in (man.get("packages") or {}).items()
             if here.get(k) != v}
    src = source_hash()
    return {"folder": str(folder), "checked_simulated": len(sim), "checked_live": len(live) - len(
                [r for r in live if r["run"] in not_run]), "rows": len(rows), "not_run": not_run, "not_run_why": why,
            "planned": len(planned), "missing": missing, "differences": differences, "problems": problems,
            "versions_differ": vdiff, "source_differs": src != man.get("source"),
            "python_differs": man.get("python") != sys.version.split()[0],
            "identical": not differences and not problems and not not_run}


def rerun_chunk(items: list, stored: list, folder: str, trust_code: bool) -> list[dict]:
    """``--verify`` on a worker: the folder's stored code pinned (``code.load``), then the chunk on the
    per-sample simulator."""
    code.load(stored, Path(folder), trust_code)
    return simulate_runs_per_sample(items)


def _first_difference(row: dict, rerun: dict) -> dict | None:
    """The first compared column where ``row`` and ``rerun`` differ, with both values (and the others)."""
    cols = [k for k in COMPARED if not _same(_norm(row.get(k)), _norm(rerun.get(k)))]
    if not cols:
        return None
    k = cols[0]
    why = f"{k}: table {row.get(k)!r}, re-run {rerun.get(k)!r}"
    if len(cols) > 1:
        why += f" (also {', '.join(cols[1:])})"
    return {"run": row["run"], "column": k, "table": row.get(k), "rerun": rerun.get(k), "columns": cols, "why": why}


def _norm(v):
    """A value as the table and a rerun both give it (a tuple, a list; numpy scalars)."""
    if isinstance(v, tuple):
        return list(v)
    if hasattr(v, "item") and not isinstance(v, (list, dict)):
        return v.item()
    return v


# ============================================================================ figure
#: the outcomes the figure draws: (key of ``summarize_group``, panel title)
PLOT_OUTCOMES = (("converged", "converged"), ("escaped", "escaped"))


def plot(path: str | Path, c: Campaign, summary: dict, size: str = "page") -> Path:
    """The rates of converged and of escaped runs (each with its 95 % Wilson interval) over the first axis of
    more than one value (not a seed, where there is another), one series per value of the second such axis
    (the others pooled).  In the one figure style (``testbed.common.figstyle``): categorical values are points side
    by side with their intervals (a numeric axis is joined by lines), the legend below the panels."""
    from ..common import figstyle
    from ..common.comparestats import wilson

    multi = [k for k, v in c.axes.items() if len(v) > 1]
    pref = [k for k in multi if not k.endswith("seed")] or multi
    if not pref:
        pref = list(c.axes)[:1]
    x_axis = pref[0] if pref else None
    series_axis = pref[1] if len(pref) > 1 else None
    rows = read_parquet(Path(summary["folder"]) / "runs.parquet") if "folder" in summary else []
    xs = c.axes[x_axis] if x_axis else [None]
    numeric = len(xs) > 1 and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in xs)
    series = c.axes[series_axis] if series_axis else [None]
    pos = [float(v) for v in xs if isinstance(v, (int, float))] if numeric else list(range(len(xs)))
    # side by side: a series' points are shifted by a fraction of the smallest gap between x positions
    gap = min((b - a for a, b in zip(sorted(pos), sorted(pos)[1:])), default=1.0) or 1.0
    width = 0.6 * gap
    shift = [(i - (len(series) - 1) / 2) * width / max(len(series), 1) for i in range(len(series))]
    panels = figstyle.panels(size, len(PLOT_OUTCOMES))
    with figstyle.style(size):
        fig, axs = figstyle.subplots(size, *panels, aspect=0.62 if size == "page" else 0.5, sharey=True)
        axs = axs.ravel()
        for ax, (key, title) in zip(axs, PLOT_OUTCOMES):
            for j, sv in enumerate(series):
                ys, lo, hi = [], [], []
                for xv in xs:
                    sel = [r for r in rows if r.get("status") == "ok" and (x_axis is None or _eq(r.get(x_axis), xv))
                           and (series_axis is None or _eq(r.get(series_axis), sv))]
                    k = sum(1 for r in sel if r.get(key))
                    w = wilson(k, len(sel))
                    rate = k / len(sel) if sel else math.nan
                    ys.append(rate)
                    lo.append(rate - w[0] if w else math.nan)
                    hi.append(w[1] - rate if w else math.nan)
                lab = "all runs" if series_axis is None else f"{series_axis} = {json.dumps(sv)}"
                ax.errorbar([p + shift[j] for p in pos], ys, yerr=[lo, hi], marker="o", capsize=2.5,
                            ls="-" if numeric else "none", color=figstyle.CYCLE[j % len(figstyle.CYCLE)], label=lab)
            if not numeric:
                ax.set_xticks(pos)
                ax.set_xticklabels([v if isinstance(v, str) else json.dumps(v) for v in xs])
                ax.set_xlim(min(pos) - 0.5 * gap, max(pos) + 0.5 * gap)
                ax.grid(False, axis="x")
            ax.set_xlabel(x_axis or "")
            ax.set_title(f"{title} (95 % Wilson interval)")
            ax.set_ylim(-0.03, 1.03)
        axs[0].set_ylabel("fraction of runs")
        figstyle.legend_below(fig, axes=axs[:1])
        return figstyle.save(fig, path)


def _eq(a, b) -> bool:
    return _same(_norm(a), _norm(b)) or (isinstance(a, str) and not isinstance(b, str) and a == json.dumps(b))
