"""Specialized batch kernels that numba can cache across processes.

A numba kernel that receives a plant's right-hand side as a jitted function
(``RHS.jit``) inlines it, which is about twice as fast as calling the ``cfunc``
through a pointer, but numba cannot cache such a specialization on disk: the
dispatcher passed as a value is lowered as a pointer constant (a "dynamic
global").  The cure is to make the right-hand side a *module global* of the
kernel's own module.  This module does that by code generation:

1. It takes the source of a kernel (``testbed.sim.kernel._batch_kernel``) and of
   every jitted callee that receives a right-hand side (``zoom_update``,
   ``flow_into``, ``dop853_step``), found by following the call sites where a
   right-hand-side parameter is passed on;
2. removes those parameters, so that each ``rhs(...)`` call refers to a global
   bound to the plant's ``RHS.jit`` (one copy of a callee per binding, e.g.
   ``flow_into__rhs``);
3. writes the result as a small module into a cache folder, its file name keyed
   on a hash of every source file the kernel depends on (numba checks a cache
   entry only against its own file), and imports it.  numba's ordinary
   file-keyed cache then applies: the first call in a fresh process loads the
   compiled kernel instead of compiling it.

Nothing of the kernels is written twice: the generated code is the kernels'
own source, rewritten.  A plant whose right-hand side is not a module-level
``@rhs_function`` (or any other failure) falls back to the generic cached
kernel with one log line.

The cache folder is ``$TESTBED_CACHE_DIR/kernels``, else
``$XDG_CACHE_HOME/dos-testbed/kernels``, else ``~/.cache/dos-testbed/kernels``.
"""

from __future__ import annotations

import ast
import builtins
import hashlib
import importlib.util
import inspect
import logging
import os
import sys
import tempfile
import textwrap
import threading
from pathlib import Path
from typing import Any

import numba as nb

log = logging.getLogger("testbed.sim.kernelcache")

#: bump when the generator's output changes in a way the sources do not show
GENERATOR_VERSION = "1"

_lock = threading.Lock()
_built: dict[str, object] = {}      # module hash -> kernel wrapper
_memo: dict[tuple, tuple] = {}      # (kernel, bindings) -> (wrapper or the kernel itself, ...), per process


class CannotSpecialize(Exception):
    """The kernel cannot be generated for this plant (the reason is the message)."""


def cache_dir() -> Path:
    """The folder of the generated kernel modules."""
    base = os.environ.get("TESTBED_CACHE_DIR")
    if base:
        return Path(base) / "kernels"
    xdg = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(xdg) / "dos-testbed" / "kernels"


# ============================================================================ public entry point
def specialized(kernel: Any, bindings: dict) -> Any:
    """A callable with ``kernel``'s arguments that runs its cached specialization.

    Parameters
    ----------
    kernel : a numba dispatcher (``cache=True``) whose parameters named in
        ``bindings`` are right-hand sides ``rhs(x, u, p, dx)``.
    bindings : parameter name -> ``plants.base.RHS`` object (a module-level
        ``@rhs_function``), e.g. ``{"rhs": type(plant).rhs}``.

    Returns
    -------
    A wrapper taking exactly ``kernel``'s arguments (the right-hand-side ones
    are ignored: they are globals of the generated module), or ``kernel``
    itself when the specialization cannot be built (logged once per plant);
    the caller then passes the ``cfunc`` as usual.
    """
    memo = (id(kernel),) + tuple((k, id(v)) for k, v in sorted(bindings.items()))
    hit = _memo.get(memo)
    if hit is not None:
        return hit[0]
    try:
        run = _specialized(kernel, bindings)
    except Exception as e:  # noqa: BLE001 - any failure falls back to the generic kernel
        names = ", ".join(f"{k} = {getattr(v, '__name__', v)}" for k, v in sorted(bindings.items()))
        log.warning("testbed: no cached specialized kernel for %s (%s); using the generic kernel", names, e)
        run = kernel
    _memo[memo] = (run, kernel, tuple(bindings.values()))  # holds the objects so that their ids stay theirs
    return run


def _specialized(kernel, bindings: dict):
    declared = getattr(sys.modules.get(kernel.py_func.__module__), "_RHS_ARGS", None)
    if declared is not None and set(declared) != set(bindings):
        raise CannotSpecialize(f"kernel right-hand sides {tuple(declared)} but bindings for {sorted(bindings)}")
    refs = {name: _rhs_reference(obj) for name, obj in bindings.items()}
    gen = _Generator(refs)
    top = gen.function(kernel, {n: n for n in bindings}, top=True)
    src = gen.module_source(top)
    gen.files |= {inspect.getfile(obj.py) for obj in bindings.values()}
    digest = _digest(src, gen.files)
    with _lock:
        hit = _built.get(digest)
        if hit is not None:
            return hit
        mod = _load(digest, src, refs)
        jitted = getattr(mod, top)
        params = list(inspect.signature(kernel.py_func).parameters)
        drop = {params.index(n) for n in bindings}

        def run(*args):
            return jitted(*[a for i, a in enumerate(args) if i not in drop])

        run.dispatcher = jitted  # type: ignore[attr-defined]  # the compiled kernel, for numba's signatures
        run.path = mod.__file__  # type: ignore[attr-defined]  # its cached source file
        _built[digest] = run
        return run


