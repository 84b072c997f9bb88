"""A campaign's folder: the journal (one JSON line per finished run, fsynced), the folder's files
(``campaign.toml``, ``scenarios/RUN.toml``, the user code beside them (``code``), ``manifest.json``),
the table (``runs.parquet``) and the summaries (``summary.json``, ``summary.md``: success rates with
their 95 % Wilson interval, medians).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import platform
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..common import comparestats
from ..common.errors import BadInput
from . import code
from .engine import outcome_counts, wilson
from .spec import OUTCOME_KEYS, SEED_KEYS, Campaign, PlannedRun

if TYPE_CHECKING:
    from ..scenario import Scenario

JOURNAL = "journal.jsonl"


# ============================================================================ the journal
def read_journal(folder: Path) -> dict:
    """run id -> its last complete row in ``folder``'s journal (a line cut by a kill is dropped,
    and cut off the file so that the next line starts clean)."""
    p = folder / JOURNAL
    rows: dict = {}
    if not p.exists():
        return rows
    data = p.read_bytes()
    good = 0
    for line in data.split(b"\n"):
        end = good + len(line) + 1
        if end > len(data):  # no newline: cut by a kill
            break
        try:
            r = json.loads(line)
        except ValueError:
            break
        rows[r["run"]] = r
        good = end
    if good < len(data):
        with open(p, "r+b") as f:
            f.truncate(good)
    return rows


class Journal:
    """Append-only, one JSON line per finished run, flushed and fsynced as it is written."""

    def __init__(self, folder: Path):
        self.f = open(folder / JOURNAL, "a", encoding="utf-8")  # closed by close()

    def write(self, row: dict) -> None:
        self.f.write(json.dumps(row, sort_keys=True, allow_nan=False) + "\n")
        self.f.flush()
        os.fsync(self.f.fileno())

    def close(self) -> None:
        self.f.close()


# ============================================================================ the folder
def default_dir(c: Campaign) -> Path:
    return Path("recordings") / f"campaign-{c.stem}"


def prepare(c: Campaign, runs: list[PlannedRun], folder: Path, base: Scenario) -> None:
    """Create ``folder`` (campaign copy, scenarios, manifest) or check that it holds this campaign."""
    cp = folder / "campaign.toml"
    man = folder / "manifest.json"
    if cp.exists():
        if cp.read_text(encoding="utf-8") != c.text:
            raise BadInput(f"{folder} holds another campaign ({c.path} changed since it started): give "
                           "another --out, or restore the file")
        try:
            old = json.loads(man.read_text())
        except (OSError, ValueError):
            raise BadInput(f"{folder}: manifest.json is missing or unreadable: give another --out") from None
        now = {r.id: r.sha256 for r in runs}
        was = {p["run"]: p["scenario_sha256"] for p in old.get("runs", [])}
        if now != was:
            raise BadInput(f"{folder} holds another campaign: the scenario {c.scenario!r} changed since it "
                           "started: give another --out, or restore the scenario")
        edited = code.changed(old.get("code") or [], runs)
        if edited:
            raise BadInput(f"{folder}: the module of {', '.join(edited)} changed since the campaign started (its "
                           "sha256 is in manifest.json): give another --out, or restore the module")
        return
    ours = {"scenarios", "scenario.toml", "manifest.json", "scenario.toml.tmp", "manifest.json.tmp"}
    if folder.exists() and any(p.name not in ours for p in folder.iterdir()):  # (ours: a start cut short)
        raise BadInput(f"{folder} exists and holds no campaign: give another --out")
    (folder / "scenarios").mkdir(parents=True, exist_ok=True)
    for r in runs:
        _write_atomic(folder / "scenarios" / f"{r.id}.toml", r.text)
    stored = code.collect(runs)
    code.write_copies(folder, stored, _write_atomic)  # beside the scenarios: they import it from there
    _write_atomic(folder / "scenario.toml", base.source)
    _write_atomic(man, json.dumps(manifest(c, runs, base, stored), indent=1) + "\n")
    _write_atomic(cp, c.text)  # last: a folder with campaign.toml is complete


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


PACKAGES = ("numpy", "scipy", "numba", "pyarrow", "eclipse-zenoh", "mcap", "protobuf", "rerun-sdk", "matplotlib",
            "dask", "distributed", "fmpy")


def versions() -> dict:
    """Installed versions of the packages a result may depend on (None: not installed)."""
    from importlib import metadata

    out: dict[str, str | None] = {}
    for p in PACKAGES:
        try:
            out[p] = metadata.version(p)
        except metadata.PackageNotFoundError:
            out[p] = None
    return out


def source_hash() -> str:
    """sha256 over the testbed's source (``testbed/``, ``plants/``, ``attackers/``: every .py and .toml)."""
    import attackers
    import plants

    h = hashlib.sha256()
    for root in (Path(__file__).parents[1], Path(plants.__file__).parent, Path(attackers.__file__).parent):
        for f in sorted(root.rglob("*")):
            if f.suffix in (".py", ".toml") and "__pycache__" not in f.parts:
                h.update(str(f.relative_to(root.parent)).encode() + b"\0" + f.read_bytes() + b"\0")
    return "sha256:" + h.hexdigest()


