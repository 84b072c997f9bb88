"""The one exception type for input a user gave that cannot be used.

Every command turns a ``BadInput`` into one line on stderr and exit status 2
(``testbed.cli``): a broken scenario file, a recording that is not one, a flag
value out of range.  Subclasses name where the input came from.
"""

from __future__ import annotations


class BadInput(ValueError):
    """Input that cannot be used, with the reason (one line, exit 2)."""


#: exit codes of every command (the one definition: every command's --help epilog and the table of
#: docs/cli.md are made from or checked against ``EXIT_CODES``)
EXIT_OK = 0
EXIT_FAILED = 1      # the run or job ran and failed (a fault, a run that did not complete)
EXIT_BAD_INPUT = 2   # bad input: nothing was run, or nothing trustworthy came out
EXIT_RECORDING_INCOMPLETE = 3   # testbed run: the run was clean, its recording is incomplete

#: code -> what it means, in the words of every command's help epilog
EXIT_CODES: dict[int, str] = {
    EXIT_OK: "ok",
    EXIT_FAILED: "the run or job failed",
    EXIT_BAD_INPUT: "bad input",
    EXIT_RECORDING_INCOMPLETE: "testbed run: the run was clean but its recording is incomplete",
}

#: the epilog of ``testbed --help`` and of every command's ``--help``
EPILOG = "exit codes: " + ", ".join(f"{code} {meaning}" for code, meaning in EXIT_CODES.items())

__all__ = ["BadInput", "EPILOG", "EXIT_BAD_INPUT", "EXIT_CODES", "EXIT_FAILED", "EXIT_OK",
           "EXIT_RECORDING_INCOMPLETE"]
