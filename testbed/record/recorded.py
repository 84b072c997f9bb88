"""The scenario a recording stores, and rebuilding it: the TOML with the run's overrides, the plant
and model modules (imported as the run did, or from the stored source), the resolved values."""

from __future__ import annotations

import json
import platform
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .topics import FORMAT_VERSION

if TYPE_CHECKING:
    from ..scenario import Scenario


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


def scenario_metadata(sc: Scenario, ref: str | None = None) -> dict[str, str]:
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


def recorded_scenario(metadata: dict[str, dict], path: str = "recording", *, trust_code: bool = False,
                      note: bool = True, _cache: Any = None) -> tuple[Scenario, dict | None, dict | None]:
    """The scenario a recorded run used, rebuilt from the TOML stored in its metadata.

    Returns ``(scenario, plant_source, model_source)``.  The run's overrides are applied
    and what the run resolved (``testbed.resolved``: the quantizer, the timing) wins over
    this version's defaults.  The plant, a ``[model]`` of another class and the method are
    imported as the run did (their reference, from the scenario's folder first: the user's own
    code).  When one cannot be, the module's source stored in the recording is code, and is run
    only with ``trust_code`` (``--trust-code``; a line on stderr says it ran).  Without it the
    scenario holds a stand-in (its recorded name, dimensions, parameters and bits, no code:
    ``Scenario.code_not_run``), one line on stderr says what is skipped, and everything that
    needs no code reads as before (``note=False``: no such line, for a caller that raises instead).
    ``plant_source`` tells which happened
    (``plants.refs.resolve_recorded``).
    """
    import tomllib

    from plants.refs import CodeNotTrusted

    from ..scenario import loads, with_overrides
    from ..scenario.spec import ScenarioError
    from ..scenario.write import to_toml

    meta = metadata.get("testbed.scenario", {})
    toml = meta.get("toml")
    if not toml:
        raise ScenarioError(f"{path}: no scenario in the recording's metadata (not a recording of testbed run or "
                            "testbed simulate --out)")
    base_dir = meta.get("base_dir") or None
    try:
        data = tomllib.loads(toml)
    except tomllib.TOMLDecodeError as e:
        raise ScenarioError(f"{path} (recorded scenario): not valid TOML: {e}") from None
    stand = _StandIns(metadata, data, path)
    try:
        if _cache is not None and getattr(_cache, "_resolved", False):  # once per recording: report and replay
            ps, ms = _cache.plant_source, _cache.model_source
            stand.restore(getattr(_cache, "_stand_ins", None))
        else:
            ps = _resolve_plant(meta, base_dir, "plant", path, trust_code, stand)
            ms = _resolve_plant(meta, base_dir, "model", path, trust_code, stand)
            _resolve_method(meta, base_dir, path, trust_code, stand)
            if stand.used and note:
                print(f"note: {'; '.join(stand.used)}: what needs that code is skipped (re-simulation, the escape "
                      "verdict, the region of attraction); the recorded values are read as they are", file=sys.stderr)
            if _cache is not None:
                _cache._resolved, _cache._stand_ins = True, stand.flags()
        changed = False
        if meta.get("attack_trace"):  # an embedded trace replaces the file the run read it from
            data["attack"] = json.loads(meta["attack_trace"])
            changed = True
        if stand.used:  # nothing of the scenario derived from code that is not run: the recorded values
            stand.patch(data)
            changed = True
        if changed:
            toml = to_toml(data)
        design = not stand.used
        sc = loads(toml, name=str(meta.get("name", "recorded"))[:200], where=f"{path} (recorded scenario)",
                   base_dir=base_dir, check_fmu=False, check_design=design)
        over = metadata.get("testbed.run", {}).get("scenario_overrides")
        try:
            sc = with_overrides(sc, json.loads(over), check_design=design) if over else sc
        except (ValueError, TypeError) as e:
            if isinstance(e, CodeNotTrusted):
                raise
            raise ScenarioError(f"{path}: recorded overrides: {e}") from None
    except CodeNotTrusted as e:  # a scenario that needs the code even to be read
        raise ScenarioError(f"{path}: {e}") from None
    return _with_resolved(sc, metadata.get("testbed.resolved")), ps, ms