def manifest(c: Campaign, runs: list[PlannedRun], base: Scenario, stored: list[dict] | None = None) -> dict:
    """What the folder holds and what made it; ``code``: the user code of the runs (``code.collect``:
    each method's and plant's reference, module, class, source text, sha256 and its copy's path)."""
    __version__ = sys.modules["testbed"].__version__  # the package's face is a layer above: read, not imported

    return {"campaign": c.path.name, "campaign_sha256": c.sha256, "scenario": c.scenario,
            "runs_kind": c.runs, "repeat": c.repeat, "seed": c.seed, "axes": c.axes, "methods": c.methods,
            "code": code.collect(runs) if stored is None else stored,
            "seed_rule": "sha256(json([campaign seed, choice, sorted [[axis, value], ...], repeat]))[:8] big "
                         "endian mod 2**31, for a random choice no axis sets (unless the scenario seeds it "
                         "and repeat = 1)",
            "testbed": __version__, "source": source_hash(), "python": sys.version.split()[0],
            "implementation": platform.python_implementation(), "platform": platform.platform(),
            "machine": platform.machine(), "packages": versions(),
            "runs": [{"run": r.id, "point": r.point, "repeat": r.repeat, "axes": r.axes, "seeds": r.seeds,
                      "scenario": f"scenarios/{r.id}.toml", "scenario_sha256": r.sha256} for r in runs]}


# ============================================================================ the table and summaries
def ordered_rows(runs: list[PlannedRun], done: dict) -> list[dict]:
    """The journal's rows in the campaign's order, each with its axes and seeds (one per run, at most)."""
    out = []
    for r in runs:
        j = done.get(r.id)
        if j is None:
            continue
        row = {"run": r.id, "point": r.point, "repeat": r.repeat, **r.axes, **r.seeds}
        row.update({k: v for k, v in j.items() if k != "run"})
        out.append(row)
    return out


def columns(rows: list[dict], axes: list[str]) -> list[str]:
    cols = ["run", "point", "repeat", *axes, *SEED_KEYS, "status", "error", *OUTCOME_KEYS, "simulator", "wall_s"]
    for r in rows:
        for k in r:
            if k not in cols:
                cols.append(k)
    return cols


