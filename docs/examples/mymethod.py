"""mymethod.py: a coding-and-control method of your own (docs/methods.md, "Bring your own method").

A zoom quantizer centred at the origin: the box [-E_k, E_k]^n is split into M levels per
coordinate, the decoder applies u_k = K q_k, and both ends update the range from theta_k alone,

    E_{k+1} = a E_k        if theta_k = 0 (zoom in),
    E_{k+1} = Lambda E_k   if theta_k = 1 (zoom out by the growth bound Lambda = e^{L T}),

so that encoder and decoder stay in lockstep (the testbed checks it).  Through a loss the decoder
applies u_k = 0.  It reads ``[quantizer] M, L, E0`` (so the paper's method runs on the same
scenario: ``testbed versus``) and one parameter of its own, ``a`` (``[method] params``, default 0.96).
"""

import math

import numpy as np

from testbed.methods import DecoderEnd, EncoderEnd, IntCodebook, Method


def _cell(x, E, M):
    """Per-coordinate cell index in 0..M-1 of x in [-E, E] (clipped), and whether x was outside."""
    s = np.floor((np.asarray(x) + E) / (2.0 * E) * M)
    sat = bool(np.any(np.abs(x) > E))
    return np.clip(s, 0, M - 1).astype(int), sat


class CenteredEncoder(EncoderEnd):
    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.E = float(self.qp.E0)

    def symbol(self, x):
        M = int(self.qp.M)
        c, sat = _cell(x, self.E, M)
        code = int(sum(int(cj) * M**j for j, cj in enumerate(c)))
        q = -self.E + (2.0 * c + 1.0) * self.E / M
        return code, sat, q

    def update(self, theta, symbol):
        self.E *= self.method.params["a"] if theta == 0 else self.qp.Lambda


class CenteredDecoder(DecoderEnd):
    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.E = float(self.qp.E0)

    def control(self, symbol):
        n = self.plant.n
        if symbol is None:
            return np.zeros(self.plant.m), np.zeros(n)
        M = int(self.qp.M)
        c = np.array([(int(symbol) // M**j) % M for j in range(n)], dtype=float)
        q = -self.E + (2.0 * c + 1.0) * self.E / M
        return self.K @ q, q

    def update(self, theta, symbol):
        self.E *= self.method.params["a"] if theta == 0 else self.qp.Lambda


class CenteredZoom(Method):
    name = "centered-zoom"
    description = "zoom quantizer centred at 0: E shrinks by a when received, grows by Lambda when lost"
    source = "docs/examples/mymethod.py (a worked example)"
    uses = ("M", "L", "E0")         # the [quantizer] keys it reads besides T
    defaults = {"a": 0.96}
    encoder_class = CenteredEncoder
    decoder_class = CenteredDecoder

    def codebook(self, n, qp):
        return IntCodebook(max(1, math.ceil(n * math.log2(int(qp.M)))))
