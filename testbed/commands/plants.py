"""``testbed plants [--json]`` and ``testbed check-plant REF [--scenario S] [--json]``.

``plants`` lists every plant a scenario can name without a module path: the
built-in ones and those of installed plant packages (entry-point group
``dos_testbed.plants``), with n, m and a description.

``check-plant`` runs the contract checks of ``testbed.loop.plantcheck`` on one plant
(a registered name, an entry-point name or ``"module.path:ClassName"``, imported
from the current folder first): one verdict line per check; exit 0 when all
pass, 1 when any fails, 2 when REF cannot be loaded.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..common import cliargs, validate
from ..common.errors import BadInput
from ..record.tracereader import read_recording_trace


def add_arguments_plants(p: argparse.ArgumentParser) -> None:
    cliargs.add_json(p, "the list (name, source, ref, n, m, description, dist, error)")


def main_plants(args: argparse.Namespace) -> int:
    import plants

    rows = plants.available()
    if args.json:
        print(json.dumps({"plants": rows}))
        return 0
    for r in rows:
        dims = f"n = {r['n']}, m = {r['m']}" if r["n"] is not None else "n, m unknown"
        src = r["source"] + (f" ({r['dist']})" if r.get("dist") else "")
        if r.get("shadowed"):
            src += ", SHADOWED by the registered plant of the same name"
        print(f"{r['name']:12s} {dims:14s} {src:28s} {r['description']}")
        if r.get("error"):
            print(f"{'':12s} ERROR: {r['error']}")
    print("(any Plant subclass also works as [plant] name = \"module.path:ClassName\"; see docs/own-plant.md)")
    return 0


def add_arguments_check_plant(p: argparse.ArgumentParser) -> None:
    p.add_argument("ref", metavar="REF", nargs="?",
                   help="a plant: registered name, installed entry-point name, or 'module.path:ClassName' "
                        "(imported from the current folder first, or from --scenario's folder); "
                        "default: the plant --scenario names")
    p.add_argument("--scenario", metavar="S",
                   help="take the plant (unless REF is given), its parameters, L, T and M from this scenario "
                        "(file or bundled name)")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="a plant parameter (repeatable; default: the scenario's, else the class defaults)")
    p.add_argument("--L", type=float, help="Lipschitz constant to check against (default: the scenario's "
                                           "[quantizer] L, else the estimate is only reported)")
    p.add_argument("--T", type=float, help="sampling period of Assumption 2 (default: the scenario's, else 0.1 s)")
    p.add_argument("--M", type=int, help="quantizer levels of Assumption 2 (default: the scenario's, else 6)")
    p.add_argument("--region", type=float, metavar="R",
                   help="Lipschitz box ||x||_inf <= R (default: the plant's lipschitz_region, else 1)")
    p.add_argument("--u-bound", type=float, default=None, metavar="U",
                   help="Lipschitz box ||u||_inf <= U (default 10)")
    cliargs.add_json(p, "the verdicts")


def _param(text: str) -> tuple[str, float]:
    k, s, v = text.partition("=")
    try:
        if not s or not k:
            raise ValueError
        return k.strip(), float(v)
    except ValueError:
        raise BadInput(f"--param must be NAME=NUMBER, got {text!r}") from None


def main_check_plant(args: argparse.Namespace) -> int:
    import plants

    from ..loop import plantcheck

    for name in ("L", "T", "region", "u_bound"):
        v = getattr(args, name)
        if v is not None:
            validate.flag(f"--{name.replace('_', '-')}", v, validate.positive)
    if args.M is not None:
        validate.flag("--M", args.M, validate.count, 2)
    sc = None
    base_dir = str(Path.cwd())
    params: dict = {}
    if args.scenario:
        from .. import scenario

        sc = scenario.load(args.scenario, read_recording_trace=read_recording_trace)
        base_dir = sc.base_dir or base_dir
        if args.ref is None:
            if sc.plant.fmu is not None:
                assert sc.model is not None  # an FMU plant has a [model] (the scenario's check)
                raise BadInput(f"the plant of {args.scenario} is the FMU {sc.plant.fmu.path}: check-plant checks "
                               f"equation (1) plants; check its [model] with testbed check-plant {sc.model.name} "
                               f"--scenario {args.scenario}")
            args.ref = sc.plant.ref or sc.plant.name
        if (sc.plant.ref or sc.plant.name) == args.ref:
            params = dict(sc.plant.params)
    elif args.ref is None:
        raise BadInput("name a plant (REF) or a scenario (--scenario S) whose plant to check; "
                       "testbed plants lists the plants")
    params.update(dict(_param(t) for t in args.param))
    try:
        cls = plants.resolve(args.ref, base_dir)
        plant = plants.instantiate(cls, args.ref, params)
    except ValueError as e:
        raise BadInput(str(e)) from None
    q = sc.quantizer if sc is not None else None
    L = args.L if args.L is not None else (q.L if q else None)
    T = args.T if args.T is not None else (q.T if q else plantcheck.DEFAULT_T)
    M = args.M if args.M is not None else (q.M if q else plantcheck.DEFAULT_M)
    u_bound = args.u_bound if args.u_bound is not None else plantcheck.DEFAULT_U_BOUND
    checks = plantcheck.check_plant(plant, L=L, T=T, M=M, region=args.region, u_bound=u_bound)
    ok = all(c.ok for c in checks)
    origin = ("scenario " + args.scenario) if sc is not None else "defaults (no --scenario)"
    info = {"ref": args.ref, "plant": plants.refs.display_name(cls), "class": f"{cls.__module__}:{cls.__qualname__}",
            "file": plants.refs.source_info(cls)["file"], "n": plant.n, "m": plant.m,
            "description": cls.description, "params": plant.params_dict(),
            "settings": {"L": L, "T": T, "M": M, "u_bound": u_bound, "from": origin},
            "checks": [c.to_dict() for c in checks], "ok": ok}
    if args.json:
        print(json.dumps(info, default=str))
    else:
        print(f"plant {args.ref}: {info['class']} ({info['file']}), n = {plant.n}, m = {plant.m}"
              + (f": {cls.description}" if cls.description else ""))
        print(f"  settings from {origin}: T = {T:g} s, M = {M}, "
              + (f"L = {L:g}" if L is not None else "L = the estimate") + f", ||u||_inf <= {u_bound:g}")
        for c in checks:
            print(f"  {'PASS' if c.ok else 'FAIL'}  {c.name:13s} {c.detail}")
        print(f"  {'all checks pass' if ok else 'SOME CHECKS FAIL'}")
    return 0 if ok else 1


__all__ = ["add_arguments_plants", "main_plants", "add_arguments_check_plant", "main_check_plant"]
