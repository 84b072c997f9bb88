"""The bundled methods: the paper's and the baselines it argues against (docs/methods.md).

* ``paper``: the resilient zoom quantizer and control law (2) of the paper (Algorithms 1, 2,
  rules (xi), (E); ``[quantizer] mode`` ideal or resilient with OVERFLOW): ``methods.paper``'s
  ``PaperEncoder`` / ``PaperDecoder``, written against the end API like every other method.
* ``zoom``: the zoom quantizer without DoS resilience (Liberzon and Hespanha 2005): the
  zoom-in E_{k+1} = (Lambda / M) E_k at *every* sample, whether or not the packet got
  through; its zoom-out stage after a saturation (OVERFLOW, as the paper's resilient mode).
* ``static``: a static uniform quantizer, range [-R, R]^n (``params.range``), M levels per
  coordinate, no zoom: u_k = (1 - theta_k) K q_k (at best practical stability).
* ``unquantized``: exact state feedback, u_k = (1 - theta_k) K x_k (infinite data rate).
* ``unquantized-hold``: exact state feedback that holds the last received input through a
  loss, u_k = K x_k if theta_k = 0, else u_{k-1} (De Persis and Tesi 2015).
"""

from __future__ import annotations

from typing import Any

from ..loop.params import Codebook, QuantizerParams
from .base import FloatCodebook, Method, MethodError, finite_params

#: batch kernel codes (``sim.kernel._batch_kernel`` ``mode``); 0, 1 are the paper's ideal and resilient
KERNEL_STATIC = 3
KERNEL_ZOOM = 4
KERNEL_UNQUANTIZED = 5
KERNEL_HOLD = 6

_PAPER_KEYS = ("M", "L", "E0", "mode", "zoom_out", "E_min", "rule", "L_u", "allow_M_le_Lambda", "allow_x0_outside")


class _LazyEnd:
    """A class attribute naming an end of ``methods.ends``, imported on first use (the ends load numba:
    reading a scenario does not)."""

    def __init__(self, name: str):
        self.name = name

    def __get__(self, obj: object, owner: type | None = None) -> Any:
        from . import ends

        return getattr(ends, self.name)


class PaperMethod(Method):
    name = "paper"
    description = "the paper's resilient zoom quantizer and control law (2) (both modes)"
    source = "the paper (Algorithms 1 and 2, rules (xi), (E)); OVERFLOW: the testbed's resilient mode"
    uses = _PAPER_KEYS
    encoder_class = _LazyEnd("PaperEncoder")
    decoder_class = _LazyEnd("PaperDecoder")

    def codebook(self, n: int, qp: QuantizerParams) -> Codebook:
        return Codebook(n, qp.M, resilient=(qp.mode == "resilient"))

    def kernel_code(self, qp: QuantizerParams) -> int:
        return 1 if qp.mode == "resilient" else 0


class ZoomMethod(Method):
    name = "zoom"
    description = "zoom quantizer without DoS resilience: zoom-in at every sample, zoom-out after a saturation"
    source = "D. Liberzon and J. P. Hespanha, Stabilization of nonlinear systems with limited information " \
             "feedback, IEEE TAC 50(6), 2005"
    uses = ("M", "L", "E0", "zoom_out", "E_min", "allow_M_le_Lambda", "allow_x0_outside")
    kernel_mode = KERNEL_ZOOM
    encoder_class = _LazyEnd("ZoomEncoder")
    decoder_class = _LazyEnd("ZoomDecoder")

    def codebook(self, n: int, qp: QuantizerParams) -> Codebook:
        return Codebook(n, qp.M, resilient=True)


class StaticMethod(Method):
    name = "static"
    description = "static uniform quantizer: fixed range [-range, range]^n, M levels per coordinate, no zoom"
    source = "a uniform quantizer of fixed range (e.g. D. F. Delchamps, IEEE TAC 35(8), 1990; practical stability)"
    uses = ("M",)
    defaults = {"range": 1.0}
    kernel_mode = KERNEL_STATIC
    encoder_class = _LazyEnd("StaticEncoder")
    decoder_class = _LazyEnd("StaticDecoder")

    def check_params(self) -> None:
        finite_params(self, "range")

    def codebook(self, n: int, qp: QuantizerParams) -> Codebook:
        return Codebook(n, qp.M, resilient=False)

    def kernel_E0(self, qp: QuantizerParams) -> float:
        return float(self.params["range"])


class UnquantizedMethod(Method):
    name = "unquantized"
    description = "exact state feedback, zero input through a loss (the infinite-data-rate control law (2))"
    source = "control law (2) of the paper with q_k = x_k"
    kernel_mode = KERNEL_UNQUANTIZED
    encoder_class = _LazyEnd("ExactEncoderZero")
    decoder_class = _LazyEnd("ExactDecoder")

    def codebook(self, n: int, qp: QuantizerParams) -> FloatCodebook:
        return FloatCodebook(n)

    def kernel_E0(self, qp: QuantizerParams) -> float:
        return 0.0


class UnquantizedHoldMethod(UnquantizedMethod):
    name = "unquantized-hold"
    description = "exact state feedback holding the last received input through a loss"
    source = "C. De Persis and P. Tesi, Input-to-state stabilizing control under denial-of-service, IEEE TAC 60(11), 2015"
    kernel_mode = KERNEL_HOLD
    encoder_class = _LazyEnd("ExactEncoder")
    decoder_class = _LazyEnd("HoldDecoder")


BUNDLED = {c.name: c for c in (PaperMethod, ZoomMethod, StaticMethod, UnquantizedMethod, UnquantizedHoldMethod)}

__all__ = ["BUNDLED", "PaperMethod", "ZoomMethod", "StaticMethod", "UnquantizedMethod", "UnquantizedHoldMethod",
           "MethodError"]
