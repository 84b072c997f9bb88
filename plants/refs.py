"""Plant references: a registered name, an installed entry point, or ``"module.path:ClassName"``.

``resolve(ref, base_dir)`` turns the ``[plant] name`` of a scenario into a
``Plant`` subclass, the same way in every process of a run:

1. ``"module.path:ClassName"``: the module is imported from ``base_dir`` (the
   scenario file's folder) first, then from ``sys.path``.  A plant module of the
   same name imported earlier from another scenario's folder is dropped, so two
   scenarios in two folders each get their own file; a file that would shadow a
   module imported otherwise (``plants.py``, ``numpy.py``) is refused.
2. a name registered with ``plants.register`` (the bundled plants are);
3. an entry point of the group ``dos_testbed.plants`` (``pip install`` of a plant
   package), whose value is ``"pkg.module:ClassName"``.

A recording stores the reference, the module's source text and its sha256
(``source_info``).  ``resolve_recorded`` imports the plant as above (a module importable
from the user's own path is the user's code); only when that fails, and only when the
caller passes ``trust_code=True`` (``--trust-code``), does it load the stored source
(``load_stored``, the one loader of stored plants and methods: it runs code read from a
recording).  Without it the recording's plant is a *stand-in* (``stand_in_plant``): its
name, dimensions and parameters, and no code; whatever would compute with it raises
``CodeNotTrusted``.
"""

from __future__ import annotations

import atexit
import hashlib
import importlib
import importlib.metadata
import importlib.util
import os
import re
import shutil
import sys
import tempfile
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

from .base import RHS, Plant

ENTRY_POINT_GROUP = "dos_testbed.plants"

#: a stored source larger than this is not written into recordings (a plant module is a few kB)
MAX_SOURCE_BYTES = 1 << 20

IDENT = r"[A-Za-z_][A-Za-z0-9_]*"
_MODULE_REF = re.compile(rf"^({IDENT}(?:\.{IDENT})*):({IDENT})$")


class PlantRefError(ValueError):
    """A plant reference that cannot be resolved, with the reason (one line)."""


#: the flag that lets a reader run code stored in a recording or a campaign folder
TRUST_FLAG = "--trust-code"


class CodeNotTrusted(ValueError):
    """Code stored in a recording (or a campaign folder) that was not run: the user did not pass
    ``--trust-code`` (``trust_code=True``).  One line, naming the flag."""


def not_trusted(kind: str, ref: str, where: str = "the recording") -> CodeNotTrusted:
    """The one line for a stored ``kind`` ("plant", "method") that is not run."""
    return CodeNotTrusted(f"{kind} {ref!r} is not importable here and its source stored in {where} is code, "
                          f"not run without {TRUST_FLAG} (trust_code=True in Python)")


#: what this process resolved a (ref, base_dir) to: module references and entry points only
_RESOLVED: dict[tuple[str, str], type[Plant]] = {}
#: top-level plant modules imported from a scenario's folder, and that folder
_FROM_FOLDER: dict[str, str] = {}


def is_module_ref(ref: str) -> bool:
    return ":" in ref


def check_plant_class(obj: object, ref: str) -> type[Plant]:
    """``obj`` if it is a usable ``Plant`` subclass, else ``PlantRefError``."""
    if not (isinstance(obj, type) and issubclass(obj, Plant)) or obj is Plant:
        raise PlantRefError(f"plant {ref!r}: {obj!r} is not a subclass of plants.Plant")
    if not isinstance(getattr(obj, "rhs", None), RHS):
        raise PlantRefError(f"plant {ref!r}: class {obj.__name__} has no right-hand side "
                            "(set rhs = a function decorated with @plants.base.rhs_function)")
    return obj


def _module_file(mod) -> Path | None:
    f = getattr(mod, "__file__", None)
    if f:
        return Path(f).resolve()
    paths = list(getattr(mod, "__path__", []) or [])
    return Path(paths[0]).resolve() if paths else None


def _is_under(mod, base: Path) -> bool:
    f = _module_file(mod)
    return f is not None and (f == base or base in f.parents)


