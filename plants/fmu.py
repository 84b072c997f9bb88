"""FMU plants: a Functional Mock-up Unit (FMI 2.0 Co-Simulation) as the true plant, through fmpy.

    [plant]
    fmu = "lienard.fmu"              # relative to the scenario file
    inputs = ["u"]                   # the FMU variables that are u (causality input, Real)
    states = ["x1", "x2"]            # the FMU variables that are x (Real, initial exact or approx)
    params = { a = 0.3333, b = 0.02 }  # FMU parameters (causality parameter), optional
    x0 = [0.1, 0.1]

``describe`` reads and checks the model description without loading the binary
(the scenario loader calls it in every process); ``FMUPlant`` extracts the FMU,
loads its library and is a ``plants.PlantProcess``: ``reset(x0)`` instantiates
it, sets the parameters and, in initialization mode, the state variables to x0;
``advance(u, dt)`` sets the inputs and calls ``fmi2DoStep(t, dt)`` (the input is
held over the step: the zero-order hold of equation (2)).

Every failure is one line: ``FMUError`` (a ``ValueError``) while loading (no
file, not a zip, no modelDescription.xml, Model Exchange only, no binary for this
platform, a variable that is not there or has the wrong kind), ``PlantFault``
while running (a failed ``fmi2DoStep``, with the FMU's last logged message).
fmpy is the optional extra ``fmu`` (``pip install 'dos-testbed[fmu]'``).
"""

from __future__ import annotations

import itertools
import math
import os
import shutil
import tempfile
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .base import PlantFault

if TYPE_CHECKING:
    import numpy.typing as npt

INSTALL_HINT = "pip install 'dos-testbed[fmu]' (or pip install fmpy)"


class FMUError(ValueError):
    """An FMU that cannot be used as a plant (found while loading it), one line."""


def _fmpy():
    try:
        import fmpy
        import fmpy.fmi2
        import fmpy.model_description
    except ImportError as e:
        raise FMUError(f"FMU plants need fmpy, which is not installed ({e}): {INSTALL_HINT}") from None
    import fmpy

    return fmpy


@dataclass(frozen=True)
class FMUInfo:
    """What ``describe`` found: the FMU's identity and the value references of u, x and the parameters."""

    path: str
    fmi_version: str
    model_name: str
    model_identifier: str
    guid: str
    inputs: tuple[tuple[str, int], ...]                    # (name, value reference)
    states: tuple[tuple[str, int, str], ...]               # (name, value reference, initial)
    params: tuple[tuple[str, int, str, object], ...]       # (name, value reference, type, value)

    @property
    def n(self) -> int:
        return len(self.states)

    @property
    def m(self) -> int:
        return len(self.inputs)


_PARAM_TYPES = {"Real": (float, int), "Integer": (int,), "Boolean": (bool,), "String": (str,)}


