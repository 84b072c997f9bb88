"""Campaigns: the product of axes over one scenario, simulated or live, one row per run, resumable.

A campaign file names a scenario, whether its runs are simulated or live, how often each point
runs (``repeat``), the campaign's seed and ``[axes]``: dotted scenario keys with their values.
The campaign is the product of the axes; a *run* is one point and one repeat.  Every run is
resolved to a complete scenario file (the axes written in, the seeds drawn) and validated before
anything runs.

Seeds (the rule, :func:`derived_seed`): a random choice of the scenario -- the random attack's
``[attack] seed``, a uniform ``[run] sim_delay``'s ``seed`` -- that no axis sets keeps the
scenario's seed when it has one and ``repeat = 1``; otherwise it draws
``sha256(json([campaign seed, choice, axis values, repeat]))`` (the first 8 bytes, big endian,
modulo 2**31), so that a run's seeds depend on what the run is, not on its position.

A campaign's folder (``DIR``) holds the campaign file (``campaign.toml``), every run's resolved
scenario (``scenarios/RUN.toml``), the journal (``journal.jsonl``: one JSON line per finished run,
flushed and fsynced as the run ends), the table written from the journal (``runs.parquet``), the
summaries (``summary.json``, ``summary.md``) and ``manifest.json`` (versions, hashes, seeds).

A row's outcome columns equal ``testbed simulate --json`` of the run's scenario bit for bit: the runs
that share a loop go through the batch kernel together (``testbed.campaign.batch``, equal to the
per-sample simulator bit for bit), the others through the per-sample simulator as ``testbed simulate``.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import os
import platform
import sys
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from .. import scenario as scenario_mod
from ..errors import BadInput
from ..scenariospec import ScenarioError
from ..scenariowrite import to_toml
from . import engine
from .engine import wilson

#: the outcome columns of a row: keys of ``testbed simulate --json`` (and ``testbed report --json``)
OUTCOME_KEYS = engine.OUTCOME_KEYS
#: columns every row has besides its axes and outcome
RUN_KEYS = ("run", "point", "repeat", "status", "error", "simulator", "wall_s")
#: the random choices a campaign seeds: column name -> dotted scenario key of the seed
SEED_KEYS = {"seeds.attack": "attack.seed", "seeds.sim_delay": "run.sim_delay.seed"}
#: keys of a campaign file
CAMPAIGN_KEYS = {"scenario", "runs", "repeat", "seed", "axes", "description"}
JOURNAL = "journal.jsonl"


# ============================================================================ the campaign file
@dataclass(frozen=True)
class Campaign:
    """A parsed campaign file."""

    path: Path
    text: str
    scenario: str
    runs: str = "simulated"
    repeat: int = 1
    seed: int = 0
    axes: dict = field(default_factory=dict)
    description: str = ""

    @property
    def sha256(self) -> str:
        return hashlib.sha256(self.text.encode()).hexdigest()

    @property
    def stem(self) -> str:
        return self.path.stem


def parse(path: str | Path) -> Campaign:
    """Read and check a campaign file (``BadInput``: one line naming the file and the key)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise BadInput(f"{p}: not a text (UTF-8) file") from None
    except OSError as e:
        raise BadInput(f"{p}: {e.strerror or e}") from None
    return loads(text, p)


