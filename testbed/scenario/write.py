"""Writing a scenario as TOML (what ``tomllib`` and ``testbed.scenario.loads`` read back): the
answer of ``testbed worst-attack --scenario-out``, a recording's scenario with its trace embedded."""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import plants.refs

from .spec import Scenario, ScenarioError, _thaw

if TYPE_CHECKING:
    import numpy as np


def _toml_key(k: object) -> str:
    k = str(k)
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else json.dumps(k)


def _toml_value(v: object) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("nan" if math.isnan(v) else ("inf" if v > 0 else "-inf"))
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def to_toml(data: dict) -> str:
    """TOML text of a scenario dict (what ``tomllib.loads`` reads back): top-level keys, then one
    ``[table]`` per section (tables inside a section inline)."""
    lines = [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    for k, v in data.items():
        if isinstance(v, dict):
            lines += ["", f"[{_toml_key(k)}]"]
            lines += [f"{_toml_key(a)} = {_toml_value(b)}" for a, b in v.items()]
    return "\n".join(lines) + "\n"


def with_attack(sc: Scenario, *, x0: Sequence[float] | np.ndarray, E0: float, intervals: Iterable[Sequence[float]],
                duration: float, name: str, description: str, out_dir: str | Path, budget: dict | None = None) -> str:
    """TOML text of ``sc`` from ``x0`` with E0, under the attack ``intervals`` ([[start, length], ...];
    none: kind "none") with the declared ``budget`` ([attack] budget keys), for ``duration``
    seconds, to be saved in ``out_dir``.

    Plant, model and FMU references become absolute (a file path) or stay names that resolve
    anywhere; a ``module:Class`` plant module found only in the scenario's folder cannot be
    named from elsewhere: ``ScenarioError`` unless ``out_dir`` is that folder.
    """
    data = sc.document()
    data["name"] = name
    data["description"] = description
    base = Path(sc.base_dir or ".").resolve()
    same_dir = Path(out_dir).resolve() == base
    for sec in ("plant", "model"):
        t = data.get(sec)
        if not isinstance(t, dict):
            continue
        if "fmu" in t:
            p = Path(str(t["fmu"])).expanduser()
            t["fmu"] = str((p if p.is_absolute() else base / p).resolve())
        ref = t.get("name")
        if isinstance(ref, str) and plants.refs.is_module_ref(ref) and not same_dir:
            mod = ref.split(":", 1)[0].split(".", 1)[0]
            if (base / f"{mod}.py").exists() or (base / mod).is_dir():
                raise ScenarioError(f"[{sec}] name = {ref!r} is a module in {base}: write the scenario there "
                                    "(a module reference cannot name a folder)")
    mt = data.get("method")
    mt = mt if isinstance(mt, dict) else {}
    params = dict(_thaw(sc.method.params))
    if sc.method.name != mt.get("name", "paper") or params != mt.get("params", {}):  # swapped (--method)
        if plants.refs.is_module_ref(sc.method.name) and not same_dir:
            mod = sc.method.name.split(":", 1)[0].split(".", 1)[0]
            if (base / f"{mod}.py").exists() or (base / mod).is_dir():
                raise ScenarioError(f"[method] name = {sc.method.name!r} is a module in {base}: write the scenario "
                                    "there (a module reference cannot name a folder)")
        data["method"] = {"name": sc.method.name, **({"params": params} if params else {})}
    used = {"T", *sc.make_method().uses}  # the written scenario's own method: no key it does not use
    data["quantizer"] = {k: v for k, v in data.get("quantizer", {}).items() if k in used}
    data["plant"]["x0"] = [float(v) for v in x0]
    if "E0" in used:
        data["quantizer"]["E0"] = float(E0)
    if intervals:
        data["attack"] = {"kind": "intervals", "intervals": [[float(a), float(t)] for a, t in intervals]}
        if budget:
            data["attack"]["budget"] = {k: float(v) for k, v in budget.items()}
    else:
        data["attack"] = {"kind": "none"}
    data.setdefault("run", {})["duration"] = float(duration)
    return to_toml(data)