def describe(path: str | Path, *, inputs: Sequence[str], states: Sequence[str], params: dict | None = None) -> FMUInfo:
    """Read ``path``'s model description and check ``inputs``, ``states`` and ``params`` against it.

    Does not load the FMU's binary, but checks that one for this platform is in
    the archive.  Raises ``FMUError`` with one line on any mismatch.
    """
    fmpy = _fmpy()
    from fmpy.model_description import ValidationError, read_model_description

    p = Path(path)
    if not p.is_file():
        raise FMUError(f"{p}: no such FMU file")
    if not zipfile.is_zipfile(p):
        raise FMUError(f"{p}: not an FMU (not a zip archive)")
    try:
        with zipfile.ZipFile(p) as z:
            if "modelDescription.xml" not in z.namelist():
                raise FMUError(f"{p}: not an FMU (no modelDescription.xml in the archive)")
        md = read_model_description(str(p), validate=True)
    except FMUError:
        raise
    except ValidationError as e:
        first = (e.problems or ["invalid"])[0]
        raise FMUError(f"{p}: invalid modelDescription.xml: {first}") from None
    except Exception as e:  # noqa: BLE001 - lxml, zipfile, fmpy: one line
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise FMUError(f"{p}: cannot read modelDescription.xml: {msg}") from None
    version = md.fmiVersion or "?"
    if version != "2.0":
        raise FMUError(f"{p}: FMI {version}; FMU plants support FMI 2.0 Co-Simulation")
    if md.coSimulation is None:
        raise FMUError(f"{p}: a Model Exchange FMU; FMU plants need FMI 2.0 Co-Simulation "
                       "(export the FMU for Co-Simulation)")
    try:
        platforms = fmpy.supported_platforms(str(p))
    except Exception as e:  # noqa: BLE001 - fmpy's errors are not one type: one line names the file
        raise FMUError(f"{p}: cannot list its binaries: {e}") from None
    if fmpy.platform not in platforms:
        have = ", ".join(x for x in platforms) or "none"
        raise FMUError(f"{p}: no binary for this platform ({fmpy.platform}); the FMU has: {have}"
                       + (" (C sources: compile the FMU for this platform)" if "c-code" in platforms else ""))
    var = {v.name: v for v in md.modelVariables}
    names = ", ".join(sorted(var))

    def get(name: str, what: str):
        v = var.get(name)
        if v is None:
            raise FMUError(f"{p}: no variable {name!r} ({what}); the FMU has: {names}")
        return v

    ins = []
    for name in inputs:
        v = get(name, "inputs")
        if v.type != "Real" or v.causality != "input":
            raise FMUError(f"{p}: inputs: {name!r} is a {v.type} {v.causality}, not a Real input")
        ins.append((name, int(v.valueReference)))
    sts = []
    for name in states:
        v = get(name, "states")
        if v.type != "Real":
            raise FMUError(f"{p}: states: {name!r} is a {v.type}, not a Real")
        if v.causality in ("input", "parameter", "calculatedParameter", "independent") or v.variability == "constant":
            raise FMUError(f"{p}: states: {name!r} is a {v.variability} {v.causality}, not a state")
        if v.initial not in ("exact", "approx"):
            raise FMUError(f"{p}: states: {name!r} has initial = {v.initial!r}: x0 cannot be set through it "
                           "(the FMU must declare its states with initial = 'exact' or 'approx')")
        sts.append((name, int(v.valueReference), v.initial))
    prs = []
    for name, value in (params or {}).items():
        v = get(name, "params")
        if v.causality != "parameter" or v.variability not in ("fixed", "tunable"):
            raise FMUError(f"{p}: params: {name!r} is a {v.variability} {v.causality}, not a parameter")
        ok = _PARAM_TYPES.get(v.type, ())
        if not ok or isinstance(value, bool) != (v.type == "Boolean") or not isinstance(value, ok):
            raise FMUError(f"{p}: params: {name!r} is {v.type}, got {value!r}")
        if v.type == "Real" and not math.isfinite(float(value)):
            raise FMUError(f"{p}: params: {name!r} must be finite, got {value!r}")
        prs.append((name, int(v.valueReference), v.type, value))
    return FMUInfo(path=str(p.resolve()), fmi_version=version, model_name=md.modelName or "",
                   model_identifier=md.coSimulation.modelIdentifier, guid=md.guid or "", inputs=tuple(ins),
                   states=tuple(sts), params=tuple(prs))


#: the log buffer of each open FMUPlant, by the key its FMU passes back as componentEnvironment
_LOGS: dict[int, list] = {}
_LOG_KEYS = itertools.count(1)
_LOGGER: list = []


def _process_logger():
    """The one FMI logger callback of this process (kept alive for the process's life).

    fmpy's C proxy that formats the FMU's printf-style messages (``addLoggerProxy``)
    keeps a single, process-wide pointer to the Python logger, overwritten by every
    FMU that registers: with one logger per FMUPlant, an FMU instantiated first would
    call the callback of the last one, freed once that one was closed (a crash).  So
    every FMUPlant registers this one callback, which routes each message to its
    FMUPlant's buffer by the ``componentEnvironment`` key the FMU passes back.
    """
    if not _LOGGER:
        from fmpy.fmi2 import fmi2CallbackLoggerTYPE

        def logger(env, _instance, status, _category, message):
            buf = _LOGS.get(env or 0)
            if buf is None:
                return
            text = message.decode("utf-8", "replace") if message else ""
            buf.append(f"[{['ok', 'warning', 'discard', 'error', 'fatal', 'pending'][status]}] {text}"
                       if 0 <= status <= 5 else text)
            del buf[:-20]

        _LOGGER.append(fmi2CallbackLoggerTYPE(logger))
    return _LOGGER[0]