def loads(text: str, path: Path) -> Campaign:
    where = str(path)
    try:
        d = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise BadInput(f"{where}: not valid TOML: {e}") from None
    bad = sorted(set(d) - CAMPAIGN_KEYS)
    if bad:
        raise BadInput(f"{where}: unknown key(s) {bad}; a campaign has {sorted(CAMPAIGN_KEYS)}")
    sc = d.get("scenario")
    if not isinstance(sc, str) or not sc:
        raise BadInput(f"{where}: scenario must be a bundled scenario's name or a path, got {sc!r}")
    runs = d.get("runs", "simulated")
    if runs not in ("simulated", "live"):
        raise BadInput(f"{where}: runs must be \"simulated\" or \"live\", got {runs!r}")
    repeat = d.get("repeat", 1)
    if isinstance(repeat, bool) or not isinstance(repeat, int) or repeat < 1:
        raise BadInput(f"{where}: repeat must be an integer >= 1, got {repeat!r}")
    seed = d.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise BadInput(f"{where}: seed must be an integer >= 0, got {seed!r}")
    axes = d.get("axes", {})
    if not isinstance(axes, dict):
        raise BadInput(f"{where}: [axes] must be a table of dotted scenario keys")
    flat = {}
    for k, v in _flatten(axes):
        if not isinstance(v, list) or not v:
            raise BadInput(f"{where}: axis {k!r} must be a non-empty list of values, got {v!r}")
        if len({json.dumps(x, sort_keys=True) for x in v}) != len(v):
            raise BadInput(f"{where}: axis {k!r} names a value twice")
        if k.split(".")[0] not in scenario_mod._SECTIONS or "." not in k:
            raise BadInput(f"{where}: axis {k!r} is not a scenario key (section.key, e.g. \"attack.seed\"; "
                           f"sections: {', '.join(sorted(scenario_mod._SECTIONS - {'name', 'description'}))})")
        flat[k] = v
    desc = d.get("description", "")
    return Campaign(path, text, sc, runs, int(repeat), int(seed), flat, str(desc))


def _flatten(d: dict, prefix: str = ""):
    """(dotted key, value) of a table: quoted dotted keys ("plant.x0") and nested tables alike."""
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and k != "params" and not key.endswith(".params"):
            yield from _flatten(v, key + ".")
        else:
            yield key, v


# ============================================================================ runs
@dataclass(frozen=True)
class Run:
    """One run: point ``point`` (its axis values ``axes``), repeat ``repeat``, its resolved scenario."""

    id: str
    point: int
    repeat: int
    axes: dict
    seeds: dict
    text: str          # the resolved scenario (TOML)
    name: str          # the scenario's name
    base_dir: str      # where a "module:Class" plant or method is imported from

    @property
    def sha256(self) -> str:
        return hashlib.sha256(self.text.encode()).hexdigest()

    def scenario(self):
        return scenario_mod.loads(self.text, name=self.name, where=f"run {self.id}", base_dir=self.base_dir or None)


def derived_seed(campaign_seed: int, choice: str, axes: dict, repeat: int) -> int:
    """The seed of random choice ``choice`` (a dotted key) of the run with axis values ``axes`` and
    repeat ``repeat``: sha256 of ``json([seed, choice, [[key, value], ...] sorted by key, repeat])``,
    its first 8 bytes big endian, modulo 2**31."""
    doc = json.dumps([int(campaign_seed), choice, sorted([k, v] for k, v in axes.items()), int(repeat)],
                     sort_keys=True, separators=(",", ":"))
    return int.from_bytes(hashlib.sha256(doc.encode()).digest()[:8], "big") % (2 ** 31)


def base_scenario(c: Campaign):
    """The campaign's scenario (a path is relative to the campaign file)."""
    ref = c.scenario
    p = Path(ref)
    if not p.is_absolute() and (ref.endswith(".toml") or "/" in ref):
        p = c.path.resolve().parent / p
        ref = str(p)
    try:
        return scenario_mod.load(ref)
    except ScenarioError as e:
        raise BadInput(f"{c.path}: scenario: {e}") from None


def _set(data: dict, key: str, value) -> None:
    parts = key.split(".")
    t = data
    for p in parts[:-1]:
        nxt = t.get(p)
        if not isinstance(nxt, dict):
            nxt = {}
            t[p] = nxt
        t = nxt
    t[parts[-1]] = value


def _get(data: dict, key: str):
    t = data
    for p in key.split("."):
        if not isinstance(t, dict) or p not in t:
            return None
        t = t[p]
    return t


