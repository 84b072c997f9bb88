"""Scenario files: one TOML file describes a run; loaded into frozen dataclasses.

Every bad value gets a ``ScenarioError`` naming the file, the key and what is
wrong.  The full schema is documented in docs/scenarios.md."""

from __future__ import annotations

import copy
import dataclasses
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from ..common.errors import BadInput
from ..loop import device
from ..loop.params import QuantizerParams
from . import methodswap, sections, traces
from . import overrides as scenariooverrides
from .spec import PlantSpec, RunSpec, Scenario, ScenarioError, _freeze

BUNDLED_DIR = "bundled"  # testbed/scenario/bundled/


MAX_SCENARIO_BYTES = 1 << 20   # a scenario is a page of TOML


def swap_method(data: dict, new: str | dict[str, Any], base_dir: str | None,
                where: str = "<scenario>") -> methodswap.Swapped:
    """``data`` with the method ``new`` swapped in by the one rule (``testbed.scenario.methodswap``: the scenario's
    own method keeps its params, dropped params and ignored ``[quantizer]`` keys are named in the note):
    (the document, the note without its ``note: ``, the method object built to check it)."""
    return methodswap.swap(data, new, base_dir or None, known_quantizer_keys=sections.KEYS["quantizer"],
                           where=where)


def from_dict(data: dict, *, name: str = "scenario", where: str = "<scenario>", source: str = "",
              base_dir: str | Path | None = None, check_fmu: bool = True, check_design: bool = True,
              swapped: methodswap.Swapped | None = None, document: dict | None = None,
              read_recording_trace: traces.RecordingTraceReader | None = None) -> Scenario:
    """Validate a parsed TOML document and build a Scenario.

    ``base_dir``: the scenario file's folder; a ``"module:Class"`` plant is imported
    from there first and an FMU path is relative to it.  ``check_fmu=False`` skips
    reading an FMU plant's file (a recording's scenario: the report needs only the model).
    ``swapped``: the swap that put ``data``'s method in (:func:`swap_method`): its note is kept on the Scenario
    and the method object it built is the Scenario's (built once).
    ``check_design=False`` skips the Schur check of a given K (scipy's expm): for the
    nodes of a run whose launcher checked the same text and overrides already.
    ``document``: what ``source`` parses to, when ``data`` is that with overrides applied (default ``data``);
    kept on the Scenario (``Scenario.document``), so that nothing parses ``source`` again.
    """
    doc = copy.deepcopy(document if document is not None else data) if source else {}
    base_dir = str(Path(base_dir).resolve()) if base_dir else ""
    ctx = sections.Ctx(where, read_recording_trace)
    name, description = sections.top_level(ctx, data, name)
    p = sections.plant_section(ctx, data, base_dir, check_fmu)
    model_obj, model = sections.model_section(ctx, data, p, base_dir)
    duration, tol, timing, deadline = sections.run_section(ctx, data)
    q = sections.quantizer_section(ctx, data, base_dir, p.n, p.x0, timing, swapped)
    T = q.T
    tm = sections.timing_section(ctx, data, T, deadline, timing, q.rule)
    dpar, L_u = sections.delay_rule(ctx, q, model_obj, deadline, tm)
    qp = QuantizerParams(T=T, M=q.M, L=q.L, E0=q.E0, mode=q.mode, zoom_out=q.zoom_out, E_min=q.E_min, rule=q.rule,
                         **dpar)
    if duration < T:
        raise ctx.err("run.duration", f"shorter than one sampling period T = {T}")
    run = RunSpec(duration=duration, converge_tol=tol, timing=timing, deadline=deadline,
                  loss_fraction=tm.loss_fraction, actuation=tm.actuation, delay=tm.delay, delay_lost=tm.delay_lost,
                  sim_delay=tm.sim_delay)
    ctrl = sections.controller_section(ctx, data, model_obj, p.n, p.m, T, check_design)
    attack = sections.attack_section(ctx, data, base_dir)
    flow = sections.flow_section(ctx, data)
    network = sections.network_section(data, where)
    pt = p.table
    spec = PlantSpec(p.name, _freeze(p.params), p.x0, ref=pt.get("name", ""), base_dir=base_dir, fmu=p.fmu,
                     device=device.parse(pt, p.n, p.m, ctx.err, fmu=p.fmu is not None)).with_built(p.plant)
    sc = Scenario(name=name, plant=spec, quantizer=qp,
                  controller=ctrl, attack=attack, run=run, flow=flow, source=source, path=where,
                  description=description, model=model, L_u=L_u, base_dir=base_dir, method=q.method,
                  method_note=f"note: {swapped.note}" if swapped and swapped.note else "", network=network, doc=doc)
    # the attack generator validates its own parameters
    try:
        sc.attack.schedule(T, max(duration, T))
    except (ValueError, TypeError, KeyError) as e:
        raise ctx.err("attack", str(e)) from None
    return sc


def bundled_names() -> list[str]:
    d = resources.files(__name__).joinpath(BUNDLED_DIR)
    return sorted(p.name[:-5] for p in d.iterdir() if p.name.endswith(".toml"))