# ============================================================================ the right-hand side
def _rhs_reference(obj) -> tuple[str, str]:
    """(module, attribute) under which a fresh process finds this RHS object."""
    fn = getattr(obj, "py", None)
    if fn is None or not hasattr(obj, "jit"):
        raise CannotSpecialize(f"{obj!r} is not an @rhs_function")
    mod = inspect.getmodule(fn)
    if mod is None or mod.__name__ == "__main__" or not getattr(mod, "__file__", None):
        raise CannotSpecialize(f"right-hand side {fn.__name__} is not in an importable module")
    name = fn.__name__
    if getattr(mod, name, None) is not obj:
        raise CannotSpecialize(f"right-hand side {mod.__name__}.{name} is not a module-level @rhs_function")
    return mod.__name__, name


# ============================================================================ code generation
class _Generator:
    """Rewrites a kernel and its right-hand-side callees into one module's source."""

    def __init__(self, refs: dict):
        self.refs = refs                       # global rhs name -> (module, attribute)
        self.defs: dict[tuple, tuple[str, str]] = {}   # (dispatcher id, bindings) -> (name, source)
        self.order: list[tuple] = []
        self.imports: dict[str, tuple[str, str, object]] = {}  # local name -> (module, attr, object)
        self.files: set[str] = set()
        self._seen_files: set[int] = set()

    # -- dependencies -------------------------------------------------------------
    def _track(self, dispatcher) -> None:
        """Record the source file of a dispatcher and of every jitted function it reaches."""
        fn = getattr(dispatcher, "py_func", None)
        if fn is None or id(fn) in self._seen_files:
            return
        self._seen_files.add(id(fn))
        self.files.add(inspect.getfile(fn))
        g = fn.__globals__
        for name in _code_names(fn.__code__):
            v = g.get(name)
            if isinstance(v, nb.core.registry.CPUDispatcher):
                self._track(v)

    def _import(self, name: str, module: str, obj) -> None:
        prev = self.imports.get(name)
        if prev is not None and prev[2] is not obj:
            raise CannotSpecialize(f"two different globals named {name!r} ({prev[0]}, {module})")
        self.imports[name] = (module, name, obj)

    # -- one function ---------------------------------------------------------------
    def function(self, dispatcher, bind: dict, top: bool = False) -> str:
        """Generate ``dispatcher`` with its parameters in ``bind`` (param -> global rhs) lifted; returns its name."""
        key = (id(dispatcher), tuple(sorted(bind.items())))
        if key in self.defs:
            return self.defs[key][0]
        py = dispatcher.py_func
        self._track(dispatcher)
        tree = ast.parse(textwrap.dedent(inspect.getsource(py)))
        fdef = tree.body[0]
        if not isinstance(fdef, ast.FunctionDef):
            raise CannotSpecialize(f"{py.__name__}: not a plain function")
        params = [a.arg for a in fdef.args.args]
        if fdef.args.vararg or fdef.args.kwarg or fdef.args.kwonlyargs or fdef.args.defaults:
            raise CannotSpecialize(f"{py.__name__}: only plain positional parameters are supported")
        missing = set(bind) - set(params)
        if missing:
            raise CannotSpecialize(f"{py.__name__} has no parameter {sorted(missing)}")
        name = py.__name__ if top else f"{py.__name__}__" + "_".join(bind[p] for p in params if p in bind)
        self.defs[key] = (name, "")  # placeholder against recursion
        fdef.name = name
        fdef.decorator_list = []
        fdef.args.args = [a for a in fdef.args.args if a.arg not in bind]
        _Rewriter(self, py, bind).visit(fdef)
        opts = dispatcher.targetoptions
        deco = "@nb.njit(cache=True" + (f", inline={opts['inline']!r}" if opts.get("inline", "never") != "never"
                                        else "") + ")"
        # the globals the rewritten body still uses come from the function's own module
        g = py.__globals__
        local = set(params) | _assigned(fdef)
        generated = {v[0] for v in self.defs.values()}
        used = {n.id for n in ast.walk(fdef) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Load)}
        for n in sorted(used - local - generated - set(bind.values())):
            if n not in g:
                if hasattr(builtins, n):
                    continue
                raise CannotSpecialize(f"{py.__name__}: unknown global {n!r}")
            self._import(n, py.__module__, g[n])
        self.defs[key] = (name, deco + "\n" + ast.unparse(fdef) + "\n")
        self.order.append(key)
        return name

    def module_source(self, top: str) -> str:
        lines = ["# GENERATED by testbed.sim.kernelcache from the kernels' sources; do not edit.",
                 f"# kernel {top}; right-hand sides: "
                 + ", ".join(f"{k} = {m}.{a}.jit" for k, (m, a) in sorted(self.refs.items())),
                 "import numba as nb", ""]
        by_mod: dict[str, list[str]] = {}
        for n, (m, a, _obj) in sorted(self.imports.items()):
            if n == "nb":
                continue
            by_mod.setdefault(m, []).append(a)
        for m, names in sorted(by_mod.items()):
            lines.append(f"from {m} import {', '.join(sorted(names))}")
        for k, (m, a) in sorted(self.refs.items()):
            lines.append(f"from {m} import {a} as _{k}_object")
            lines.append(f"{k} = _{k}_object.jit")
        lines.append("")
        for key in self.order:  # callees before their callers
            lines.append("")
            lines.append(self.defs[key][1])
        return "\n".join(lines)


