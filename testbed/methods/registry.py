"""Method references, resolved like plant references (``plants.refs``), the same way in every process:

1. ``"module.path:ClassName"``: imported from the scenario file's folder first, then ``sys.path``;
2. a bundled name (``paper``, ``zoom``, ``static``, ``unquantized``, ``unquantized-hold``) or one
   registered with :func:`register`;
3. an entry point of the group ``dos_testbed.methods`` (``pip install`` of a method package).

A recording stores the reference, the module's source text and its sha256 (:func:`source_info`).
"""

from __future__ import annotations

import importlib.metadata
from collections.abc import Callable, Iterable
from typing import Any, NoReturn

from plants.refs import CodeNotTrusted, import_module_attr, not_trusted, recorded_class, resolve_in
from plants.refs import source_info as _plant_source_info

from .base import Method, MethodError
from .bundled import BUNDLED

ENTRY_POINT_GROUP = "dos_testbed.methods"
DEFAULT = "paper"

_REGISTRY: dict[str, type[Method]] = dict(BUNDLED)
_RESOLVED: dict[tuple[str, str], type[Method]] = {}


def register(cls: type[Method]) -> type[Method]:
    """Register a method class under its ``name`` (usable as a decorator)."""
    _REGISTRY[cls.name] = check_method_class(cls, cls.name)
    return cls


def names() -> list[str]:
    return list(_REGISTRY)


def check_method_class(obj: object, ref: str) -> type[Method]:
    if not (isinstance(obj, type) and issubclass(obj, Method)) or obj is Method:
        raise MethodError(f"method {ref!r}: {obj!r} is not a subclass of testbed.methods.Method")
    return obj


def entry_points() -> dict[str, importlib.metadata.EntryPoint]:
    out: dict[str, importlib.metadata.EntryPoint] = {}
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        out.setdefault(ep.name, ep)
    return out


def _from_module(ref: str, base_dir: str | None) -> type[Method]:
    try:
        return check_method_class(import_module_attr(ref, base_dir, "method", MethodError), ref)
    except ValueError as e:  # plants.refs.PlantRefError from the shared importer
        raise MethodError(str(e).replace("plant", "method", 1)) from None


def _load_entry_point(ep: importlib.metadata.EntryPoint) -> type[Method]:
    try:
        obj = ep.load()
    except Exception as e:  # noqa: BLE001 - a user's package: whatever it raises becomes one line
        raise MethodError(f"method {ep.name!r}: entry point {ep.value!r} failed to load: {type(e).__name__}: {e}") from None
    return check_method_class(obj, ep.name)


def resolve(ref: str, base_dir: str | None = None) -> type[Method]:
    """The :class:`Method` subclass a reference names; :class:`MethodError` (one line) when it cannot."""
    return resolve_in(ref, base_dir, what="method", error=MethodError, registry=_REGISTRY, cache=_RESOLVED,
                      from_module=_from_module, entry_points=entry_points, load=_load_entry_point,
                      unknown=lambda: f"unknown method {ref!r}; bundled methods: {', '.join(names())}; or an "
                                      f"installed method package ({ENTRY_POINT_GROUP} entry point), or "
                                      "'module.path:ClassName'")


def make(ref: str, base_dir: str | None = None, params: dict | None = None) -> Method:
    """An instance of the method ``ref`` with ``params`` (its ``[method] params``)."""
    cls = resolve(ref, base_dir)
    try:
        return cls(**dict(params or {}))
    except MethodError:
        raise
    except Exception as e:  # noqa: BLE001 - a user's constructor: one line
        raise MethodError(f"method {ref!r}: {type(e).__name__}: {e}") from None


def source_info(cls: type[Method]) -> dict[str, str]:
    """``module``, ``class``, ``file``, ``source``, ``sha256`` of a method's module (as for plants)."""
    return _plant_source_info(cls)


def pin(ref: str, base_dir: str | None, cls: type[Method]) -> type[Method]:
    """Make ``resolve(ref, base_dir)`` return ``cls`` in this process (a class loaded from code stored in
    a recording or a campaign's folder, so that nothing is imported from that folder in its place)."""
    cls = check_method_class(cls, ref)
    _RESOLVED[(ref, str(base_dir) if base_dir else "")] = cls
    if ":" not in ref:
        _RESOLVED[(ref, "")] = cls
    return cls


def bundled(ref: str) -> bool:
    return ref in BUNDLED


def resolve_recorded(ref: str, base_dir: str | None, *, module: str = "", class_name: str = "", source: str = "",
                     sha256: str = "", trust_code: bool = False, stand_in: Callable[[], type] | None = None) -> dict:
    """Resolve a recorded method reference as the run did (``plants.refs.recorded_class``, the rule plants
    follow): imported (the user's own code); else, with ``trust_code``, the module's source stored in the
    recording (``plants.refs.load_stored``: THIS RUNS THE STORED CODE); else ``stand_in()``
    (:func:`stand_in_method`; None: ``CodeNotTrusted``), pinned to ``ref`` in this process.  Returns
    ``{"loaded_from": "import" | "recording" | "not run", "reason"}``."""
    _cls, how, reason = recorded_class("method", ref, base_dir, resolve=resolve, cache=_RESOLVED,
                                       keys=[(ref, str(base_dir) if base_dir else "")], check=check_method_class,
                                       error=MethodError, module=module, class_name=class_name,
                                       source=source if ":" in ref else "", sha256=sha256, trust_code=trust_code,
                                       stand_in=stand_in)
    return {"loaded_from": how, "reason": reason}


class _StoredCodebook:
    """A stand-in method's codebook: the recorded number of bits (None when the recording has none)."""

    resilient = False
    overflow = -1

    def __init__(self, bits: int | None):
        self.bits = bits
        self.nbytes = None if bits is None else (bits + 7) // 8
        self.n_codes = None if bits is None else 1 << min(bits, 62)


def stand_in_method(ref: str, class_name: str, uses: Iterable[str], bits: int | None) -> type[Method]:
    """A method class for a recorded method whose stored source is not run: it takes any parameters, uses
    the ``[quantizer]`` keys ``uses`` (the recorded scenario's), has a codebook of the recorded ``bits``,
    and no ends: making them (or the batch kernel's mode) raises ``CodeNotTrusted``."""
    why = str(not_trusted("method", ref))

    def refuse(self: object, *a: object, **kw: object) -> NoReturn:
        raise CodeNotTrusted(why)

    def init(self: Any, **params: Any) -> None:
        self.params = dict(params)

    ns = {"name": "", "description": "a recorded method whose stored source was not run", "uses": tuple(uses),
          "__init__": init, "codebook": lambda self, n, qp: _StoredCodebook(bits), "make_encoder": refuse,
          "make_decoder": refuse, "kernel_code": refuse, "STORED_NOT_RUN": why}
    return type(class_name if class_name.isidentifier() else "StoredMethod", (Method,), ns)