def write_parquet(path: Path, rows: list[dict], axes: list[str]) -> None:
    """``rows`` as a Parquet table (an axis of mixed values becomes JSON text); atomically."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    cols = columns(rows, axes)
    arrays = {}
    for k in cols:
        vals = [r.get(k) for r in rows]
        if k in axes and len({type(v) for v in vals if v is not None}) > 1:
            if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals):
                vals = [float(v) for v in vals if isinstance(v, (int, float))]  # all are (the test above)
            else:
                vals = [json.dumps(v) for v in vals]
        try:
            arrays[k] = pa.array(vals)
        except (pa.ArrowInvalid, pa.ArrowTypeError, TypeError):
            arrays[k] = pa.array([None if v is None else json.dumps(v) for v in vals])
    table = pa.table(arrays) if rows else pa.table({k: pa.array([], pa.null()) for k in cols})
    tmp = path.with_name(path.name + ".tmp")
    pq.write_table(table, tmp)
    os.replace(tmp, path)


def read_parquet(path: Path) -> list[dict]:
    import pyarrow.parquet as pq

    return pq.read_table(path).to_pylist()


def _median(v: Iterable[float | None]) -> float | None:
    v = sorted(x for x in v if x is not None and not (isinstance(x, float) and math.isnan(x)))
    if not v:
        return None
    n = len(v)
    return float(v[n // 2]) if n % 2 else (v[n // 2 - 1] + v[n // 2]) / 2


def summarize_group(rows: list[dict]) -> dict:
    ok = [r for r in rows if r.get("status") == "ok"]
    s = sum(1 for r in ok if r.get("converged"))
    w = wilson(s, len(ok))
    return {"runs": len(rows), "failed": len(rows) - len(ok), "n": len(ok), "successes": s,
            "success_rate": s / len(ok) if ok else None, "wilson95": None if w is None else list(w),
            **outcome_counts(ok),
            "median_final_norm": _median([r.get("final_norm") for r in ok]),
            "median_settle_samples": _median([r.get("settle_samples") for r in ok]),
            "median_max_norm": _median([r.get("max_norm") for r in ok]),
            "median_saturations": _median([r.get("saturations") for r in ok]),
            "median_samples_lost": _median([r.get("samples_lost") for r in ok]),
            "median_wall_s": _median([r.get("wall_s") for r in ok])}


def summarize(c: Campaign, runs: list[PlannedRun], rows: list[dict]) -> dict:
    """Per point and per value of each axis: the success rate (success = converged) with its 95 %
    Wilson score interval, how the runs ended (converged, bounded, escaped) and medians; the totals; the
    paired comparisons of each axis's values with its first (``tables.comparisons``)."""
    from .tables import comparisons
    keys = list(c.axes)
    by_point: dict = {}
    for r in rows:
        by_point.setdefault(r["point"], []).append(r)
    points = []
    seen = set()
    for run in runs:
        if run.point in seen:
            continue
        seen.add(run.point)
        points.append({"point": run.point, "axes": run.axes, **summarize_group(by_point.get(run.point, []))})
    by_axis: dict[str, list] = {}
    for k in keys:
        by_axis[k] = []
        for v in c.axes[k]:
            sel = [r for r in rows if r.get(k) == v]
            by_axis[k].append({"value": v, **summarize_group(sel)})
    return {"campaign": c.path.name, "scenario": c.scenario, "runs_kind": c.runs, "planned": len(runs),
            "done": len(rows), "failed": sum(1 for r in rows if r.get("status") != "ok"),
            "success": "converged (final ||x||_inf < converge_tol)", "interval": "95 % Wilson score",
            "outcomes": "converged; bounded: neither converged nor escaped by the end of the run (still "
                        "converging, or held in a ball); escaped: the run's escape verdict",
            "statistics": dict(comparestats.METHODS),
            "total": summarize_group(rows), "by_axis": by_axis, "points": points,
            "comparisons": comparisons(c.axes, rows),
            "partial_recordings": [p for r in rows if r.get("partial_recordings")
                                   for p in json.loads(r["partial_recordings"])]}


def _fmt(v: float | None, spec: str = ".3g") -> str:
    return "-" if v is None else format(v, spec)


def summary_md(s: dict) -> str:
    lines = [f"# Campaign {s['campaign']}", "",
             f"Scenario `{s['scenario']}`, {s['runs_kind']} runs: {s['done']} of {s['planned']} done, "
             f"{s['failed']} failed. Success: {s['success']}; interval: {s['interval']}.", ""]

    def table(title: str, head: str, groups: Iterable[tuple[str, Any]]) -> list[str]:
        out = [f"## {title}", "", f"| {head} | runs | success | rate | 95 % Wilson | bounded | escaped | median "
               "final norm | median max norm | median saturations |", "|---|---|---|---|---|---|---|---|---|---|"]
        for label, g in groups:
            w = g["wilson95"]
            out.append(f"| {label} | {g['runs']} | {g['successes']}/{g['n']} | {_fmt(g['success_rate'], '.3f')} | "
                       + ("-" if w is None else f"[{w[0]:.3f}, {w[1]:.3f}]")
                       + f" | {g.get('bounded', '-')} | {g['escaped']} | {_fmt(g['median_final_norm'])} | "
                       f"{_fmt(g['median_max_norm'])} | {_fmt(g['median_saturations'])} |")
        return out + [""]

    lines += table("All runs", "group", [("all", s["total"])])
    if s.get("comparisons"):
        from .tables import markdown

        lines += ["## Paired comparisons", "", markdown(s)]
    if s.get("partial_recordings"):
        lines += ["Partial recordings of interrupted live runs (kept aside; each run was run again): "
                  + ", ".join(f"`{p}`" for p in s["partial_recordings"]), ""]
    for k, groups in s["by_axis"].items():
        lines += table(f"By {k}", k, [(json.dumps(g["value"]), g) for g in groups])
    lines += table("By point", "point", [(", ".join(f"{k} = {json.dumps(v)}" for k, v in p["axes"].items()) or "-", p)
                                          for p in s["points"]])
    return "\n".join(lines)


def write_results(folder: Path, c: Campaign, runs: list[PlannedRun], done: dict) -> tuple[list[dict], dict]:
    """runs.parquet, summary.json, summary.md from the journal's rows."""
    rows = ordered_rows(runs, done)
    write_parquet(folder / "runs.parquet", rows, list(c.axes))
    s = summarize(c, runs, rows)
    _write_atomic(folder / "summary.json", json.dumps(s, indent=1) + "\n")
    _write_atomic(folder / "summary.md", summary_md(s) + "\n")
    return rows, s
