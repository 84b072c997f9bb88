"""Types: mypy over testbed/, plants/ and attackers/ with the configuration in pyproject.toml ([tool.mypy]).

One mypy run, with the per-module ``ignore_errors`` list of pyproject.toml taken out: the modules that
have errors must be exactly that list (a module on it that became clean comes off it, and no module
off it may gain an error), so the configured check, the one a developer runs as ``mypy``, is clean
and the list of modules still to type only shrinks.
"""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

# mypy over the whole code takes a minute and more (87 s for the first test on a busy 2-core machine): slow tier
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]


def _config() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["mypy"]


def _ignored(cfg: dict) -> set[str]:
    out: set[str] = set()
    for o in cfg.get("overrides", []):
        if o.get("ignore_errors"):
            mods = o["module"]
            out.update([mods] if isinstance(mods, str) else mods)
    return out


def _module(path: str) -> str:
    p = Path(path).with_suffix("")
    parts = list(p.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def test_mypy_is_clean_and_the_untyped_list_is_exact(tmp_path):
    cfg = _config()
    ignored = _ignored(cfg)
    strict_cfg = {k: v for k, v in cfg.items() if k != "overrides"}
    strict_cfg["overrides"] = [o for o in cfg.get("overrides", []) if not o.get("ignore_errors")]
    lines = ["[mypy]"]
    for k, v in strict_cfg.items():
        if k in ("overrides", "files"):
            continue
        lines.append(f"{k} = {str(v).lower() if isinstance(v, bool) else v}")
    for o in strict_cfg["overrides"]:
        mods = o["module"] if isinstance(o["module"], str) else ",".join(o["module"])
        lines.append(f"[mypy-{mods}]")
        lines += [f"{k} = {str(v).lower() if isinstance(v, bool) else v}" for k, v in o.items() if k != "module"]
    ini = tmp_path / "mypy.ini"
    ini.write_text("\n".join(lines) + "\n")
    cache = ROOT / ".mypy_cache"
    r = subprocess.run([sys.executable, "-m", "mypy", "--config-file", str(ini), "--cache-dir", str(cache),
                        "--no-error-summary", "--show-error-codes", *cfg["files"]],
                       cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode in (0, 1), r.stderr[-2000:]
    errors = [ln for ln in r.stdout.splitlines() if re.match(r"^\S+\.py:\d+: error:", ln)]
    failing = {_module(ln.split(":")[0]) for ln in errors}
    unlisted = sorted(failing - ignored)
    assert not unlisted, "type errors in modules that are meant to be typed:\n" + "\n".join(
        ln for ln in errors if _module(ln.split(":")[0]) in unlisted)
    clean = sorted(ignored - failing)
    assert not clean, f"these modules type-check now: take them off [tool.mypy] ignore_errors in pyproject.toml: {clean}"


def test_mypy_as_configured_is_clean():
    """``mypy`` at the project's root, as a developer runs it, reads pyproject.toml and finds nothing."""
    r = subprocess.run([sys.executable, "-m", "mypy", "--cache-dir", str(ROOT / ".mypy_cache")], cwd=ROOT,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-1000:]


STRICT = ("--disallow-untyped-defs", "--disallow-incomplete-defs", "--check-untyped-defs")


def _strict_list(cfg: dict) -> set[str]:
    out: set[str] = set()
    for o in cfg.get("overrides", []):
        if o.get("disallow_untyped_defs"):
            mods = o["module"]
            out.update([mods] if isinstance(mods, str) else mods)
    return out


def test_every_module_that_passes_strict_is_on_the_strict_list():
    """A module that type-checks with the strict flags (every function annotated, every body checked) is on the
    strict override of pyproject.toml, so that it stays strict: the list only grows."""
    cfg = _config()
    r = subprocess.run([sys.executable, "-m", "mypy", "--cache-dir", str(ROOT / ".mypy_cache" / "strict"),
                        "--no-error-summary", "--show-error-codes", *STRICT, *cfg["files"]],
                       cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode in (0, 1), r.stderr[-2000:]
    failing = {_module(ln.split(":")[0]) for ln in r.stdout.splitlines() if re.match(r"^\S+\.py:\d+: error:", ln)}
    modules = {_module(str(p.relative_to(ROOT))) for pk in cfg["files"] for p in (ROOT / pk).rglob("*.py")}
    missing = sorted(modules - failing - _strict_list(cfg))
    assert not missing, f"these modules pass the strict flags: add them to the strict override in pyproject.toml: {missing}"