class _StandIns:
    """The classes a recording's data stands in for, when their stored source is not run."""

    def __init__(self, metadata: dict, data: dict, path: str):
        self.data, self.path = data, path
        self.used: list[str] = []
        self.model_stand_in = self.method_stand_in = False
        res = metadata.get("testbed.resolved") or {}
        try:
            K = json.loads(res["K"])
            self.m, self.n = len(K), len(K[0])
            self.K = K
        except (KeyError, TypeError, ValueError, IndexError):
            self.K = None
        self.L_u: float | None
        try:
            self.L_u = float(json.loads(res["L_u"]))
            self.rule = json.loads(res["quantizer"]).get("rule")
        except (KeyError, TypeError, ValueError, AttributeError):
            self.L_u, self.rule = None, None
        try:
            bits = int(metadata.get("testbed.run", {}).get("bits", ""))
            self.bits = bits if 0 < bits < 1 << 20 else None
        except ValueError:
            self.bits = None

    def flags(self) -> tuple:
        return list(self.used), self.model_stand_in, self.method_stand_in

    def restore(self, flags) -> None:
        if flags:
            self.used, self.model_stand_in, self.method_stand_in = list(flags[0]), flags[1], flags[2]

    def _table(self, name: str) -> dict:
        t = self.data.get(name)
        return t if isinstance(t, dict) else {}

    def plant(self, prefix: str, ref: str, class_name: str):
        """A factory of the stand-in of the recorded plant (``prefix`` "plant") or model ("model")."""
        from plants.refs import CodeNotTrusted, not_trusted, stand_in_plant

        def make():
            if self.K is None:
                raise CodeNotTrusted(f"{not_trusted(prefix, ref)} (the recording stores no resolved K)")
            params = self._table(prefix).get("params")
            if prefix == "model" and "params" not in self._table("model"):
                params = self._table("plant").get("params")
            self.used.append(str(not_trusted(prefix, ref, self.path)))
            if prefix == "model" or self._table("model").get("name", ref) == ref:  # the model is this class
                self.model_stand_in = True
            return stand_in_plant(ref, class_name, self.n, self.m, list(params) if isinstance(params, dict) else [])
        return make

    def method(self, ref: str, class_name: str):
        """A factory of the stand-in of the recorded method."""
        from plants.refs import not_trusted

        from ..methods.registry import stand_in_method

        def make():
            self.used.append(str(not_trusted("method", ref, self.path)))
            self.method_stand_in = self._table("method").get("name") == ref  # not a --method swap
            uses = [k for k in self._table("quantizer") if k != "T"]
            return stand_in_method(ref, class_name, dict.fromkeys([*uses, "allow_M_le_Lambda", "allow_x0_outside",
                                                                   "L_u"]), self.bits)
        return make

    def patch(self, data: dict) -> None:
        """The recorded scenario's data with what a stand-in cannot give taken from the recording: the
        resolved K (no design on a model without code) and L_u; the checks the run passed not repeated."""
        qt = data.setdefault("quantizer", {})
        if self.model_stand_in and self.K is not None:
            ct = data.get("controller")
            ct = ct if isinstance(ct, dict) else {}
            data["controller"] = {"K": self.K, **({"u_max": ct["u_max"]} if "u_max" in ct else {})}
            if self.rule == "delay-aware" and "L_u" not in qt and self.L_u is not None:
                qt["L_u"] = self.L_u
        if self.method_stand_in:
            qt["allow_M_le_Lambda"] = qt["allow_x0_outside"] = True


def _resolve_plant(meta: dict, base_dir: str | None, prefix: str, path: str, trust_code: bool,
                   stand: _StandIns) -> dict | None:
    """Resolve the recorded plant (or model) reference, pinning the stored source (``trust_code``) or a
    stand-in when it is not importable."""
    from plants.refs import PlantRefError, resolve_recorded

    ref = meta.get(f"{prefix}_ref")
    if not ref:
        return None  # an FMU plant, a model that is the plant, or a recording from before references were stored
    try:
        _cls, status = resolve_recorded(ref, base_dir, module=meta.get(f"{prefix}_module", ""),
                                        class_name=meta.get(f"{prefix}_class", ""),
                                        source=meta.get(f"{prefix}_source", ""),
                                        sha256=meta.get(f"{prefix}_sha256", ""), trust_code=trust_code,
                                        stand_in=stand.plant(prefix, ref, meta.get(f"{prefix}_class", "")))
    except PlantRefError as e:
        from ..scenario.spec import ScenarioError

        raise ScenarioError(f"{path}: {e}") from None
    status["module"] = meta.get(f"{prefix}_module", "")
    if status["loaded_from"] == "recording":
        print(f"note: {prefix} module {status['module']!r} is not importable ({status['reason']}); "
              f"loaded the source stored in {path} (sha256 {status['sha256'][:12]}): "
              "this runs code from the recording (--trust-code)", file=sys.stderr)
    elif status["differs"]:
        print(f"note: {prefix} module {status['module']!r} as imported now differs from the one recorded "
              f"in {path} (sha256 {status['importable_sha256'][:12]} vs {status['sha256'][:12]})",
              file=sys.stderr)
    return status


def _resolve_method(meta: dict, base_dir: str | None, path: str, trust_code: bool, stand: _StandIns) -> None:
    """Resolve the recorded method reference, pinning its stored source (``trust_code``) or a stand-in when
    it is not importable."""
    from ..methods import MethodError
    from ..methods.registry import resolve_recorded
    from ..scenario.spec import ScenarioError

    ref = meta.get("method_ref")
    if not ref:
        return  # a recording from before methods: the paper's
    try:
        st = resolve_recorded(ref, base_dir, module=meta.get("method_module", ""),
                              class_name=meta.get("method_class", ""), source=meta.get("method_source", ""),
                              sha256=meta.get("method_sha256", ""), trust_code=trust_code,
                              stand_in=stand.method(ref, meta.get("method_class", "")))
    except MethodError as e:
        raise ScenarioError(f"{path}: {e}") from None
    if st["loaded_from"] == "recording":
        print(f"note: method module {meta.get('method_module')!r} is not importable ({st['reason']}); loaded the "
              f"source stored in {path} (sha256 {meta.get('method_sha256', '')[:12]}): this runs code from the "
              "recording (--trust-code)", file=sys.stderr)


def _with_resolved(sc, meta: dict | None):
    """``sc`` with the quantizer and timing the recorded run resolved (a later version's defaults
    may differ: the recording's own values win)."""
    import dataclasses

    from ..loop.quantizer import QuantizerParams
    from ..scenario.spec import DelaySpec, SimDelaySpec

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


def resolved_metadata(sc: Scenario) -> dict[str, str]:
    """What the run resolved from its scenario: the quantizer's parameters (the delay-aware rule's
    nominal delays and margins included), the timing and its bounds (``testbed.resolved``)."""
    import dataclasses

    run = dataclasses.asdict(sc.run)
    return {"quantizer": json.dumps(dataclasses.asdict(sc.quantizer)), "run": json.dumps(run),
            "timing_params_ns": json.dumps([int(v) for v in sc.timing_params]), "L_u": json.dumps(sc.L_u),
            "K": json.dumps(sc.K.tolist()), "u_max": json.dumps(sc.controller.u_max)}
