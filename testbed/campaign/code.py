"""The user code a campaign's runs import, kept in its folder so that the folder alone reruns them.

Every method and plant (``[plant]``, ``[model]``) a run names that does not ship with the testbed (a
``"module.path:ClassName"`` or an installed entry point) is stored when the campaign starts: its
module's source text and sha256 in ``manifest.json`` (``code``), and, for a ``"module:Class"``
reference, a copy of the module beside the runs' scenarios (``scenarios/module.py``).

- ``testbed simulate DIR/scenarios/RUN.toml`` (and a live campaign's ``testbed run`` of it) imports the
  copy as any scenario imports a module from its own folder: the user runs that folder's scenario.
- ``testbed campaign --verify DIR`` never imports from the folder (its runs resolve from no folder):
  each class is the module importable from the user's own path (``sys.path``, not inside the folder)
  when its sha256 is the stored one, else the source stored in the manifest, loaded by
  ``plants.refs.load_stored`` (which checks the sha256) and only with ``--trust-code``; either way it
  is pinned (``pin``) to the reference for the rerun.
"""

from __future__ import annotations

import hashlib
import tomllib
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from ..common.errors import BadInput

if TYPE_CHECKING:
    from .spec import PlannedRun

#: the classes this process has pinned: (kind, ref, sha256, base_dir)
_LOADED: set = set()


def _sha256(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _refs(data: dict) -> Iterator[tuple[str, str]]:
    """(kind, reference) of the method, plant and model a resolved scenario names."""
    from .. import methods

    mt = data.get("method")

    mt = mt if isinstance(mt, dict) else {}
    yield "method", mt.get("name", methods.DEFAULT)
    for sec in ("plant", "model"):
        t = data.get(sec)
        if isinstance(t, dict) and isinstance(t.get("name"), str):
            yield "plant", t["name"]


def _registry(kind: str) -> tuple:
    """(resolve, source_info, pin, check, error, ships_with_testbed) of the plants' or the methods' registry."""
    if kind == "method":
        from ..methods import registry as r

        return r.resolve, r.source_info, r.pin, r.check_method_class, r.MethodError, r.bundled
    import plants
    from plants import refs as pr

    return (pr.resolve, pr.source_info, pr.pin, pr.check_plant_class, pr.PlantRefError,
            lambda ref: not pr.is_module_ref(ref) and ref in plants.names())


def collect(runs: Iterable[PlannedRun]) -> list[dict]:
    """The user code of ``runs`` (``spec.PlannedRun``): one entry per (kind, reference) with ``kind``, ``ref``,
    ``module``, ``class``, ``sha256``, ``source`` and ``copy`` (the copy's path in the folder, or None)."""
    out: dict = {}
    for r in runs:
        for kind, ref in _refs(tomllib.loads(r.text)):
            resolve, source_info, _pin, _check, _error, ships = _registry(kind)
            if (kind, ref) in out or ships(ref):
                continue
            info = source_info(resolve(ref, r.base_dir or None))
            module = info["module"]
            copy = f"scenarios/{module.replace('.', '/')}.py" if ":" in ref and info["source"] else None
            out[(kind, ref)] = {"kind": kind, "ref": ref, "module": module, "class": info["class"],
                                "sha256": info["sha256"], "source": info["source"], "copy": copy}
    return list(out.values())


def write_copies(folder: Path, entries: list[dict], write: Callable[[Path, str], None]) -> None:
    """Each entry's copy beside the scenarios (``write(path, text)``: atomically); a dotted module's
    packages get an empty ``__init__.py`` where they have none."""
    for e in entries:
        if not e.get("copy"):
            continue
        path = folder / e["copy"]
        path.parent.mkdir(parents=True, exist_ok=True)
        p = path.parent
        while p != folder / "scenarios" and folder / "scenarios" in p.parents:
            if not (p / "__init__.py").exists():
                write(p / "__init__.py", "")
            p = p.parent
        write(path, e["source"])


def changed(entries: list[dict], runs: Iterable[PlannedRun]) -> list[str]:
    """The entries whose module is no longer the stored one (a campaign resumed after an edit)."""
    now = {(e["kind"], e["ref"]): e["sha256"] for e in collect(runs)}
    return [f"{e['kind']} {e['ref']!r}" for e in entries if now.get((e["kind"], e["ref"]), e["sha256"]) != e["sha256"]]


def check(folder: Path, entries: list[dict]) -> list[str]:
    """Problems of the folder's stored code: a source that does not match its sha256, a copy missing or
    not the stored source."""
    out = []
    for e in entries:
        if not e.get("source") or _sha256(e["source"]) != e.get("sha256"):
            out.append(f"manifest: the stored source of {e['kind']} {e['ref']!r} does not match its sha256")
        if e.get("copy"):
            p = folder / e["copy"]
            try:
                same = _sha256(p.read_text(encoding="utf-8")) == e.get("sha256")
            except (OSError, UnicodeDecodeError):
                out.append(f"{e['copy']}: missing or unreadable (the copy of {e['kind']} {e['ref']!r})")
                continue
            if not same:
                out.append(f"{e['copy']}: differs from the manifest's sha256 of {e['kind']} {e['ref']!r}")
    return out


def _importable(e: dict, folder: Path) -> type | None:
    """The class the user's own path (``sys.path``) gives ``e['ref']`` when its module's sha256 is the stored
    one, else None.  A module that ``sys.path`` would find inside ``folder`` (the working directory there)
    is the folder's code, not the user's: not imported."""
    import importlib.util

    resolve, source_info, _pin, _check, error, _ships = _registry(e["kind"])
    try:
        spec = importlib.util.find_spec(e["module"].split(".")[0])
    except (ImportError, ValueError):
        spec = None
    where = Path(spec.origin).resolve() if spec is not None and spec.origin else None
    if where is not None and Path(folder).resolve() in where.parents:
        return None
    try:
        cls = resolve(e["ref"], None)
    except (error, ValueError):
        return None
    return cls if source_info(cls)["sha256"] == e["sha256"] else None


def untrusted(entries: list[dict], folder: Path) -> list[dict]:
    """The entries a rerun can only take from the folder's stored source (nothing importable here has it)."""
    return [e for e in entries if _importable(e, folder) is None]


def load(entries: list[dict], folder: Path, trust_code: bool) -> None:
    """Pin every entry's class to its reference (resolved from no folder) in this process, as the module
    docstring says: the importable module with the stored sha256, else the stored source with
    ``trust_code`` (``BadInput`` without: one line naming --trust-code)."""
    from plants.refs import load_stored

    for e in entries:
        key = (e["kind"], e["ref"], e["sha256"], str(folder))
        if key in _LOADED:
            continue
        _resolve, _info, pin, check_cls, error, _ships = _registry(e["kind"])
        cls = _importable(e, folder)
        if cls is None:
            if not trust_code:
                raise BadInput(refusal([e]))
            try:
                cls = load_stored(e["kind"], e["ref"], e["module"], e["class"], e["source"], e["sha256"], check_cls,
                                  error, trust_code=True)
            except error as ex:
                raise BadInput(str(ex)) from None
        pin(e["ref"], None, cls)
        _LOADED.add(key)


def refusal(entries: list[dict]) -> str:
    """The one line that refuses to run code stored in a folder without --trust-code."""
    names = ", ".join(f"{e['kind']} {e['ref']!r} (sha256 {e['sha256'][:12]}...)" for e in entries)
    return (f"the runs need code stored in the campaign's folder, not importable here: {names}; re-running them "
            "runs that code: pass --trust-code to allow it (or put the module on PYTHONPATH)")
