"""Coding-and-control methods behind one interface (docs/methods.md).

``Method`` with its ``EncoderEnd`` and ``DecoderEnd`` (what both hold and may call: ``End``); the
bundled methods (``paper``, ``zoom``, ``static``, ``unquantized``, ``unquantized-hold``); references
resolved like plants'.
"""

from .base import (
    DecoderEnd,
    EncoderEnd,
    End,
    FloatCodebook,
    IntCodebook,
    Method,
    MethodError,
    symbol_code,
    valid_symbol,
)
from .bundled import BUNDLED
from .registry import DEFAULT, ENTRY_POINT_GROUP, entry_points, make, names, register, resolve, source_info

__all__ = ["Method", "End", "EncoderEnd", "DecoderEnd", "MethodError", "IntCodebook", "FloatCodebook", "symbol_code",
           "valid_symbol", "BUNDLED", "DEFAULT", "ENTRY_POINT_GROUP", "entry_points", "make", "names", "register",
           "resolve", "source_info"]
