"""The paper's method, written against the end API (``EncoderEnd``, ``DecoderEnd``): a worked example.

Both ends start from xi_0 = 0 and E_0 = E0.  The encoder sends the index of the box of
Q(xi_k, E_k) that holds x_k (Algorithm 1, ``PaperEncoder.symbol``); the decoder turns it into the
box's centre q_k and applies u_k = (1 - theta_k) K q_k (Algorithm 2 and control law (2),
``PaperDecoder.control``).  After sample k both apply, from what both know (theta_k and, when
theta_k = 0, the symbol), the update rules (xi) and (E) (``update``):

    xi_{k+1} = phi_T(q_k, K q_k),  E_{k+1} = (Lambda / M) E_k     if theta_k = 0
    xi_{k+1} = phi_T(xi_k, 0),     E_{k+1} = Lambda E_k           if theta_k = 1

floored as ``End.floor_E`` says, and u_{k-1} kept in ``u_prev``.  The resilient mode (the
testbed's) adds the OVERFLOW codeword: a state outside the box is sent as the spare code M^n,
u_k = 0, and both ends zoom out, E_{k+1} = sigma Lambda max(E_k, E_r) (``testbed.loop.quantizer``).

The rules are one compiled function, ``quantizer.zoom_update``, which the batch kernel runs too
(so that the two simulators agree bit for bit).  It calls the flow map ``End.phi_T`` calls, sums
u = K q as ``End.feedback`` does and floors E as ``End.floor_E`` does, so a method written in
Python with those three and configured like this one computes the same numbers
(``PredictiveZoom`` of docs/examples/mymethod.py, tests/core/test_methods.py).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from ..loop.flow import compiled_for
from ..loop.params import FlowOptions, QuantizerParams
from ..loop.quantizer import box_center, control_input, quantize_index, zoom_update
from .base import DecoderEnd, EncoderEnd, Symbol

if TYPE_CHECKING:
    from plants.base import Plant


class ZoomRule:
    """Rules (xi), (E) and the OVERFLOW zoom-out as both ends apply them: ``rule``, a compiled
    function with ``quantizer.zoom_update``'s arguments, over the model, K and ``[quantizer]`` of
    an end.  ``dpar``: the delay-aware rule's parameters (default ``qp.dpar``)."""

    def __init__(self, rule: Callable[..., tuple[float, int]], model: Plant, K: np.ndarray, qp: QuantizerParams,
                 flow: FlowOptions, dpar: np.ndarray | None = None):
        self.rule = rule
        self.model, self.K, self.qp = model, K, qp
        self._rhs = type(model).rhs.cfunc
        self._p = model.p
        self._opts = flow.as_array()
        self._Ks = np.empty((13, model.n))
        self._ytmp = np.empty(model.n)
        self._dpar = qp.dpar if dpar is None else np.asarray(dpar, dtype=np.float64)
        self._call: Callable[..., tuple[float, int]] | None = None

    def __call__(self, theta: int, overflow: bool, q: np.ndarray, xi: np.ndarray, E: float,
                 u_prev: np.ndarray) -> tuple[np.ndarray, float, np.ndarray, int]:
        """(xi_{k+1}, E_{k+1}, u_k, the flow map's status) after sample k."""
        xi_next = np.empty(self.model.n)
        u_k = np.empty(self.model.m)
        qp = self.qp
        args = (self._rhs, self._p, qp.T, self._opts, self.K, int(theta), bool(overflow), xi, float(E), q,
                u_prev, qp.Lambda, qp.M, qp.sigma, qp.E_min, self._dpar, self._Ks, self._ytmp, u_k, xi_next)
        if self._call is None:
            E_next, st = self.rule(*args)
            self._call = compiled_for(self.rule, args)  # once per sample on a live node: no type dispatch
        else:
            E_next, st = self._call(*args)
        return xi_next, float(E_next), u_k, int(st)


class PaperEncoder(EncoderEnd):
    """Algorithm 1: ``symbol(x_k)`` is the index of the box of Q(xi_k, E_k) that holds x_k (the
    nearest box when x_k is outside: a saturation, sent as OVERFLOW in the resilient mode);
    ``update`` applies (xi), (E) once the ack brings theta_k."""

    def __init__(self, *a: Any, **kw: Any):
        super().__init__(*a, **kw)
        self.E = float(self.qp.E0)  # xi_0 = 0, E_0 = E0
        self.zoom = ZoomRule(zoom_update, self.plant, self.K, self.qp, self.flow)

    def symbol(self, x: np.ndarray) -> tuple[Symbol, bool, np.ndarray]:
        i, sat = quantize_index(x, self.xi, self.E, self.qp.M)
        q = np.empty(self.plant.n)
        box_center(i, self.xi, self.E, self.qp.M, q)
        if sat and self.codebook.resilient:
            i = self.codebook.overflow
        return int(i), bool(sat), q

    def update(self, theta: int, symbol: Symbol) -> None:
        overflow = symbol == self.codebook.overflow
        self.xi, self.E, self.u_prev, self.flow_status = self.zoom(theta, overflow, self.q, self.xi, self.E,
                                                                   self.u_prev)


class PaperDecoder(DecoderEnd):
    """Algorithm 2 and control law (2): ``control(symbol)`` is q_k, the centre of the box the
    symbol names, and u_k = K q_k (u_k = 0 and q_k = 0 for a loss or an OVERFLOW); ``update``
    applies (xi), (E)."""

    def __init__(self, *a: Any, **kw: Any):
        super().__init__(*a, **kw)
        self.E = float(self.qp.E0)  # xi_0 = 0, E_0 = E0
        self.zoom = ZoomRule(zoom_update, self.plant, self.K, self.qp, self.flow)
        self._q = np.zeros(self.plant.n)
        self._overflow = False

    def control(self, symbol: Symbol) -> tuple[np.ndarray, np.ndarray]:
        n = self.plant.n
        theta = 1 if symbol is None else 0
        overflow = theta == 0 and int(symbol) == self.codebook.overflow
        if overflow:
            self.overflows += 1
        q = np.zeros(n)
        if theta == 0 and not overflow:
            box_center(int(symbol), self.xi, self.E, self.qp.M, q)
        u = np.empty(self.plant.m)
        control_input(self.K, q, theta, overflow, u)
        self._q, self._overflow = q, overflow
        return u, q

    def update(self, theta: int, symbol: Symbol) -> None:
        self.xi, self.E, self.u_prev, self.flow_status = self.zoom(theta, self._overflow, self._q, self.xi, self.E,
                                                                   self.u_prev)