def _import(modname: str, base_dir: str | None):
    top = modname.split(".")[0]
    if base_dir:
        base = Path(base_dir).resolve()
        if (base / f"{top}.py").is_file() or (base / top / "__init__.py").is_file():
            old = sys.modules.get(top)
            if old is not None and not _is_under(old, base):
                if _FROM_FOLDER.get(top) is None:
                    # not a plant module of another scenario folder: the testbed's own packages, a library
                    raise PlantRefError(f"module {top!r} in {base} has the name of a module already imported from "
                                        f"{_module_file(old)}: rename it")
                for k in [k for k in sys.modules if k == top or k.startswith(top + ".")]:
                    del sys.modules[k]   # the same name in another scenario folder: each gets its own
            sys.path.insert(0, str(base))
            try:
                importlib.invalidate_caches()
                mod = importlib.import_module(modname)
            finally:
                try:
                    sys.path.remove(str(base))
                except ValueError:
                    pass
            if _is_under(sys.modules.get(top, mod), base):
                _FROM_FOLDER[top] = str(base)
            return mod
    return importlib.import_module(modname)


def import_module_attr(ref: str, base_dir: str | None, what: str, error: type[Exception]) -> Any:
    """The object a ``"module.path:Name"`` reference names, imported from ``base_dir`` first, then
    ``sys.path``; ``error`` (one line naming the ``what``: "plant", "method") when it cannot be."""
    m = _MODULE_REF.match(ref)
    if not m:
        raise error(f"{what} {ref!r}: a module reference is 'module.path:ClassName'")
    modname, attr = m.groups()
    where = f"{base_dir}, then sys.path" if base_dir else "sys.path"
    try:
        mod = _import(modname, base_dir)
    except ModuleNotFoundError as e:
        if e.name and (modname == e.name or modname.startswith(e.name + ".")):
            raise error(f"{what} {ref!r}: no module {modname!r} (looked in {where})") from None
        raise error(f"{what} {ref!r}: importing {modname!r} failed: {type(e).__name__}: {e}") from None
    except Exception as e:  # noqa: BLE001 - anything a user's module raises: one line
        raise error(f"{what} {ref!r}: importing {modname!r} failed: {type(e).__name__}: {e}") from None
    if not hasattr(mod, attr):
        raise error(f"{what} {ref!r}: module {modname!r} ({_module_file(mod)}) has no {attr!r}")
    return getattr(mod, attr)


def _from_module(ref: str, base_dir: str | None) -> type[Plant]:
    return check_plant_class(import_module_attr(ref, base_dir, "plant", PlantRefError), ref)


# ----------------------------------------------------------------------------- entry points
def entry_points() -> dict[str, importlib.metadata.EntryPoint]:
    """The installed entry points of the group ``dos_testbed.plants``, by name (first one wins)."""
    out: dict[str, importlib.metadata.EntryPoint] = {}
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        out.setdefault(ep.name, ep)
    return out


def _dist_name(ep) -> str | None:
    d = getattr(ep, "dist", None)
    return getattr(d, "name", None) if d is not None else None


def load_entry_point(ep: importlib.metadata.EntryPoint) -> type[Plant]:
    try:
        obj = ep.load()
    except Exception as e:  # noqa: BLE001 - a broken installed package: one line
        raise PlantRefError(f"plant {ep.name!r}: entry point {ep.value!r} of {_dist_name(ep) or 'a package'} "
                            f"failed to load: {type(e).__name__}: {e}") from None
    return check_plant_class(obj, ep.name)


# ----------------------------------------------------------------------------- the registry
_REGISTRY: dict[str, type[Plant]] = {}


def register(cls: type[Plant]) -> type[Plant]:
    """Add a plant class to the registry under ``cls.name`` (this process only)."""
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    _REGISTRY[cls.name] = cls
    return cls


def names() -> list[str]:
    """The registered names (built-in and registered in this process; not the entry points)."""
    return sorted(_REGISTRY)


