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

A campaign's folder (``DIR``: ``testbed.campaign.folder``) holds the campaign file, every run's
resolved scenario, the journal, the table and the summaries; a run's row comes from
``testbed.campaign.rows`` (its outcome columns equal ``testbed simulate --json`` of the run's scenario
bit for bit).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from .. import scenario as scenario_mod
from ..common import validate
from ..common.errors import BadInput
from ..record.tracereader import read_recording_trace
from ..scenario import methodswap
from ..scenario.sections import SECTIONS
from ..scenario.spec import ScenarioError
from ..scenario.write import to_toml
from . import engine

if TYPE_CHECKING:
    from ..scenario import Scenario

#: the outcome columns of a row: keys of ``testbed simulate --json`` (and ``testbed report --json``)
OUTCOME_KEYS = engine.OUTCOME_KEYS
#: columns every row has besides its axes and outcome
RUN_KEYS = ("run", "point", "repeat", "status", "error", "simulator", "wall_s")
#: the random choices a campaign seeds: column name -> dotted scenario key of the seed
SEED_KEYS = {"seeds.attack": "attack.seed", "seeds.sim_delay": "run.sim_delay.seed"}
#: the kind of a seed's table that draws random numbers (another kind keeps no seed)
RANDOM_KIND = {"attack.seed": "random", "run.sim_delay.seed": "uniform"}
#: keys of a campaign file
CAMPAIGN_KEYS = {"scenario", "runs", "repeat", "seed", "axes", "description", "methods"}


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
    methods: dict = field(default_factory=dict)   # [methods.NAME] params: method reference -> its params

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
    try:
        repeat = validate.count(d.get("repeat", 1), 1)
    except validate.Invalid as e:
        raise BadInput(f"{where}: repeat {e}") from None
    try:
        seed = validate.count(d.get("seed", 0), 0)
    except validate.Invalid as e:
        raise BadInput(f"{where}: seed {e}") from None
    axes = d.get("axes", {})
    if not isinstance(axes, dict):
        raise BadInput(f"{where}: [axes] must be a table of dotted scenario keys")
    flat = {}
    for k, v in _flatten(axes):
        if not isinstance(v, list) or not v:
            raise BadInput(f"{where}: axis {k!r} must be a non-empty list of values, got {v!r}")
        if len({json.dumps(x, sort_keys=True) for x in v}) != len(v):
            raise BadInput(f"{where}: axis {k!r} names a value twice")
        if k.split(".")[0] not in SECTIONS or "." not in k:
            raise BadInput(f"{where}: axis {k!r} is not a scenario key (section.key, e.g. \"attack.seed\"; "
                           f"sections: {', '.join(sorted(SECTIONS - {'name', 'description'}))})")
        flat[k] = v
    for k in flat:
        if k.startswith("method.") and k != "method.name" and k != "method.params" and not k.startswith("method.params."):
            raise BadInput(f"{where}: axis {k!r}: [method] has name and params (\"method.name\", "
                           "\"method.params.KEY\")")
    mt = d.get("methods", {})
    if not isinstance(mt, dict):
        raise BadInput(f"{where}: [methods] must be tables [methods.\"NAME\"] with params = {{...}}")
    methods = {}
    for name, t in mt.items():
        if not isinstance(t, dict) or set(t) - {"params"} or not isinstance(t.get("params", {}), dict):
            raise BadInput(f"{where}: [methods.{json.dumps(name)}] holds one key, params = {{...}} (the method's "
                           f"[method] params in this campaign), got {t!r}")
        methods[name] = dict(t.get("params", {}))
    desc = d.get("description", "")
    return Campaign(path, text, sc, runs, int(repeat), int(seed), flat, str(desc), methods)


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
class PlannedRun:
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

    def scenario(self) -> Scenario:
        return scenario_mod.loads(self.text, name=self.name, where=f"run {self.id}", base_dir=self.base_dir or None,
                                  read_recording_trace=read_recording_trace)


def derived_seed(campaign_seed: int, choice: str, axes: dict, repeat: int) -> int:
    """The seed of random choice ``choice`` (a dotted key) of the run with axis values ``axes`` and
    repeat ``repeat``: sha256 of ``json([seed, choice, [[key, value], ...] sorted by key, repeat])``,
    its first 8 bytes big endian, modulo 2**31."""
    doc = json.dumps([int(campaign_seed), choice, sorted([k, v] for k, v in axes.items()), int(repeat)],
                     sort_keys=True, separators=(",", ":"))
    return int.from_bytes(hashlib.sha256(doc.encode()).digest()[:8], "big") % (2 ** 31)


def base_scenario(c: Campaign) -> Scenario:
    """The campaign's scenario (a path is relative to the campaign file)."""
    ref = c.scenario
    p = Path(ref)
    if not p.is_absolute() and (ref.endswith(".toml") or "/" in ref):
        p = c.path.resolve().parent / p
        ref = str(p)
    try:
        return scenario_mod.load(ref, read_recording_trace=read_recording_trace)
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


