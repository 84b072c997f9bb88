"""The one exception type for input a user gave that cannot be used.

Every command turns a ``BadInput`` into one line on stderr and exit status 2
(``testbed.cli``): a broken scenario file, a recording that is not one, a flag
value out of range.  Subclasses name where the input came from.
"""

from __future__ import annotations


class BadInput(ValueError):
    """Input that cannot be used, with the reason (one line, exit 2)."""


#: exit codes of every command (documented in docs/cli.md)
EXIT_OK = 0
EXIT_FAILED = 1      # the run or job ran and failed (a fault, a run that did not complete)
EXIT_BAD_INPUT = 2   # bad input: nothing was run, or nothing trustworthy came out

__all__ = ["BadInput", "EXIT_OK", "EXIT_FAILED", "EXIT_BAD_INPUT"]
