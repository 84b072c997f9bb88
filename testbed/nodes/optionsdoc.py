"""The options table of docs/cli.md, generated from the one definition of each live-run option
(``testbed.common.optionspec``): ``python -m testbed.nodes.optionsdoc`` rewrites the block between
``<!-- BEGIN generated:options -->`` and ``<!-- END generated:options -->``, ``--check`` exits 1 when it is stale."""

from __future__ import annotations

import re
import sys
from pathlib import Path

from ..common import optionspec
from ..wire.session import SessionOptions
from .options import NodeConfig, RecorderConfig, RunConfig, RunOptions

#: the configurations whose options the table lists, in its order
CLASSES = (RunOptions, SessionOptions, RunConfig, NodeConfig, RecorderConfig)

DOC = Path(__file__).resolve().parents[2] / "docs" / "cli.md"

_BLOCK = re.compile(r"(<!-- BEGIN generated:options -->\n)(.*?)(<!-- END generated:options -->)", re.S)


def options_table() -> str:
    return optionspec.table(CLASSES)


def render(text: str) -> str:
    """``text`` with its options block regenerated."""
    return _BLOCK.sub(lambda m: m.group(1) + options_table() + m.group(3), text)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    text = DOC.read_text(encoding="utf-8")
    new = render(text)
    if "--check" in argv:
        if new != text:
            print(f"{DOC}: the options table is stale (python -m testbed.nodes.optionsdoc)", file=sys.stderr)
            return 1
        return 0
    DOC.write_text(new, encoding="utf-8")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
