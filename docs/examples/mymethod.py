"""mymethod.py: coding-and-control methods of your own (docs/methods.md, "Bring your own method").

``CenteredZoom``: a zoom quantizer centred at the origin.  The box [-E_k, E_k]^n is split into M
levels per coordinate, the decoder applies u_k = K q_k, and both ends update the range from
theta_k alone,

    E_{k+1} = a E_k        if theta_k = 0 (zoom in),
    E_{k+1} = Lambda E_k   if theta_k = 1 (zoom out by the growth bound Lambda = e^{L T}),

so that encoder and decoder stay in lockstep (the testbed checks it).  Through a loss the decoder
applies u_k = 0.  It reads ``[quantizer] M, L, E0`` (so the paper's method runs on the same
scenario: ``testbed versus``) and one parameter of its own, ``a`` (``[method] params``, default 0.96).

``PredictiveZoom``: the box follows the state.  Its centre xi_k is both ends' prediction of x_k
by the model's flow map ``phi_T`` (an end's ``self.phi_T``), from the input u_k both know was
applied,

    xi_{k+1} = phi_T(q_k, u_k),  E_{k+1} = (Lambda / M) E_k     if theta_k = 0, u_k = K q_k
    xi_{k+1} = phi_T(xi_k, u_k), E_{k+1} = Lambda E_k           if theta_k = 1,

and E_{k+1} floored as the paper's ends floor it (``self.floor_E``).  Through a loss it applies
u_k = 0 (``hold = false``, the default: then this is the paper's method in its ideal mode, and
equals ``paper`` bit for bit where nothing saturates) or holds u_{k-1} (``hold = true``).  It reads
``[quantizer] M, L, E0, E_min``.
"""

import math

import numpy as np

from testbed.methods import DecoderEnd, EncoderEnd, IntCodebook, Method


def _cell(x, E, M):
    """Per-coordinate cell index in 0..M-1 of x in [-E, E] (clipped), and whether x was outside."""
    s = np.floor((np.asarray(x) + E) / (2.0 * E) * M)
    sat = bool(np.any(np.abs(x) > E))
    return np.clip(s, 0, M - 1).astype(int), sat


def _code(c, M):
    """The symbol of cell indices c: sum_j c_j M^j."""
    return int(sum(int(cj) * M**j for j, cj in enumerate(c)))


def _cells(symbol, n, M):
    """The cell indices of a symbol (the inverse of ``_code``)."""
    return np.array([(int(symbol) // M**j) % M for j in range(n)], dtype=float)


class CenteredEncoder(EncoderEnd):
    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.E = float(self.qp.E0)

    def symbol(self, x):
        M = int(self.qp.M)
        c, sat = _cell(x, self.E, M)
        code = _code(c, M)
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
        c = _cells(symbol, n, M)
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


# ----------------------------------------------------------------------------- the box follows the state
def _predict(end, theta, q, u):
    """Both ends' update after sample k, from what both know (theta_k, q_k, the applied u_k)."""
    qp = end.qp
    if theta == 0:
        end.xi, E = end.phi_T(q, u), qp.Lambda / qp.M * end.E
    else:
        end.xi, E = end.phi_T(end.xi, u), qp.Lambda * end.E
    end.E = end.floor_E(E, end.xi)
    end.u_prev = u


def _loss_input(end):
    """u_k through a loss: u_{k-1} (hold) or 0."""
    return end.u_prev.copy() if end.method.params["hold"] else np.zeros(end.plant.m)


class PredictiveEncoder(EncoderEnd):
    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.E = float(self.qp.E0)          # xi_0 = 0 (the default of every end)

    def symbol(self, x):
        M = int(self.qp.M)
        c, sat = _cell(x - self.xi, self.E, M)
        q = self.xi - self.E + (2.0 * c + 1.0) * self.E / M
        return _code(c, M), sat, q

    def update(self, theta, symbol):
        u = self.feedback(self.q) if theta == 0 else _loss_input(self)   # self.q: q_k of this sample
        _predict(self, theta, self.q, u)


class PredictiveDecoder(DecoderEnd):
    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.E = float(self.qp.E0)

    def control(self, symbol):
        n, M = self.plant.n, int(self.qp.M)
        if symbol is None:
            q, u = np.zeros(n), _loss_input(self)
        else:
            q = self.xi - self.E + (2.0 * _cells(symbol, n, M) + 1.0) * self.E / M
            u = self.feedback(q)            # K q, summed as the paper's ends sum it
        self._q, self._u = q, u
        return u, q

    def update(self, theta, symbol):
        _predict(self, theta, self._q, self._u)


class PredictiveZoom(Method):
    name = "predictive-zoom"
    description = "zoom quantizer centred at the prediction phi_T: the paper's rules, u = 0 or u_{k-1} through a loss"
    source = "docs/examples/mymethod.py (a worked example)"
    uses = ("M", "L", "E0", "E_min")
    defaults = {"hold": False}
    encoder_class = PredictiveEncoder
    decoder_class = PredictiveDecoder

    def codebook(self, n, qp):
        return IntCodebook(max(1, math.ceil(n * math.log2(int(qp.M)))))