def load(ref: str | Path, *, check_design: bool = True, overrides: dict | None = None,
         read_recording_trace: traces.RecordingTraceReader | None = None) -> Scenario:
    """Load a scenario from a file path or a bundled name (``paper``, ``paper-escape``, ...), with run-time
    ``overrides`` applied as in :func:`with_overrides` (the text parsed and the Scenario built once);
    ``read_recording_trace``: how a recording named as an ``[attack]`` trace is read (``testbed.scenario.traces``)."""
    p = Path(ref)
    if p.suffix == ".toml" or p.exists():
        if not p.is_file():
            raise ScenarioError(f"{ref}: no such scenario file (bundled: {', '.join(bundled_names())})")
        try:
            if p.stat().st_size > MAX_SCENARIO_BYTES:
                raise ScenarioError(f"{ref}: {p.stat().st_size} bytes is not a scenario file "
                                    f"(at most {MAX_SCENARIO_BYTES // 1024} kB)")
            text = p.read_text(encoding="utf-8")
        except UnicodeDecodeError as e:
            raise ScenarioError(f"{ref}: not a text (UTF-8) file: {e.reason} at byte {e.start}") from None
        except OSError as e:
            raise ScenarioError(f"{ref}: {e.strerror or e}") from None
        name, where, base_dir = p.stem, str(p), str(p.resolve().parent)
    else:
        res = resources.files(__name__).joinpath(BUNDLED_DIR, f"{ref}.toml")
        if not res.is_file():
            raise ScenarioError(f"{ref!r} is neither a scenario file nor a bundled scenario "
                                f"(bundled: {', '.join(bundled_names())})")
        text = res.read_text()
        name, where, base_dir = str(ref), f"bundled:{ref}", None
    return loads(text, name=name, where=where, base_dir=base_dir, check_design=check_design, overrides=overrides,
                 read_recording_trace=read_recording_trace)


def loads(text: str, *, name: str = "scenario", where: str = "<string>",
          base_dir: str | Path | None = None, check_fmu: bool = True, check_design: bool = True,
          overrides: dict | None = None,
          read_recording_trace: traces.RecordingTraceReader | None = None) -> Scenario:
    """A scenario from TOML text; ``base_dir``, ``check_fmu``, ``check_design``, ``read_recording_trace`` as in
    ``from_dict``;
    ``overrides`` as in :func:`with_overrides`, applied to the parsed document before the one build."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ScenarioError(f"{where}: not valid TOML: {e}") from None
    over = scenariooverrides.checked(overrides, name)
    build: dict[str, Any] = dict(name=name, source=text, base_dir=base_dir, check_fmu=check_fmu,
                                 check_design=check_design, read_recording_trace=read_recording_trace)
    if not over:
        return from_dict(data, where=where, **build)
    where_o = f"{where} (with run overrides)"
    try:
        bd = str(Path(base_dir).resolve()) if base_dir else None
        edited, swapped = scenariooverrides.apply(copy.deepcopy(data), over,
                                                  lambda d, m: swap_method(d, m, bd, where_o))
        sc = from_dict(edited, where=where_o, swapped=swapped, document=data, **build)
    except ScenarioError as e:  # the file's own error first (raised here), else the overrides' fault
        base = from_dict(data, where=where, **build)
        raise BadInput(scenariooverrides.hint(str(e), base.name, base.x0, over)) from None
    return dataclasses.replace(sc, path=where)


#: run-time overrides a scenario accepts (``testbed run|simulate --duration ...``): name -> (table, key)
OVERRIDES = scenariooverrides.OVERRIDES


def unseeded(sc: Scenario) -> bool:
    """A random attack without a seed: the run must draw one, print it and store it (``with_seed``)."""
    return sc.attack.kind == "random" and "seed" not in sc.attack.params_dict


def with_seed(sc: Scenario, overrides: dict) -> tuple[Scenario, dict]:
    """``sc`` with a drawn attack seed when it has none (the overrides then carry it, so a
    recording repeats it); otherwise unchanged."""
    if not unseeded(sc) or overrides.get("seed") is not None:
        return sc, overrides
    import secrets

    over = dict(overrides, seed=secrets.randbelow(2**31))
    return with_overrides(sc, over), over  # all of them: with_overrides starts from the file


def with_overrides(sc: Scenario, overrides: dict | None, *, check_design: bool = True,
                   read_recording_trace: traces.RecordingTraceReader | None = None) -> Scenario:
    """``sc`` with run-time overrides applied and validated as if written in its file.

    They apply to the file (``sc.source``, parsed once: ``sc.document()``), not on top of overrides
    applied before: pass all of them.  ``sc.source`` stays the original text; recordings store the
    overrides beside it.  A trace the scenario read is kept as read (``read_recording_trace``: for an
    ``attack`` override naming another).
    A bad override raises ``BadInput`` (not ``ScenarioError``: the file is fine) whose message
    names the overrides and says what to change (:func:`testbed.scenario.overrides.hint`).
    """
    over = scenariooverrides.checked(overrides, sc.name)
    if not over:
        return sc
    where = f"{sc.path} (with run overrides)"
    data = sc.document()
    if sc.attack.kind == "trace" and "attack" not in over:  # the trace as read, not its source read again
        data["attack"] = {**data["attack"], **{k: list(v) if isinstance(v, tuple) else v
                                               for k, v in sc.attack.params_dict.items()}}
    try:
        data, swapped = scenariooverrides.apply(data, over,
                                                lambda d, m: swap_method(d, m, sc.base_dir or None, where))
        sc2 = from_dict(data, name=sc.name, where=where, source=sc.source, document=sc.doc or None,
                        base_dir=sc.base_dir or None, check_fmu=sc.plant.fmu is None or sc.plant.fmu.checked,
                        check_design=check_design, swapped=swapped, read_recording_trace=read_recording_trace)
    except ScenarioError as e:
        raise BadInput(scenariooverrides.hint(str(e), sc.name, sc.x0, over)) from None
    return dataclasses.replace(sc2, path=sc.path)