# ----------------------------------------------------------------------------- resolving
def resolve_in(ref: object, base_dir: str | os.PathLike | None, *, what: str, error: type[Exception], registry: dict,
               cache: dict, from_module: Callable[[str, str | None], Any],
               entry_points: Callable[[], Mapping[str, Any]], load: Callable[[Any], Any],
               unknown: Callable[[], str]) -> Any:
    """The class a reference names, in the order of the module docstring: a ``"module.path:Name"``
    (``from_module(ref, base_dir)``, once per reference and folder), a name in ``registry``, an entry point
    (``entry_points()``, loaded once with ``load(ep)``).  ``error`` with one line when it cannot
    (``unknown()`` for a name found nowhere).  Plants resolve with it here, methods in
    ``testbed.methods.registry``: one order and one cache rule for both."""
    if not isinstance(ref, str) or not ref:
        raise error(f"{what} name must be a non-empty string, got {ref!r}")
    bd = str(base_dir) if base_dir else ""
    if is_module_ref(ref):
        key = (ref, bd)
        if key not in cache:
            cache[key] = from_module(ref, bd or None)
        return cache[key]
    if ref in registry:
        return registry[ref]
    key = (ref, "")
    if key not in cache:
        ep = entry_points().get(ref)
        if ep is None:
            raise error(unknown())
        cache[key] = load(ep)
    return cache[key]


def resolve(ref: str, base_dir: str | os.PathLike | None = None, *, registry: dict | None = None) -> type[Plant]:
    """The ``Plant`` subclass a reference names (see the module docstring for the order).

    Raises ``PlantRefError`` (a ``ValueError``) with one line when it cannot.
    """
    return resolve_in(ref, base_dir, what="plant", error=PlantRefError,
                      registry=_REGISTRY if registry is None else registry, cache=_RESOLVED, from_module=_from_module,
                      entry_points=entry_points, load=load_entry_point,
                      unknown=lambda: f"unknown plant {ref!r}; registered plants: {', '.join(names())}; or an "
                                      f"installed plant package ({ENTRY_POINT_GROUP} entry point), or "
                                      "'module.path:ClassName'")


def display_name(cls: type[Plant]) -> str:
    """``cls.name``, or the class name for a plant that sets none."""
    return cls.name or cls.__name__


# ----------------------------------------------------------------------------- stored source
def _sha256(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def source_info(cls: type) -> dict[str, str]:
    """Where ``cls`` comes from and its module's source: ``module``, ``class``, ``file``, ``source``, ``sha256``.

    ``source`` is empty (and ``sha256`` too) when the file cannot be read or is
    larger than ``MAX_SOURCE_BYTES``.
    """
    mod = sys.modules.get(cls.__module__)
    f = _module_file(mod) if mod is not None else None
    text = ""
    if f is not None and f.is_file():
        try:
            if f.stat().st_size <= MAX_SOURCE_BYTES:
                text = f.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError):
            text = ""
    return {"module": cls.__module__, "class": cls.__qualname__, "file": str(f) if f else "",
            "source": text, "sha256": _sha256(text) if text else ""}


_TMP_DIRS: list[str] = []


def _cleanup() -> None:
    for d in _TMP_DIRS:
        shutil.rmtree(d, ignore_errors=True)


atexit.register(_cleanup)


def load_stored(kind: str, ref: str, module: str, class_name: str, source: str, sha256: str,
                check: Callable[[object, str], type], error: type[Exception], *, trust_code: bool = False) -> type:
    """Import ``class_name`` from a module's source stored in a recording, under the module's own name.

    THIS RUNS THE STORED CODE, and only when ``trust_code`` (the user's ``--trust-code``): otherwise
    ``CodeNotTrusted`` and nothing is written or run.  The sha256 must match the text and the names
    must be identifiers (the hash only tells a corrupt recording: it comes from the same file).  The
    text is written to a private temporary folder (removed at exit; numba caches a plant's right-hand
    side next to it) and imported as ``module``; if it fails, the module that held that name before is
    put back.  ``check(cls, ref)`` checks the class (``check_plant_class``, ``check_method_class``);
    every refusal is one line of ``error`` naming the ``kind`` ("plant", "method") and ``ref``.  Plants
    and methods of a recording both load through here.
    """
    if not trust_code:
        raise not_trusted(kind, ref)
    if not source:
        raise error(f"{kind} {ref!r}: no stored source")
    if _sha256(source) != sha256:
        raise error(f"{kind} {ref!r}: the stored source does not match its sha256 (corrupt recording)")
    if not re.fullmatch(rf"{IDENT}(?:\.{IDENT})*", module or "") or not re.fullmatch(IDENT, class_name or ""):
        raise error(f"{kind} {ref!r}: bad stored module or class name {module!r}:{class_name!r}")
    d = tempfile.mkdtemp(prefix=f"testbed-recorded-{kind}-")
    _TMP_DIRS.append(d)
    path = Path(d) / f"{module.rsplit('.', 1)[-1]}.py"
    path.write_text(source, encoding="utf-8")
    spec = importlib.util.spec_from_file_location(module, path)
    assert spec is not None and spec.loader is not None  # a .py file path always has both
    mod = importlib.util.module_from_spec(spec)
    old = sys.modules.get(module)
    sys.modules[module] = mod
    try:
        spec.loader.exec_module(mod)
        return check(getattr(mod, class_name, None), ref)
    except Exception as e:
        if old is not None:
            sys.modules[module] = old
        else:
            sys.modules.pop(module, None)
        if isinstance(e, error):
            raise
        raise error(f"{kind} {ref!r}: the stored source of {module!r} failed to load: "
                    f"{type(e).__name__}: {e}") from None


