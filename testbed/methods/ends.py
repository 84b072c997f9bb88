"""The bundled methods' encoder and decoder ends (compiled kernels: imported when a run starts).

Each is an ``EncoderEnd`` / ``DecoderEnd`` (``base``), built as ``End(method, model, K, qp, flow)``;
the paper's are in ``paper`` (re-exported here, where ``bundled`` finds every end).
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numba as nb
import numpy as np

from ..loop.params import DEFAULT_FLOW, FlowOptions, QuantizerParams
from ..loop.quantizer import box_center, control_input, floor_E, quantize_index, zoom_update
from .base import DecoderEnd, EncoderEnd, FloatCodebook, Method, Symbol
from .paper import PaperDecoder, PaperEncoder, ZoomRule

if TYPE_CHECKING:
    from plants.base import Plant


@nb.njit(cache=True)
def unaware_update(rhs: Any, p: np.ndarray, T: float, opts: np.ndarray, Kgain: np.ndarray, theta: int,
                   overflow: bool, xi: np.ndarray, E: float, q: np.ndarray, u_prev: np.ndarray, Lambda: float,
                   M: int, sigma: float, E_min: float, dpar: np.ndarray, K_s: np.ndarray, ytmp: np.ndarray,
                   u_s: np.ndarray, xi_out: np.ndarray) -> tuple[float, int]:
    """The zoom quantizer's update without DoS resilience: rule (xi) as the paper's, but the
    zoom-in E_{k+1} = (Lambda / M) E_k whatever theta_k (after an OVERFLOW received: the zoom-out
    E_{k+1} = sigma Lambda max(E_k, E_r)); the same floors as ``zoom_update``."""
    En, st = zoom_update(rhs, p, T, opts, Kgain, theta, overflow, xi, E, q, u_prev, Lambda, M, sigma,
                         E_min, dpar, K_s, ytmp, u_s, xi_out)
    if theta == 1:
        En = floor_E(Lambda / M * E, xi_out, E_min)
    return En, st


class ZoomEncoder(PaperEncoder):
    """The paper's encoder under ``unaware_update`` (always the resilient mode, no delay-aware rule)."""

    def __init__(self, method: Method, model: Plant, K: np.ndarray, qp: QuantizerParams,
                 flow: FlowOptions = DEFAULT_FLOW):
        super().__init__(method, model, K, replace(qp, mode="resilient", rule="paper"), flow)
        self.zoom = ZoomRule(unaware_update, self.plant, self.K, self.qp, self.flow, dpar=np.zeros(4))


class ZoomDecoder(PaperDecoder):
    """The paper's decoder under ``unaware_update``."""

    def __init__(self, method: Method, model: Plant, K: np.ndarray, qp: QuantizerParams,
                 flow: FlowOptions = DEFAULT_FLOW):
        super().__init__(method, model, K, replace(qp, mode="resilient", rule="paper"), flow)
        self.zoom = ZoomRule(unaware_update, self.plant, self.K, self.qp, self.flow, dpar=np.zeros(4))


class StaticEncoder(EncoderEnd):
    def symbol(self, x: np.ndarray) -> tuple[Symbol, bool, np.ndarray]:
        R, M = float(self.method.params["range"]), int(self.qp.M)
        zero = np.zeros(self.plant.n)
        i, sat = quantize_index(x, zero, R, M)
        q = np.empty(self.plant.n)
        box_center(i, zero, R, M, q)
        return int(i), bool(sat), q


class StaticDecoder(DecoderEnd):
    def control(self, symbol: Symbol) -> tuple[np.ndarray, np.ndarray]:
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

    def update(self, theta: int, symbol: Symbol) -> None:
        self.u_prev = self._u


class ExactEncoder(EncoderEnd):
    def symbol(self, x: np.ndarray) -> tuple[Symbol, bool, np.ndarray]:
        self._x = np.array(x, dtype=np.float64)
        return FloatCodebook.encode_state(x), False, self._x

    def update(self, theta: int, symbol: Symbol) -> None:
        if theta == 0:
            u = np.empty(self.plant.m)
            control_input(self.K, self._x, 0, False, u)
            self.u_prev = u


class ExactDecoder(DecoderEnd):
    hold = False

    def control(self, symbol: Symbol) -> tuple[np.ndarray, np.ndarray]:
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

    def update(self, theta: int, symbol: Symbol) -> None:
        if theta == 0 or self.hold:
            self.u_prev = self._u
        else:
            self.u_prev = np.zeros(self.plant.m)


class HoldDecoder(ExactDecoder):
    hold = True


class ExactEncoderZero(ExactEncoder):
    def update(self, theta: int, symbol: Symbol) -> None:
        if theta == 0:
            super().update(theta, symbol)
        else:
            self.u_prev = np.zeros(self.plant.m)