def _resolve(base, axes: dict, seeds_from) -> tuple[dict, dict, str]:
    """The scenario dict of ``base`` with ``axes`` written in and the seeds of its random choices
    (``seeds_from(choice)`` where the campaign draws one, else None: keep); (data, seeds, note)."""
    data = tomllib.loads(base.source)
    note = ""
    if "method.name" in axes:  # swaps the method as --method does (first: a method.params axis goes into it)
        data["method"] = {"name": axes["method.name"]}
    for k, v in axes.items():
        if k != "method.name":
            _set(data, k, v)
    if "method.name" in axes:
        from .. import methods

        try:
            m = methods.make(str(axes["method.name"]), base.base_dir or None, _get(data, "method.params") or {})
        except methods.MethodError as e:
            raise BadInput(str(e)) from None
        except (TypeError, ValueError) as e:
            raise BadInput(str(e)) from None
        used = {"T", *m.uses}
        qt = data.get("quantizer", {})
        unused = [k for k in qt if k not in used] if isinstance(qt, dict) else []
        if unused:
            note = f"method {axes['method.name']!r} ignores [quantizer] {', '.join(unused)} of the scenario"
            data["quantizer"] = {k: v for k, v in qt.items() if k in used}
    seeds = {}
    att = data.get("attack") if isinstance(data.get("attack"), dict) else {}
    if "attack.seed" in axes and att.get("kind") != "random":
        raise BadInput(f"varies nothing: the attack's kind {att.get('kind')!r} draws no random numbers "
                       "(only kind = 'random' does)")
    if att.get("kind") == "random":
        s = seeds_from("attack.seed") if "attack.seed" not in axes else None
        if s is not None:
            att["seed"] = s
        seeds["seeds.attack"] = att.get("seed")
    else:
        seeds["seeds.attack"] = None
    sd = _get(data, "run.sim_delay")
    if isinstance(sd, dict) and sd.get("kind") == "uniform":
        s = seeds_from("run.sim_delay.seed") if "run.sim_delay.seed" not in axes else None
        if s is not None:
            sd["seed"] = s
        seeds["seeds.sim_delay"] = sd.get("seed")
    else:
        seeds["seeds.sim_delay"] = None
    return data, seeds, note


def plan(c: Campaign, base=None) -> tuple[list[Run], list[str]]:
    """Every run of campaign ``c``, resolved and validated (``BadInput`` naming the axis, the value and
    the reason for a bad one), and the notes (once per campaign)."""
    base = base_scenario(c) if base is None else base
    keys = list(c.axes)
    runs, notes = [], []
    for p, values in enumerate(itertools.product(*(c.axes[k] for k in keys))):
        axes = dict(zip(keys, values))
        for r in range(c.repeat):
            def seeds_from(choice, axes=axes, r=r):
                if _get(tomllib.loads(base.source), choice) is not None and c.repeat == 1:
                    return None
                return derived_seed(c.seed, choice, axes, r)

            try:
                data, seeds, note = _resolve(base, axes, seeds_from)
                text = to_toml(data)
                run = Run(f"p{p:05d}r{r}", p, r, axes, seeds, text, base.name, base.base_dir or "")
                run.scenario()
            except (BadInput, TypeError, ValueError) as e:
                raise BadInput(f"{c.path}: {_culprit(base, axes)}: {_reason(e)}") from None
            if note and note not in notes:
                notes.append(note)
            runs.append(run)
    return runs, notes


def _valid(base, axes: dict) -> bool:
    try:
        data, _, _ = _resolve(base, axes, lambda _choice: None)
        scenario_mod.from_dict(data, name=base.name, where="scenario", base_dir=base.base_dir or None)
    except (BadInput, TypeError, ValueError):
        return False
    return True


def _culprit(base, axes: dict) -> str:
    """What a bad point's error names: the one axis whose value, left to the scenario's, makes the point
    valid ("axis 'plant.x0' value [9, 0]"), else the whole point."""
    for k, v in axes.items():
        if _valid(base, {a: b for a, b in axes.items() if a != k}):
            return f"axis {k!r} value {json.dumps(v)}"
    return "the point " + ", ".join(f"{k} = {json.dumps(v)}" for k, v in axes.items())


def _reason(e: Exception) -> str:
    s = str(e)
    return s.split(": ", 1)[1] if s.startswith(("scenario: ", "run p")) else s


