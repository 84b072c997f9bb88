"""The scenario a recording stores, and rebuilding it: the TOML with the run's overrides, the plant
and model modules (imported as the run did, or from the stored source), the resolved values."""

from __future__ import annotations

import json
import platform
import sys
from pathlib import Path

from .topics import FORMAT_VERSION


def software_versions() -> dict[str, str]:
    from importlib import metadata

    out = {"python": sys.version.split()[0], "platform": platform.platform(), "format": FORMAT_VERSION}
    for dist in ("dos-testbed", "numpy", "scipy", "numba", "eclipse-zenoh", "mcap", "protobuf", "rerun-sdk"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "not installed"
    try:
        import subprocess

        root = Path(__file__).resolve().parents[2]
        if (root / ".git").exists():
            r = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True,
                               text=True, timeout=5)
            if r.returncode == 0:
                out["git"] = r.stdout.strip()
    except Exception:  # noqa: BLE001 - git is optional
        pass
    return out


def _module_keys(prefix: str, ref: str, info: dict) -> dict[str, str]:
    bundled = info.get("module", "").startswith(("plants.", "testbed."))  # ships with the testbed (testbed.software)
    return {f"{prefix}_ref": ref, f"{prefix}_module": info.get("module", ""), f"{prefix}_class": info.get("class", ""),
            f"{prefix}_file": info.get("file", ""), f"{prefix}_source": "" if bundled else info.get("source", ""),
            f"{prefix}_sha256": info.get("sha256", "")}


def scenario_metadata(sc, ref: str | None = None) -> dict[str, str]:
    """The ``testbed.scenario`` record: the scenario's name, TOML, reference, folder, plant and model modules."""
    from plants.refs import source_info

    out = {"name": sc.name, "toml": sc.source or "", "ref": ref or sc.name, "base_dir": sc.base_dir or ""}
    fmu = sc.plant.fmu is not None
    try:
        info = sc.plant.source_info()
    except (ValueError, AttributeError):
        info = {}
    out.update(_module_keys("plant", "" if fmu else (sc.plant.ref or sc.plant.name), info))
    model = sc.model
    if model is not None and (fmu or model.name != sc.plant.ref):  # a [model] that is not the plant's class
        import plants

        try:
            minfo = source_info(plants.resolve(model.name, model.base_dir or None))
        except ValueError:
            minfo = {}
        out.update(_module_keys("model", model.name, minfo))
    try:
        meth = sc.method.source_info()
    except (ValueError, AttributeError):
        meth = {}
    out.update(_module_keys("method", sc.method.name, meth))
    out["method_params"] = json.dumps(dict(sc.method.params)) if sc.method.params else ""
    if sc.attack.kind == "trace":  # the trace itself, so that the recording needs no other file
        out["attack_trace"] = json.dumps({"kind": "trace", **sc.attack.params_dict})
    return out


def recorded_scenario(metadata: dict[str, dict], path: str = "recording", *, _cache=None):
    """The scenario a recorded run used, rebuilt from the TOML stored in its metadata.

    Returns ``(scenario, plant_source, model_source)``.  The run's overrides are applied
    and what the run resolved (``testbed.resolved``: the quantizer, the timing) wins over
    this version's defaults.  The plant is imported as the run did (its reference, from
    the scenario's folder first); only when that fails is the plant module's source
    stored in the recording loaded, which runs code from the recording: a line on
    stderr says so.  ``plant_source`` tells which happened (``plants.refs.resolve_recorded``).
    """
    import tomllib

    from ..scenario import loads, with_overrides
    from ..scenariospec import ScenarioError
    from ..scenariowrite import to_toml

    meta = metadata.get("testbed.scenario", {})
    toml = meta.get("toml")
    if not toml:
        raise ScenarioError(f"{path}: no scenario in the recording's metadata (not a recording of testbed run or "
                            "testbed simulate --out)")
    base_dir = meta.get("base_dir") or None
    if _cache is not None and getattr(_cache, "_resolved", False):  # once per recording: report and replay
        ps, ms = _cache.plant_source, _cache.model_source
    else:
        ps = _resolve_plant(meta, base_dir, "plant", path)
        ms = _resolve_plant(meta, base_dir, "model", path)
        _resolve_method(meta, base_dir, path)
        if _cache is not None:
            _cache._resolved = True
    if meta.get("attack_trace"):  # an embedded trace replaces the file the run read it from
        data = tomllib.loads(toml)
        data["attack"] = json.loads(meta["attack_trace"])
        toml = to_toml(data)
    sc = loads(toml, name=str(meta.get("name", "recorded"))[:200], where=f"{path} (recorded scenario)",
               base_dir=base_dir, check_fmu=False)
    over = metadata.get("testbed.run", {}).get("scenario_overrides")
    try:
        sc = with_overrides(sc, json.loads(over)) if over else sc
    except (ValueError, TypeError) as e:
        raise ScenarioError(f"{path}: recorded overrides: {e}") from None
    return _with_resolved(sc, metadata.get("testbed.resolved")), ps, ms