def load_source(ref: str, base_dir: str | None, module: str, class_name: str, source: str,
                sha256: str, *, trust_code: bool = False) -> type[Plant]:
    """Load a plant class from a module's stored source text (``source_info``, :func:`load_stored`: only
    with ``trust_code``) and pin it to ``ref``: afterwards ``resolve(ref, base_dir)`` returns the class in
    this process."""
    cls = load_stored("plant", ref, module, class_name, source, sha256, check_plant_class, PlantRefError,
                      trust_code=trust_code)
    for key in _plant_keys(ref, base_dir):
        _RESOLVED[key] = cls
    return cls


def _plant_keys(ref: str, base_dir) -> list[tuple[str, str]]:
    bd = str(base_dir) if base_dir else ""
    return [(ref, bd)] + ([] if is_module_ref(ref) or not bd else [(ref, "")])


def pin(ref: str, base_dir: str | None, cls: type[Plant]) -> type[Plant]:
    """Make ``resolve(ref, base_dir)`` return ``cls`` in this process (a class loaded from code stored in
    a recording or a campaign's folder, so that nothing is imported from that folder in its place)."""
    cls = check_plant_class(cls, ref)
    for key in _plant_keys(ref, base_dir):
        _RESOLVED[key] = cls
    return cls


# ----------------------------------------------------------------------------- a recording's classes
#: classes pinned to a recorded reference in this process: (kind, ref, base_dir) -> (how, sha256, class)
_PINNED: dict[tuple[str, str, str], tuple[str, str, type]] = {}


def recorded_class(kind: str, ref: str, base_dir: str | os.PathLike | None, *, resolve: Callable[[str, Any], type],
                   cache: dict, keys: Iterable[object], check: Callable[[object, str], type],
                   error: type[Exception], module: str, class_name: str, source: str, sha256: str, trust_code: bool,
                   stand_in: Callable[[], type] | None = None) -> tuple[type, str, str | None]:
    """The class of a recorded plant or method reference, one rule for both.

    1. imported as the run did (``resolve(ref, base_dir)``: the scenario's folder, then ``sys.path``):
       a module importable from the user's own path is the user's code;
    2. else, with ``trust_code``, the source stored in the recording (:func:`load_stored`, which runs it);
    3. else ``stand_in()``: a class made from the recording's data that runs nothing (``CodeNotTrusted``
       when there is none, or when ``stand_in`` is None).

    The class of 2 or 3 is pinned in ``cache`` under ``keys`` (the scenario rebuilt from the recording
    resolves to it).  A class pinned from a recording earlier in this process is decided again: a reader
    without ``trust_code`` never uses code a trusted one loaded.  Returns ``(cls, loaded_from, reason)``,
    ``loaded_from`` one of "import", "recording", "not run"; ``reason``: why the import failed.
    """
    pk = (kind, ref, str(base_dir) if base_dir else "")
    was = _PINNED.pop(pk, None)
    if was is not None:
        how, digest, old = was
        if how == "recording" and trust_code and digest == sha256:
            _PINNED[pk] = was
            for key in keys:
                cache[key] = old
            return old, "recording", None
        for key in keys:
            cache.pop(key, None)
        mod = sys.modules.get(old.__module__)
        if how == "recording" and mod is not None and getattr(mod, old.__name__, None) is old:
            sys.modules.pop(old.__module__, None)  # not importable as the user's code afterwards
    try:
        return resolve(ref, base_dir), "import", None
    except error as e:
        if not source:
            raise
        reason = str(e)
    if trust_code:
        cls = load_stored(kind, ref, module, class_name, source, sha256, check, error, trust_code=True)
        how = "recording"
    elif stand_in is None:
        raise not_trusted(kind, ref)
    else:
        cls, how = stand_in(), "not run"
    _PINNED[pk] = (how, sha256, cls)
    for key in keys:
        cache[key] = cls
    return cls, how, reason