class _Rewriter(ast.NodeTransformer):
    """Renames lifted parameters to their globals and redirects the calls that pass them on."""

    def __init__(self, gen: _Generator, py, bind: dict):
        self.gen = gen
        self.py = py
        self.bind = bind

    def visit_Call(self, node: ast.Call):
        passed = [(i, a.id) for i, a in enumerate(node.args) if isinstance(a, ast.Name) and a.id in self.bind]
        if any(isinstance(k.value, ast.Name) and k.value.id in self.bind for k in node.keywords):
            raise CannotSpecialize(f"{self.py.__name__}: a right-hand side passed by keyword")
        if passed:
            if not isinstance(node.func, ast.Name):
                raise CannotSpecialize(f"{self.py.__name__}: a right-hand side passed to a method")
            callee = self.py.__globals__.get(node.func.id)
            if not isinstance(callee, nb.core.registry.CPUDispatcher):
                raise CannotSpecialize(f"{self.py.__name__}: a right-hand side passed to {node.func.id}, "
                                       "which is not a numba function")
            cparams = list(inspect.signature(callee.py_func).parameters)
            sub = {cparams[i]: self.bind[n] for i, n in passed}
            node.func = ast.Name(id=self.gen.function(callee, sub), ctx=ast.Load())
            drop = {i for i, _ in passed}
            node.args = [a for i, a in enumerate(node.args) if i not in drop]
        self.generic_visit(node)
        return node

    def visit_Name(self, node: ast.Name):
        if node.id in self.bind:
            if not isinstance(node.ctx, ast.Load):
                raise CannotSpecialize(f"{self.py.__name__}: assigns to its right-hand side {node.id}")
            return ast.copy_location(ast.Name(id=self.bind[node.id], ctx=node.ctx), node)
        return node


def _code_names(code) -> set[str]:
    out = set(code.co_names)
    for c in code.co_consts:
        if hasattr(c, "co_names"):
            out |= _code_names(c)
    return out


def _assigned(fdef: ast.FunctionDef) -> set[str]:
    return {n.id for n in ast.walk(fdef) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store)}


# ============================================================================ files
def _digest(src: str, files) -> str:
    h = hashlib.sha256()
    h.update(f"{GENERATOR_VERSION}|numba {nb.__version__}|{sys.version_info[:2]}".encode())
    h.update(src.encode())
    for f in sorted(files):
        h.update(f.encode())
        h.update(Path(f).read_bytes())
    return h.hexdigest()[:20]


def _load(digest: str, src: str, refs: dict):
    d = cache_dir()
    d.mkdir(parents=True, exist_ok=True)
    stem = "k_" + "_".join(f"{a}" for _m, a in sorted(refs.values())) + "_" + digest
    stem = "".join(c if c.isalnum() or c == "_" else "_" for c in stem)
    path = d / f"{stem}.py"
    if not path.exists() or path.read_text() != src:
        # write once, atomically, never over an existing file (its mtime keys numba's cache)
        fd, tmp_ = tempfile.mkstemp(dir=d, prefix=f".{stem}.", suffix=".tmp")
        tmp: str | None = tmp_
        try:
            with os.fdopen(fd, "w") as f:
                f.write(src)
            try:
                os.link(tmp_, path)
            except FileExistsError:
                if path.read_text() != src:
                    os.replace(tmp_, path)
                    tmp = None
        finally:
            if tmp is not None and os.path.exists(tmp):
                os.unlink(tmp)
    modname = f"_testbed_kernel_{digest}"
    mod = sys.modules.get(modname)
    if mod is not None:
        return mod
    spec = importlib.util.spec_from_file_location(modname, path)
    assert spec is not None and spec.loader is not None  # a .py file path always has both
    mod = importlib.util.module_from_spec(spec)
    sys.modules[modname] = mod
    try:
        spec.loader.exec_module(mod)
    except BaseException:
        sys.modules.pop(modname, None)
        raise
    return mod