# ============================================================================ running
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
            sc = scenario_mod.loads(text, name=name, where=f"run {rid}", base_dir=base_dir or None)
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
            s, _ = engine.simulate_one(sc)  # the run engine's single run, as testbed versus runs it
            rows[rid] = {"run": rid, **engine.outcome(s), "status": "ok", "error": None,
                         "simulator": "per-sample", "wall_s": time.perf_counter() - t0}
        except Exception as e:  # noqa: BLE001 - a crashed run is a row of its own (exit 1), the campaign goes on
            rows[rid] = _failed(rid, e, t0)
    return [rows[it[0]] for it in items]


def simulate_runs_per_sample(items: list) -> list[dict]:
    """:func:`simulate_runs` on the per-sample simulator only (what ``--verify`` re-runs)."""
    return simulate_runs(items, batch=False)


def _failed(rid, e, t0) -> dict:
    return {"run": rid, **{k: None for k in OUTCOME_KEYS}, "status": "failed", "error": f"{type(e).__name__}: {e}",
            "simulator": None, "wall_s": time.perf_counter() - t0}


def live_run(run: Run, folder: Path, *, timeout: float | None = None) -> dict:
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
    row = {"run": run.id, "recording": str(rec.relative_to(folder.parent)),
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
    from ..report import report

    d = report(str(rec), resimulate=0)
    out = {k: d.get(k) for k in OUTCOME_KEYS}
    t = d.get("timing")
    out["timing"] = None if t is None else json.dumps(t, sort_keys=True)
    return out


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


def prepare(c: Campaign, runs: list[Run], folder: Path, base) -> None:
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
        return
    ours = {"scenarios", "scenario.toml", "manifest.json", "scenario.toml.tmp", "manifest.json.tmp"}
    if folder.exists() and any(p.name not in ours for p in folder.iterdir()):  # (ours: a start cut short)
        raise BadInput(f"{folder} exists and holds no campaign: give another --out")
    (folder / "scenarios").mkdir(parents=True, exist_ok=True)
    for r in runs:
        _write_atomic(folder / "scenarios" / f"{r.id}.toml", r.text)
    _write_atomic(folder / "scenario.toml", base.source)
    _write_atomic(man, json.dumps(manifest(c, runs, base), indent=1) + "\n")
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

    out = {}
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


def manifest(c: Campaign, runs: list[Run], base) -> dict:
    __version__ = sys.modules["testbed"].__version__  # the package's face is a layer above: read, not imported

    return {"campaign": c.path.name, "campaign_sha256": c.sha256, "scenario": c.scenario,
            "runs_kind": c.runs, "repeat": c.repeat, "seed": c.seed, "axes": c.axes,
            "seed_rule": "sha256(json([campaign seed, choice, sorted [[axis, value], ...], repeat]))[:8] big "
                         "endian mod 2**31, for a random choice no axis sets (unless the scenario seeds it "
                         "and repeat = 1)",
            "testbed": __version__, "source": source_hash(), "python": sys.version.split()[0],
            "implementation": platform.python_implementation(), "platform": platform.platform(),
            "machine": platform.machine(), "packages": versions(),
            "runs": [{"run": r.id, "point": r.point, "repeat": r.repeat, "axes": r.axes, "seeds": r.seeds,
                      "scenario": f"scenarios/{r.id}.toml", "scenario_sha256": r.sha256} for r in runs]}


# ============================================================================ the table and summaries
def ordered_rows(runs: list[Run], done: dict) -> list[dict]:
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
                vals = [float(v) for v in vals]
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


def _median(v):
    v = sorted(x for x in v if x is not None and not (isinstance(x, float) and math.isnan(x)))
    if not v:
        return None
    n = len(v)
    return float(v[n // 2]) if n % 2 else (v[n // 2 - 1] + v[n // 2]) / 2


def _group(rows: list[dict]) -> dict:
    ok = [r for r in rows if r.get("status") == "ok"]
    s = sum(1 for r in ok if r.get("converged"))
    w = wilson(s, len(ok))
    return {"runs": len(rows), "failed": len(rows) - len(ok), "n": len(ok), "successes": s,
            "success_rate": s / len(ok) if ok else None, "wilson95": None if w is None else list(w),
            "escaped": sum(1 for r in ok if r.get("escaped")),
            "median_final_norm": _median([r.get("final_norm") for r in ok]),
            "median_max_norm": _median([r.get("max_norm") for r in ok]),
            "median_saturations": _median([r.get("saturations") for r in ok]),
            "median_samples_lost": _median([r.get("samples_lost") for r in ok]),
            "median_wall_s": _median([r.get("wall_s") for r in ok])}


def summarize(c: Campaign, runs: list[Run], rows: list[dict]) -> dict:
    """Per point and per value of each axis: the success rate (success = converged) with its 95 %
    Wilson score interval, and medians; the totals."""
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
        points.append({"point": run.point, "axes": run.axes, **_group(by_point.get(run.point, []))})
    by_axis = {}
    for k in keys:
        by_axis[k] = []
        for v in c.axes[k]:
            sel = [r for r in rows if r.get(k) == v]
            by_axis[k].append({"value": v, **_group(sel)})
    return {"campaign": c.path.name, "scenario": c.scenario, "runs_kind": c.runs, "planned": len(runs),
            "done": len(rows), "failed": sum(1 for r in rows if r.get("status") != "ok"),
            "success": "converged (final ||x||_inf < converge_tol)", "interval": "95 % Wilson score",
            "total": _group(rows), "by_axis": by_axis, "points": points,
            "partial_recordings": [p for r in rows if r.get("partial_recordings")
                                   for p in json.loads(r["partial_recordings"])]}


def _fmt(v, spec=".3g"):
    return "-" if v is None else format(v, spec)


def summary_md(s: dict) -> str:
    lines = [f"# Campaign {s['campaign']}", "",
             f"Scenario `{s['scenario']}`, {s['runs_kind']} runs: {s['done']} of {s['planned']} done, "
             f"{s['failed']} failed. Success: {s['success']}; interval: {s['interval']}.", ""]

    def table(title, head, groups):
        out = [f"## {title}", "", f"| {head} | runs | success | rate | 95 % Wilson | escaped | median final "
               "norm | median max norm | median saturations |", "|---|---|---|---|---|---|---|---|---|"]
        for label, g in groups:
            w = g["wilson95"]
            out.append(f"| {label} | {g['runs']} | {g['successes']}/{g['n']} | {_fmt(g['success_rate'], '.3f')} | "
                       + ("-" if w is None else f"[{w[0]:.3f}, {w[1]:.3f}]")
                       + f" | {g['escaped']} | {_fmt(g['median_final_norm'])} | {_fmt(g['median_max_norm'])} | "
                       f"{_fmt(g['median_saturations'])} |")
        return out + [""]

    lines += table("All runs", "group", [("all", s["total"])])
    if s.get("partial_recordings"):
        lines += ["Partial recordings of interrupted live runs (kept aside; each run was run again): "
                  + ", ".join(f"`{p}`" for p in s["partial_recordings"]), ""]
    for k, groups in s["by_axis"].items():
        lines += table(f"By {k}", k, [(json.dumps(g["value"]), g) for g in groups])
    lines += table("By point", "point", [(", ".join(f"{k} = {json.dumps(v)}" for k, v in p["axes"].items()) or "-", p)
                                          for p in s["points"]])
    return "\n".join(lines)


def write_results(folder: Path, c: Campaign, runs: list[Run], done: dict) -> tuple[list[dict], dict]:
    """runs.parquet, summary.json, summary.md from the journal's rows."""
    rows = ordered_rows(runs, done)
    write_parquet(folder / "runs.parquet", rows, list(c.axes))
    s = summarize(c, runs, rows)
    _write_atomic(folder / "summary.json", json.dumps(s, indent=1) + "\n")
    _write_atomic(folder / "summary.md", summary_md(s) + "\n")
    return rows, s