def _resolve(base, axes: dict, seeds_from, methods: dict | None = None) -> tuple[dict, dict, str]:
    """The scenario dict of ``base`` with ``axes`` written in and the seeds of its random choices
    (``seeds_from(choice)`` where the campaign draws one, else None: keep); (data, seeds, note).

    The method (a ``method.name`` axis, else the scenario's own) is swapped in by the one rule
    (``scenario.swap_method``, as ``--method`` and ``testbed versus`` do) with its params: the scenario's
    own when it is the scenario's method, then its ``[methods.NAME] params`` (``methods``), then the
    ``method.params`` axes."""
    data = tomllib.loads(base.source)
    for k, v in axes.items():
        if not k.startswith("method."):
            _set(data, k, v)
    own, _ = methodswap.own_method(data)
    name = axes.get("method.name", own)
    given = dict((methods or {}).get(name, {}))
    if "method.params" in axes:
        if not isinstance(axes["method.params"], dict):
            raise BadInput(f"axis 'method.params' takes tables of params, got {axes['method.params']!r}")
        given.update(axes["method.params"])
    given.update({k[len("method.params."):]: v for k, v in axes.items() if k.startswith("method.params.")})
    note = ""
    if "method.name" in axes or given:
        try:
            data, note, _ = scenario_mod.swap_method(data, {"name": name, "params": given}, base.base_dir or None,
                                                     "scenario")
        except ScenarioError as e:
            raise BadInput(str(e)) from None
    seeds = {}
    att = data.get("attack")
    att = att if isinstance(att, dict) else {}
    if "attack.seed" in axes and att.get("kind") != "random":
        raise BadInput(f"varies nothing: the attack's kind {att.get('kind')!r} draws no random numbers "
                       "(only kind = 'random' does)")
    for column, key in SEED_KEYS.items():
        table = _get(data, key.rpartition(".")[0])
        if isinstance(table, dict) and table.get("kind") == RANDOM_KIND[key]:
            s = seeds_from(key) if key not in axes else None
            if s is not None:
                table["seed"] = s
            seeds[column] = table.get("seed")
        else:
            seeds[column] = None
    return data, seeds, note


def plan(c: Campaign, base: Scenario | None = None) -> tuple[list[PlannedRun], list[str]]:
    """Every run of campaign ``c``, resolved and validated (``BadInput`` naming the axis, the value and
    the reason for a bad one), and the notes (once per campaign)."""
    base = base_scenario(c) if base is None else base
    _check_methods(c, base)
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
                data, seeds, note = _resolve(base, axes, seeds_from, c.methods)
                text = to_toml(data)
                run = PlannedRun(f"p{p:05d}r{r}", p, r, axes, seeds, text, base.name, base.base_dir or "")
                run.scenario()
            except (BadInput, TypeError, ValueError) as e:
                raise BadInput(f"{c.path}: {_culprit(base, axes, c.methods)}: {_reason(e)}{_hint(c, e)}") from None
            if note and note not in notes:
                notes.append(note)
            runs.append(run)
    return runs, notes


def _check_methods(c: Campaign, base) -> None:
    """``[methods.NAME]``: each names a method the campaign runs, with params that method takes."""
    if not c.methods:
        return
    own = base.method.name
    ran = c.axes.get("method.name", [own])
    for name, params in c.methods.items():
        where = f"{c.path}: [methods.{json.dumps(name)}]"
        if name not in ran:
            raise BadInput(f"{where}: the campaign runs no method {name!r} (the methods it runs: "
                           f"{', '.join(repr(m) for m in ran)})")
        try:
            scenario_mod.swap_method(tomllib.loads(base.source), {"name": name, "params": params},
                                     base.base_dir or None, "scenario")
        except ScenarioError as e:
            raise BadInput(f"{where} params: {_reason(e)}") from None


def _hint(c: Campaign, e: Exception) -> str:
    """How to give one method its own params, when a ``method.params`` axis met a method without them."""
    if "has no parameter" in str(e) and "method.name" in c.axes and any(k.startswith("method.params") for k in c.axes):
        return " (a method.params axis applies to every method of the campaign: give one method its own params " \
               "with [methods.\"NAME\"] params = {...} in the campaign file)"
    return ""


def _valid(base, axes: dict, methods: dict | None = None) -> bool:
    try:
        data, _, _ = _resolve(base, axes, lambda _choice: None, methods)
        scenario_mod.from_dict(data, name=base.name, where="scenario", base_dir=base.base_dir or None,
                               read_recording_trace=read_recording_trace)
    except (BadInput, TypeError, ValueError):
        return False
    return True


def _culprit(base, axes: dict, methods: dict | None = None) -> str:
    """What a bad point's error names: the one axis whose value, left to the scenario's, makes the point
    valid ("axis 'plant.x0' value [9, 0]"), else the whole point."""
    for k, v in axes.items():
        if _valid(base, {a: b for a, b in axes.items() if a != k}, methods):
            return f"axis {k!r} value {json.dumps(v)}"
    return "the point " + ", ".join(f"{k} = {json.dumps(v)}" for k, v in axes.items())


def _reason(e: Exception) -> str:
    s = str(e)
    return s.split(": ", 1)[1] if s.startswith(("scenario: ", "run p")) else s
