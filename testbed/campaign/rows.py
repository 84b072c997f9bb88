"""A campaign's runs, one row each: a chunk of simulated runs (those that share a loop on the batch
kernel, ``testbed.campaign.batch``; the others on the per-sample simulator, as ``testbed simulate``
runs them), or one live run (``testbed run`` of its scenario, recorded).  A row's outcome columns are
``spec.OUTCOME_KEYS`` and ``settle_samples`` (``engine.settle_samples``); a run that crashes is a row with ``status = "failed"``.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from .. import scenario as scenario_mod
from ..record.tracereader import read_recording_trace
from . import engine
from .spec import OUTCOME_KEYS, PlannedRun


def simulate_runs(items: list, batch: bool = True) -> list[dict]:
    """Run a chunk of simulated runs (``(id, text, name, base_dir)``, data only); one row each (outcome keys
    of ``testbed simulate --json``, or ``status = "failed"``), in order.  ``batch``: the runs that share a
    loop go through the batch kernel in one call (``testbed.campaign.batch``), the others (and every run
    without ``batch``) through the per-sample simulator, as ``testbed simulate`` runs them."""
    from .batch import batch_key, run_group

    rows: dict = {}
    groups: dict = {}
    single = []
    for rid, text, name, base_dir in items:
        t0 = time.perf_counter()
        try:
            sc = scenario_mod.loads(text, name=name, where=f"run {rid}", base_dir=base_dir or None,
                                     read_recording_trace=read_recording_trace)
            key = batch_key(sc, text, base_dir) if batch else None
        except Exception as e:  # noqa: BLE001 - a crashed run is a row of its own (exit 1), the campaign goes on
            rows[rid] = _failed(rid, e, t0)
            continue
        if key is None:
            single.append((rid, sc, t0))
        else:
            groups.setdefault(key, []).append((rid, sc, t0))
    for g in groups.values():
        t0 = time.perf_counter()
        try:
            outs = run_group([sc for _, sc, _ in g])
        except Exception:  # noqa: BLE001 - each run of the group then shows its own error, per sample
            outs = [None] * len(g)
        wall = (time.perf_counter() - t0) / len(g)
        for (rid, sc, _), o in zip(g, outs):
            if o is None:
                single.append((rid, sc, time.perf_counter()))
            else:
                rows[rid] = {"run": rid, **o, "status": "ok", "error": None, "simulator": "batch",
                             "wall_s": wall}
    for rid, sc, t0 in single:
        try:
            s, res = engine.simulate_one(sc)  # the run engine's single run, as testbed versus runs it
            rows[rid] = {"run": rid, **engine.outcome(s),
                         "settle_samples": engine.settle_samples(res.x, res.x_final, sc.run.converge_tol),
                         "status": "ok", "error": None,
                         "simulator": "per-sample", "wall_s": time.perf_counter() - t0}
        except Exception as e:  # noqa: BLE001 - a crashed run is a row of its own (exit 1), the campaign goes on
            rows[rid] = _failed(rid, e, t0)
    return [rows[it[0]] for it in items]


def simulate_runs_per_sample(items: list) -> list[dict]:
    """:func:`simulate_runs` on the per-sample simulator only (what ``--verify`` re-runs)."""
    return simulate_runs(items, batch=False)


def _failed(rid: str, e: BaseException, t0: float) -> dict:
    return {"run": rid, **{k: None for k in OUTCOME_KEYS}, "status": "failed", "error": f"{type(e).__name__}: {e}",
            "simulator": None, "wall_s": time.perf_counter() - t0}


def live_run(run: PlannedRun, folder: Path, *, timeout: float | None = None) -> dict:
    """One live run (``testbed run`` of the run's scenario, recorded in ``folder``); its row."""
    import subprocess

    folder.mkdir(parents=True, exist_ok=True)
    sc_path = folder.parent / "scenarios" / f"{run.id}.toml"
    rec = folder / f"{run.id}.mcap"
    partial = sorted(str(p.relative_to(folder.parent)) for p in folder.glob(f"{run.id}.partial-*.mcap"))
    if rec.exists():  # a run killed mid-way: its partial recording is kept aside (and named in the row)
        aside = folder / f"{run.id}.partial-{time.time_ns()}.mcap"
        rec.rename(aside)
        partial.append(str(aside.relative_to(folder.parent)))
    t0 = time.perf_counter()
    cmd = [sys.executable, "-m", "testbed.cli", "run", str(sc_path), "--out", str(rec)]
    row: dict[str, Any] = {"run": run.id, "recording": str(rec.relative_to(folder.parent)),
           "partial_recordings": json.dumps(partial) if partial else None}
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        err = (p.stderr.strip().splitlines() or [""])[-1]
        if p.returncode not in (0, 1) or not rec.exists():
            raise RuntimeError(f"testbed run exited {p.returncode}: {err}")
        row.update(_live_outcome(rec), status="ok", error=None)
    except Exception as e:  # noqa: BLE001 - a failed live run is a row of its own (exit 1)
        row.update({k: None for k in OUTCOME_KEYS}, status="failed", error=f"{type(e).__name__}: {e}")
    row["wall_s"] = time.perf_counter() - t0
    return row


def _live_outcome(rec: Path) -> dict:
    from ..runs.report import report

    d = report(str(rec), resimulate=0)
    out = {k: d.get(k) for k in OUTCOME_KEYS}
    x = np.asarray(d.get("x") or [], dtype=float)
    if x.size and d.get("x_final") is not None:
        tol = (d.get("escape_criterion") or {}).get("x_tol", 1e-4)
        out["settle_samples"] = engine.settle_samples(x, np.asarray(d["x_final"], dtype=float), tol)
    else:
        out["settle_samples"] = None
    t = d.get("timing")
    out["timing"] = None if t is None else json.dumps(t, sort_keys=True)
    return out
