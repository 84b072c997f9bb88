"""Helpers every layer shares: bad input (``errors``, ``validate``), a command's guarded run and
shared flags (``dispatch``, ``cliargs``), a run option's one definition (``optionspec``),
the figure style, the progress bar, the compile notice, protobuf, and the statistics of
comparisons (``comparestats``)."""