class _NotRunRHS(RHS):
    """The right-hand side of a stand-in plant: every use raises ``CodeNotTrusted``."""

    def __init__(self, why: str):
        self._why = why
        self.__name__ = "rhs_not_run"
        self.__doc__ = why

    def _refuse(self):
        raise CodeNotTrusted(self._why)

    py = property(lambda self: self._refuse())
    jit = property(lambda self: self._refuse())
    cfunc = property(lambda self: self._refuse())


def stand_in_plant(ref: str, class_name: str, n: int, m: int, params: Iterable[object]) -> type[Plant]:
    """A plant class for a recorded plant whose stored source is not run: its class name, dimensions and
    parameter names (the recording's data) and no code: its right-hand side, linearization and parameter
    vector raise ``CodeNotTrusted``.  ``not_run(cls)`` is the line that says why."""
    import dataclasses
    import keyword

    why = str(not_trusted("plant", ref))
    taken = set(dir(Plant))
    names = [str(k) for k in params]
    for k in names:
        if not re.fullmatch(IDENT, k) or keyword.iskeyword(k) or k in taken or k.startswith("_"):
            raise CodeNotTrusted(f"{why} (its parameter {k[:40]!r} has no stand-in)")

    def refuse(self, *a, **kw):
        raise CodeNotTrusted(why)

    cname = class_name if re.fullmatch(IDENT, class_name or "") else "StoredPlant"
    ns = {"name": cname, "rhs": _NotRunRHS(why), "n": property(lambda self: int(n)), "m": property(lambda self: int(m)),
          "param_vector": refuse, "linearization": refuse, "STORED_NOT_RUN": why}
    return dataclasses.make_dataclass(cname, [(k, float, dataclasses.field(default=float("nan"))) for k in names],
                                      bases=(Plant,), namespace=ns, frozen=True)


def not_run(obj: object) -> str | None:
    """The ``CodeNotTrusted`` line of a stand-in class or object (``stand_in_plant``, a method's), else None."""
    return getattr(obj, "STORED_NOT_RUN", None)


def resolve_recorded(ref: str, base_dir: str | None, *, module: str = "", class_name: str = "",
                     source: str = "", sha256: str = "", trust_code: bool = False,
                     stand_in: Callable[[], type[Plant]] | None = None) -> tuple[type[Plant], dict]:
    """Resolve a recorded plant reference (:func:`recorded_class`): imported, else the stored source
    with ``trust_code``, else ``stand_in()`` (``stand_in_plant``; None: ``CodeNotTrusted``).

    Returns the class and a status ``{"ref", "sha256", "loaded_from": "import" | "recording" | "not run",
    "differs", "importable_sha256", "reason"}``: ``differs`` is True when the
    importable module's source is not the recorded one; ``reason`` says why the
    import failed when the recorded source was used or not run.
    """
    status = {"ref": ref, "sha256": sha256, "loaded_from": "import", "differs": False,
              "importable_sha256": None, "reason": None}
    cls, how, reason = recorded_class("plant", ref, base_dir, resolve=resolve, cache=_RESOLVED,
                                      keys=_plant_keys(ref, base_dir), check=check_plant_class, error=PlantRefError,
                                      module=module, class_name=class_name, source=source, sha256=sha256,
                                      trust_code=trust_code, stand_in=stand_in)
    if how != "import":
        status.update(loaded_from=how, reason=reason)
        return cls, status
    now = source_info(cls)["sha256"]
    status["importable_sha256"] = now or None
    status["differs"] = bool(sha256) and now != sha256
    return cls, status


__all__ = ["ENTRY_POINT_GROUP", "PlantRefError", "CodeNotTrusted", "TRUST_FLAG", "not_trusted", "not_run",
           "stand_in_plant", "recorded_class", "load_stored", "resolve", "entry_points", "load_entry_point", "source_info",
           "load_source", "resolve_recorded", "display_name", "is_module_ref", "check_plant_class",
           "import_module_attr", "resolve_in", "IDENT", "pin"]
