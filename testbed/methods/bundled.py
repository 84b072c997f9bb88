"""The bundled methods: the paper's and the baselines it argues against (docs/methods.md).

* ``paper``: the resilient zoom quantizer and control law (2) of the paper (Algorithms 1, 2,
  rules (xi), (E); ``[quantizer] mode`` ideal or resilient with OVERFLOW) -- the very
  ``quantizer.Encoder`` / ``quantizer.Decoder`` objects.
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

from dataclasses import replace

import numba as nb
import numpy as np

from ..flow import compiled_for
from ..loopspec import ROUNDOFF, Codebook
from ..quantizer import Decoder, Encoder, box_center, control_input, quantize_index, zoom_update
from .base import DecoderEnd, EncoderEnd, FloatCodebook, Method, MethodError, finite_params

#: batch kernel codes (``simulate._batch_kernel`` ``mode``); 0, 1 are the paper's ideal and resilient
KERNEL_STATIC = 3
KERNEL_ZOOM = 4
KERNEL_UNQUANTIZED = 5
KERNEL_HOLD = 6

_PAPER_KEYS = ("M", "L", "E0", "mode", "zoom_out", "E_min", "rule", "L_u", "allow_M_le_Lambda", "allow_x0_outside")


# ============================================================================ paper
class PaperMethod(Method):
    name = "paper"
    description = "the paper's resilient zoom quantizer and control law (2) (both modes)"
    source = "the paper (Algorithms 1 and 2, rules (xi), (E)); OVERFLOW: the testbed's resilient mode"
    uses = _PAPER_KEYS

    def codebook(self, n, qp):
        return Codebook(n, qp.M, resilient=(qp.mode == "resilient"))

    def make_encoder(self, model, K, qp, flow):
        return Encoder(model, K, qp, flow)

    def make_decoder(self, model, K, qp, flow):
        return Decoder(model, K, qp, flow)

    def kernel_code(self, qp) -> int:
        return 1 if qp.mode == "resilient" else 0


# ============================================================================ zoom (Liberzon-Hespanha)
@nb.njit(cache=True)
def unaware_update(rhs, p, T, opts, Kgain, theta, overflow, xi, E, q, u_prev, Lambda, M, sigma,
                   E_min, dpar, K_s, ytmp, u_s, xi_out):
    """The zoom quantizer's update without DoS resilience: rule (xi) as the paper's, but the
    zoom-in E_{k+1} = (Lambda / M) E_k whatever theta_k (after an OVERFLOW received: the zoom-out
    E_{k+1} = sigma Lambda max(E_k, E_r)); the same floors as ``zoom_update``."""
    En, st = zoom_update(rhs, p, T, opts, Kgain, theta, overflow, xi, E, q, u_prev, Lambda, M, sigma,
                         E_min, dpar, K_s, ytmp, u_s, xi_out)
    if theta == 1:
        En = Lambda / M * E
        big = 0.0
        for i in range(xi_out.shape[0]):
            big = max(big, abs(xi_out[i]))
        if En < ROUNDOFF * big:
            En = ROUNDOFF * big
        if En < E_min:
            En = E_min
    return En, st


class _ZoomEnd:
    def _update(self, theta, overflow, q):
        xi_next = np.empty(self.plant.n)
        u_k = np.empty(self.plant.m)
        qp = self.qp
        args = (self._rhs, self._p, qp.T, self._opts, self.K, int(theta), bool(overflow), self.xi, float(self.E), q,
                self.u_prev, qp.Lambda, qp.M, qp.sigma, qp.E_min, self._dpar, self._Ks, self._ytmp, u_k, xi_next)
        if self._zoom is None:
            E_next, st = unaware_update(*args)
            self._zoom = compiled_for(unaware_update, args)
        else:
            E_next, st = self._zoom(*args)
        self.xi, self.E, self.u_prev, self.flow_status = xi_next, float(E_next), u_k, int(st)
        self.k += 1


class ZoomEncoder(_ZoomEnd, Encoder):
    def __init__(self, model, K, qp, flow):
        super().__init__(model, K, replace(qp, mode="resilient", rule="paper"), flow)
        self._dpar = np.zeros(4)


class ZoomDecoder(_ZoomEnd, Decoder):
    def __init__(self, model, K, qp, flow):
        super().__init__(model, K, replace(qp, mode="resilient", rule="paper"), flow)
        self._dpar = np.zeros(4)


class ZoomMethod(Method):
    name = "zoom"
    description = "zoom quantizer without DoS resilience: zoom-in at every sample, zoom-out after a saturation"
    source = "D. Liberzon and J. P. Hespanha, Stabilization of nonlinear systems with limited information " \
             "feedback, IEEE TAC 50(6), 2005"
    uses = ("M", "L", "E0", "zoom_out", "E_min", "allow_M_le_Lambda", "allow_x0_outside")
    kernel_mode = KERNEL_ZOOM

    def codebook(self, n, qp):
        return Codebook(n, qp.M, resilient=True)

    def make_encoder(self, model, K, qp, flow):
        return ZoomEncoder(model, K, qp, flow)

    def make_decoder(self, model, K, qp, flow):
        return ZoomDecoder(model, K, qp, flow)


# ============================================================================ static
class StaticEncoder(EncoderEnd):
    def symbol(self, x):
        R, M = float(self.method.params["range"]), int(self.qp.M)
        zero = np.zeros(self.plant.n)
        i, sat = quantize_index(x, zero, R, M)
        q = np.empty(self.plant.n)
        box_center(i, zero, R, M, q)
        return int(i), bool(sat), q


class StaticDecoder(DecoderEnd):
    def control(self, symbol):
        n, m = self.plant.n, self.plant.m
        q = np.zeros(n)
        u = np.empty(m)
        if symbol is None:
            control_input(self.K, q, 1, False, u)
        else:
            box_center(int(symbol), np.zeros(n), float(self.method.params["range"]), int(self.qp.M), q)
            control_input(self.K, q, 0, False, u)
        self._u = u
        return u, q

    def update(self, theta, symbol):
        self.u_prev = self._u


class StaticMethod(Method):
    name = "static"
    description = "static uniform quantizer: fixed range [-range, range]^n, M levels per coordinate, no zoom"
    source = "a uniform quantizer of fixed range (e.g. D. F. Delchamps, IEEE TAC 35(8), 1990; practical stability)"
    uses = ("M",)
    defaults = {"range": 1.0}
    kernel_mode = KERNEL_STATIC
    encoder_class = StaticEncoder
    decoder_class = StaticDecoder

    def check_params(self):
        finite_params(self, "range")

    def codebook(self, n, qp):
        return Codebook(n, qp.M, resilient=False)

    def kernel_E0(self, qp):
        return float(self.params["range"])


# ============================================================================ unquantized
class ExactEncoder(EncoderEnd):
    def symbol(self, x):
        self._x = np.array(x, dtype=np.float64)
        return FloatCodebook.encode_state(x), False, self._x

    def update(self, theta, symbol):
        if theta == 0:
            u = np.empty(self.plant.m)
            control_input(self.K, self._x, 0, False, u)
            self.u_prev = u


class ExactDecoder(DecoderEnd):
    hold = False

    def control(self, symbol):
        n, m = self.plant.n, self.plant.m
        u = np.empty(m)
        if symbol is None:
            q = np.zeros(n)
            if self.hold:
                u[:] = self.u_prev
            else:
                control_input(self.K, q, 1, False, u)
        else:
            q = FloatCodebook.decode_state(symbol)
            control_input(self.K, q, 0, False, u)
        self._u = u
        return u, q

    def update(self, theta, symbol):
        if theta == 0 or self.hold:
            self.u_prev = self._u
        else:
            self.u_prev = np.zeros(self.plant.m)


class HoldDecoder(ExactDecoder):
    hold = True


class ExactEncoderZero(ExactEncoder):
    def update(self, theta, symbol):
        if theta == 0:
            super().update(theta, symbol)
        else:
            self.u_prev = np.zeros(self.plant.m)


class UnquantizedMethod(Method):
    name = "unquantized"
    description = "exact state feedback, zero input through a loss (the infinite-data-rate control law (2))"
    source = "control law (2) of the paper with q_k = x_k"
    kernel_mode = KERNEL_UNQUANTIZED
    encoder_class = ExactEncoderZero
    decoder_class = ExactDecoder

    def codebook(self, n, qp):
        return FloatCodebook(n)

    def kernel_E0(self, qp):
        return 0.0


class UnquantizedHoldMethod(UnquantizedMethod):
    name = "unquantized-hold"
    description = "exact state feedback holding the last received input through a loss"
    source = "C. De Persis and P. Tesi, Input-to-state stabilizing control under denial-of-service, IEEE TAC 60(11), 2015"
    kernel_mode = KERNEL_HOLD
    encoder_class = ExactEncoder
    decoder_class = HoldDecoder


BUNDLED = {c.name: c for c in (PaperMethod, ZoomMethod, StaticMethod, UnquantizedMethod, UnquantizedHoldMethod)}

__all__ = ["BUNDLED", "PaperMethod", "ZoomMethod", "StaticMethod", "UnquantizedMethod", "UnquantizedHoldMethod",
           "unaware_update", "MethodError"]
