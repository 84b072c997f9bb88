"""A run option defined once: a field of a frozen dataclass with an ``option(...)`` in its metadata.

From that one definition come the flags of every command that receives the option (``add_arguments``), the
typed configuration built from a parsed command line (``from_args``), the flags that make the same value again
(``argv``: how the launcher hands a node its configuration) and the options table of docs/cli.md (``table``).

A command is named by its ``testbed`` subcommand: ``run``, ``node``, ``record``, ``conformance`` (and ``simulate``,
which takes the run options).  ``per`` overrides the flag's help, default, choices or form for some commands (the
launcher's ``--listen`` is one endpoint, a node's is repeatable); the default of the dataclass field is the one of
every other command, written once.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable, Collection, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any, TypeVar

T = TypeVar("T")

#: every command that receives live-run options
COMMANDS = ("run", "node", "record", "conformance", "simulate")

_UNSET = object()


@dataclass(frozen=True)
class Option:
    """How one field of a configuration is a command-line flag (the parts a command may override: ``per``)."""

    help: str
    commands: tuple[str, ...]
    metavar: str | None = None
    choices: tuple | None = None
    kind: type | None = None                   # argparse ``type`` (None: str, or a switch for a bool field)
    switch: bool = False                       # ``--NAME`` alone, store_true
    repeat: bool = False                       # repeatable (``action="append"``), a tuple in the config
    flag: str | None = None                    # default ``--`` + the field's name with dashes
    short: str | None = None                   # e.g. ``-v``
    group: str | None = None                   # the help group (None: the command's own, or the caller's)
    default: Any = _UNSET                      # the flag's default when it is not the field's
    digest: bool = False                       # enters the run's start digest (``run_digest``)
    hidden: bool = False                       # set by the launcher, not shown in --help
    convert: Callable | None = None            # parsed value -> the field's value
    nargs: str | None = None                   # e.g. "?" with ``const``: ``--NAME`` alone means ``const``
    const: Any = None
    per: dict = field(default_factory=dict)    # command -> {attribute: value} overriding the above

    def on(self, command: str) -> Option:
        """The option as ``command`` takes it."""
        return dataclasses.replace(self, **self.per.get(command, {}), per={}) if command in self.per else self


def option(default: Any = None, help: str = "", *, commands: tuple[str, ...] = ("node",), **kw: Any) -> Any:
    """A dataclass field that is a command-line option (``Option``'s attributes as keywords)."""
    kw.setdefault("switch", default is False and "kind" not in kw)
    meta = {"option": Option(help=help, commands=tuple(commands), **kw)}
    if isinstance(default, (dict, list)):  # a repeatable ROLE=VALUE flag's dict: a new one per config
        return field(default_factory=type(default), metadata=meta)
    return field(default=default, metadata=meta)


def options(cls: type, command: str | None = None) -> Iterator[tuple[dataclasses.Field, Option]]:
    """The option fields of a configuration class (those ``command`` receives), in their order."""
    for f in dataclasses.fields(cls):
        o = f.metadata.get("option")
        if o is not None and (command is None or command in o.commands):
            yield f, o.on(command) if command else o


def flag_of(f: dataclasses.Field, o: Option) -> str:
    return o.flag or "--" + f.name.replace("_", "-")


def default_of(f: dataclasses.Field, o: Option) -> Any:
    """The value a command's flag has when it is not given (the field's default unless the command has its own)."""
    if o.default is not _UNSET:
        return o.default
    if f.default is dataclasses.MISSING and f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return f.default


def defaults(cls: type, command: str) -> dict:
    """The fields of ``cls`` that ``command`` receives, as that command's flags default them."""
    return {f.name: tuple(d) if isinstance(d := default_of(f, o), list) else (() if d is None and isinstance(
        f.default, tuple) else d) for f, o in options(cls, command)}


def add_arguments(p: argparse._ActionsContainer, cls: type, command: str, *, group: argparse._ActionsContainer | None = None,
                  section: str | None = None, names: Collection[str] | None = None) -> None:
    """The flags of ``cls``'s options that ``command`` receives: into ``group`` (a parser or an argument group)
    when given, else into each option's own group of ``p`` (made once, in the order of first use), or ``p``;
    ``section``: only the options of that group, ``names``: only these fields."""
    groups: dict[str, Any] = {}
    for f, o in options(cls, command):
        if (section is not None and o.group != section) or (names is not None and f.name not in names):
            continue
        target = group
        if target is None and o.group is None:
            target = p
        elif target is None and o.group is not None:
            if o.group not in groups:
                groups[o.group] = p.add_argument_group(o.group)
            target = groups[o.group]
        assert target is not None  # group, p or the option's group
        flags = [n for n in (o.short, flag_of(f, o)) if n]
        kw: dict[str, Any] = {"help": argparse.SUPPRESS if o.hidden else o.help}
        if o.switch:
            kw["action"] = "store_true"
        else:
            if o.repeat:
                kw["action"] = "append"
                kw["default"] = []
            else:
                d = default_of(f, o)
                if d is not None and d != ():
                    kw["default"] = d
            if o.kind is not None:
                kw["type"] = o.kind
            if o.choices is not None:
                kw["choices"] = o.choices
            if o.metavar is not None:
                kw["metavar"] = o.metavar
            if o.nargs is not None:
                kw["nargs"], kw["const"] = o.nargs, o.const
        target.add_argument(*flags, dest=f.name, **kw)


def values(cls: type, args: argparse.Namespace, command: str) -> dict:
    """The fields of ``cls`` that ``command`` receives, from a parsed command line (each converted once)."""
    out = {}
    for f, o in options(cls, command):
        v = getattr(args, f.name, default_of(f, o))
        if o.convert is not None:
            v = o.convert(v)
        elif isinstance(f.default, tuple):  # a repeatable flag, or one the launcher takes once
            v = tuple(v) if isinstance(v, (list, tuple)) else (() if v is None else (v,))
        out[f.name] = v
    return out


def from_args(cls: type[T], args: argparse.Namespace, command: str, **given: Any) -> T:
    """``cls`` built from a parsed command line of ``command`` (``given``: the fields that are not options)."""
    return cls(**values(cls, args, command), **given)


def _text(v: object) -> str:
    return repr(v) if isinstance(v, float) else str(v)


def argv(cfg: object, command: str) -> list[str]:
    """The flags of ``command`` that make ``cfg``'s options again: ``--NAME VALUE`` for each value that is set
    (each element of a tuple on its own), ``--NAME`` for each switch that is on."""
    out: list[str] = []
    for f, o in options(type(cfg), command):
        v = getattr(cfg, f.name)
        name = flag_of(f, o)
        if o.switch:
            out += [name] if v else []
        elif isinstance(v, dict):  # ROLE=VALUE flags: read by the launcher itself, never passed on
            raise TypeError(f"{name}: {type(cfg).__name__} is not passed on as the flags of testbed {command}")
        elif isinstance(v, tuple):
            for x in v:
                out += [name, _text(x)]
        elif v is not None:
            out += [name, _text(v)]
    return out


def _cell(v: object) -> str:
    if v is None or v in ((), [], {}) or v is False:
        return ""
    return f"`{v}`"


def _md(text: str) -> str:
    return text.replace("|", "\\|")


def table(classes: Iterable[type], commands: tuple[str, ...] = ("run", "node", "record", "conformance")) -> str:
    """The options table of docs/cli.md: a row per option of ``classes`` and per form of it (the commands that take
    it alike: flag, default and help), and whether it enters the run's start digest."""
    rows = ["| option | commands | default | run digest | what it does |", "|---|---|---|---|---|"]
    for cls in classes:
        for f, o in options(cls):
            if o.hidden:
                continue
            forms: dict[tuple, list[str]] = {}
            for c in commands:
                if c not in o.commands:
                    continue
                oc = o.on(c)
                value = "" if oc.switch else " " + (oc.metavar or ("|".join(oc.choices) if oc.choices
                                                                   else f.name.upper()))
                flag = ", ".join(n for n in (oc.short, flag_of(f, oc)) if n) + value + (
                    " (repeatable)" if oc.repeat else "")
                d = default_of(f, oc)
                text = oc.help.replace("%(default)s", str(d)).replace("%(default)g", f"{d:g}" if isinstance(
                    d, float) else str(d))
                forms.setdefault((flag, _cell(d), text), []).append(c)
            for (flag, d, text), takes in forms.items():
                rows.append(f"| `{_md(flag)}` | {', '.join(takes)} | {_md(d)} | {'yes' if o.digest else ''} | "
                            f"{_md(text)} |")
    return "\n".join(rows) + "\n"