def _resolve_plant(meta: dict, base_dir: str | None, prefix: str, path: str) -> dict | None:
    """Resolve the recorded plant (or model) reference, pinning the stored source when it is not importable."""
    from plants.refs import PlantRefError, resolve_recorded

    ref = meta.get(f"{prefix}_ref")
    if not ref:
        return None  # an FMU plant, a model that is the plant, or a recording from before references were stored
    try:
        _cls, status = resolve_recorded(ref, base_dir, module=meta.get(f"{prefix}_module", ""),
                                        class_name=meta.get(f"{prefix}_class", ""),
                                        source=meta.get(f"{prefix}_source", ""),
                                        sha256=meta.get(f"{prefix}_sha256", ""))
    except PlantRefError as e:
        from ..scenariospec import ScenarioError

        raise ScenarioError(f"{path}: {e}") from None
    status["module"] = meta.get(f"{prefix}_module", "")
    if status["loaded_from"] == "recording":
        print(f"note: {prefix} module {status['module']!r} is not importable ({status['reason']}); "
              f"loaded the source stored in {path} (sha256 {status['sha256'][:12]}): "
              "this runs code from the recording", file=sys.stderr)
    elif status["differs"]:
        print(f"note: {prefix} module {status['module']!r} as imported now differs from the one recorded "
              f"in {path} (sha256 {status['importable_sha256'][:12]} vs {status['sha256'][:12]})",
              file=sys.stderr)
    return status


def _resolve_method(meta: dict, base_dir: str | None, path: str) -> None:
    """Resolve the recorded method reference, loading its stored source when it is not importable."""
    from ..methods import MethodError
    from ..methods.registry import resolve_recorded
    from ..scenariospec import ScenarioError

    ref = meta.get("method_ref")
    if not ref:
        return  # a recording from before methods: the paper's
    try:
        st = resolve_recorded(ref, base_dir, module=meta.get("method_module", ""),
                              class_name=meta.get("method_class", ""), source=meta.get("method_source", ""),
                              sha256=meta.get("method_sha256", ""))
    except MethodError as e:
        raise ScenarioError(f"{path}: {e}") from None
    if st["loaded_from"] == "recording":
        print(f"note: method module {meta.get('method_module')!r} is not importable ({st['reason']}); loaded the "
              f"source stored in {path} (sha256 {meta.get('method_sha256', '')[:12]}): this runs code from the "
              "recording", file=sys.stderr)


def _with_resolved(sc, meta: dict | None):
    """``sc`` with the quantizer and timing the recorded run resolved (a later version's defaults
    may differ: the recording's own values win)."""
    import dataclasses

    from ..quantizer import QuantizerParams
    from ..scenariospec import DelaySpec, SimDelaySpec

    if not meta:
        return sc
    try:
        qd = json.loads(meta["quantizer"])
        rd = json.loads(meta["run"])
        qp = QuantizerParams(**qd)
        for key, cls in (("delay", DelaySpec), ("delay_lost", DelaySpec), ("sim_delay", SimDelaySpec)):
            if rd.get(key) is not None:
                v = dict(rd[key])
                if "values" in v:
                    v["values"] = tuple(v["values"])
                rd[key] = cls(**v)
        run = dataclasses.replace(sc.run, **rd)
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"unreadable testbed.resolved metadata: {e}") from None
    return dataclasses.replace(sc, quantizer=qp, run=run)


def resolved_metadata(sc) -> dict[str, str]:
    """What the run resolved from its scenario: the quantizer's parameters (the delay-aware rule's
    nominal delays and margins included), the timing and its bounds (``testbed.resolved``)."""
    import dataclasses

    run = dataclasses.asdict(sc.run)
    return {"quantizer": json.dumps(dataclasses.asdict(sc.quantizer)), "run": json.dumps(run),
            "timing_params_ns": json.dumps([int(v) for v in sc.timing_params]), "L_u": json.dumps(sc.L_u),
            "K": json.dumps(sc.K.tolist()), "u_max": json.dumps(sc.controller.u_max)}