class FMUPlant:
    """An FMI 2.0 Co-Simulation FMU as the true plant: a ``plants.PlantProcess``.

    Parameters
    ----------
    path : the .fmu file.
    inputs, states : the FMU variable names of u (m of them) and x (n of them).
    params : FMU parameters set at every ``reset`` (names of causality parameter).
    instance_name : the FMU instance's name (it appears in the FMU's log messages).

    ``reset(x0)`` must come before the first ``advance``.  Use as a context
    manager or call ``close()``: it frees the instance, unloads the library and
    removes the extracted files.
    """

    def __init__(self, path: str | Path, *, inputs, states, params: dict | None = None,
                 instance_name: str = "plant"):
        self.info = describe(path, inputs=inputs, states=states, params=params)
        self.n = self.info.n
        self.m = self.info.m
        self.t = 0.0
        self._log: list[str] = []
        self._dir = tempfile.mkdtemp(prefix="testbed-fmu-")
        self._fmu = None
        self._x = np.zeros(self.n)
        self._ready = False
        self._vr_u = [vr for _, vr in self.info.inputs]
        self._vr_x = [vr for _, vr, _ in self.info.states]
        from fmpy import extract
        from fmpy.fmi2 import FMU2Slave

        cwd = os.getcwd()
        try:
            extract(self.info.path, self._dir)
            self._fmu = FMU2Slave(guid=self.info.guid, unzipDirectory=self._dir,
                                  modelIdentifier=self.info.model_identifier, instanceName=instance_name)
        except Exception as e:  # noqa: BLE001 - a bad archive member, a library that does not load
            os.chdir(cwd)   # fmpy changes into the binary's folder to load it and stays there when that fails
            self.close()
            msg = str(e).splitlines()[0] if str(e) else type(e).__name__
            raise FMUError(f"{self.info.path}: cannot load the FMU's binary: {msg}") from None
        self._callbacks = self._make_callbacks()

    # -- the FMU's log goes to a short buffer: its last error is part of a fault's line
    def _make_callbacks(self):
        from ctypes import byref

        from fmpy import calloc, free
        from fmpy.fmi2 import fmi2CallbackAllocateMemoryTYPE, fmi2CallbackFreeMemoryTYPE, fmi2CallbackFunctions

        cb = fmi2CallbackFunctions()
        cb.logger = _process_logger()
        cb.allocateMemory = fmi2CallbackAllocateMemoryTYPE(calloc)
        cb.freeMemory = fmi2CallbackFreeMemoryTYPE(free)
        self._log_key = next(_LOG_KEYS)
        _LOGS[self._log_key] = self._log
        cb.componentEnvironment = self._log_key   # the FMU hands it back with every message
        try:
            from fmpy.logging import addLoggerProxy

            addLoggerProxy(byref(cb))   # formats the FMU's printf-style messages in C
        except Exception:  # noqa: BLE001 - without the proxy, messages arrive unformatted
            pass
        return cb

    def _fault(self, what: str, e: Exception | None = None) -> PlantFault:
        last = next((m for m in reversed(self._log) if not m.startswith("[ok]")), "")
        why = f" ({e})" if e is not None else ""
        return PlantFault(f"FMU {Path(self.info.path).name}: {what}{why}" + (f": {last}" if last else ""))

    # -- PlantProcess
    def reset(self, x0: npt.ArrayLike) -> None:
        """Instantiate (or reset) the FMU at t = 0, set the parameters, set x0 in initialization mode."""
        if self._fmu is None:
            raise PlantFault(f"FMU {Path(self.info.path).name}: closed")
        x0 = np.asarray(x0, dtype=np.float64).reshape(-1)
        if x0.shape != (self.n,) or not np.all(np.isfinite(x0)):
            raise ValueError(f"x0 must be {self.n} finite numbers, got {x0.tolist()}")
        f = self._fmu
        self._log.clear()
        try:
            if f.component is None:
                f.instantiate(callbacks=self._callbacks, loggingOn=False)
            else:
                f.reset()
            f.setupExperiment(startTime=0.0)
            for _name, vr, typ, value in self.info.params:
                {"Real": f.setReal, "Integer": f.setInteger, "Boolean": f.setBoolean,
                 "String": f.setString}[typ]([vr], [value])
            approx = [(vr, v) for (_, vr, init), v in zip(self.info.states, x0) if init == "approx"]
            if approx:  # initial = approx: settable before initialization mode only
                f.setReal([a for a, _ in approx], [float(v) for _, v in approx])
            f.enterInitializationMode()
            exact = [(vr, v) for (_, vr, init), v in zip(self.info.states, x0) if init == "exact"]
            if exact:
                f.setReal([a for a, _ in exact], [float(v) for _, v in exact])
            f.setReal(self._vr_u, [0.0] * self.m)
            f.exitInitializationMode()
            x = np.array(f.getReal(self._vr_x), dtype=np.float64)
        except PlantFault:
            raise
        except Exception as e:  # noqa: BLE001 - FMICallException and "Failed to instantiate model"
            raise self._fault("initialization failed", e) from None
        if not np.array_equal(x, x0):
            raise PlantFault(f"FMU {Path(self.info.path).name}: the state after initialization is {x.tolist()}, "
                             f"not x0 = {x0.tolist()} (the state variables do not hold the state)")
        self._x = x
        self.t = 0.0
        self._ready = True

    def advance(self, u: npt.ArrayLike, dt: float) -> int:
        """Hold u for dt seconds (``fmi2DoStep(t, dt)``); 0 on success, ``PlantFault`` on failure."""
        dt = float(dt)
        if dt == 0.0:
            return 0
        if not self._ready:
            raise PlantFault(f"FMU {Path(self.info.path).name}: advance before reset"
                             if self._fmu is not None else f"FMU {Path(self.info.path).name}: closed")
        if not dt > 0.0 or not math.isfinite(dt):
            raise ValueError(f"dt must be >= 0, got {dt}")
        u = np.asarray(u, dtype=np.float64).reshape(-1)
        if u.shape != (self.m,):
            raise ValueError(f"u must have {self.m} entries, got {u.tolist()}")
        f = self._fmu
        if f is None:
            raise PlantFault("the FMU was closed")
        try:
            f.setReal(self._vr_u, [float(v) for v in u])
            f.doStep(currentCommunicationPoint=self.t, communicationStepSize=dt)
            x = np.array(f.getReal(self._vr_x), dtype=np.float64)
        except Exception as e:  # noqa: BLE001 - FMICallException: one line, the run ends as a plant fault
            self._ready = False
            raise self._fault(f"step from t = {self.t:.6g} s by {dt:.6g} s failed", e) from None
        if not np.all(np.isfinite(x)):
            self._ready = False
            raise PlantFault(f"FMU {Path(self.info.path).name}: non-finite state {x.tolist()} at "
                             f"t = {self.t + dt:.6g} s")
        self.t += dt
        self._x = x
        return 0

    @property
    def x(self) -> np.ndarray:
        return self._x.copy()

    def close(self) -> None:
        key = getattr(self, "_log_key", None)
        if key is not None:
            _LOGS.pop(key, None)
        f, self._fmu = self._fmu, None
        self._ready = False
        if f is not None:
            try:
                if f.component is not None:
                    try:
                        f.terminate()
                    except Exception:  # noqa: BLE001 - a failed FMU may refuse to terminate
                        pass
                    f.freeInstance()    # also unloads the library
                else:
                    f.freeLibrary()
            except Exception:  # noqa: BLE001 - closing: the library may be gone already
                pass
        if self._dir:
            shutil.rmtree(self._dir, ignore_errors=True)
            self._dir = ""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


__all__ = ["FMUError", "FMUInfo", "FMUPlant", "describe", "INSTALL_HINT"]
