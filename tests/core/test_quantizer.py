"""Algorithms 1 and 2, update rules (xi) and (E), codebook and the saturation protocol."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import plants
from testbed.loop.flow import phi_T
from testbed.loop.quantizer import Codebook, InvalidSymbol, QuantizerParams, box_center, quantize_index
from testbed.methods.bundled import PaperMethod
from testbed.sim.loop import OnlineAttacker, simulate_loop

LIENARD = plants.make("lienard")
K_PAPER = np.array([[-1.81, -1.90]])
PAPER = PaperMethod()  # the paper's ends: PAPER.make_encoder(model, K, qp), PAPER.make_decoder(...)


@settings(max_examples=300, deadline=None)
@given(n=st.integers(1, 4), M=st.integers(2, 9), E=st.floats(1e-6, 1e3),
       seed=st.integers(0, 2**31 - 1))
def test_quantization_error_at_most_E_over_M(n, M, E, seed):
    """(4): x in Q(xi, E) implies ||x - q||_inf <= E / M, and q is a box centre inside Q."""
    rng = np.random.default_rng(seed)
    xi = rng.uniform(-10, 10, n)
    x = xi + rng.uniform(-E, E, n)
    i, sat = quantize_index(x, xi, E, M)
    assert not sat
    assert 0 <= i < M**n
    q = np.empty(n)
    box_center(i, xi, E, M, q)
    ulp = 4 * np.spacing(np.max(np.abs(xi)) + E)  # round-off of the box arithmetic
    assert np.max(np.abs(x - q)) <= E / M + ulp
    assert np.max(np.abs(q - xi)) <= E * (1 - 1 / M) + ulp


def test_boundary_and_saturation_flags():
    xi = np.zeros(2)
    i, sat = quantize_index(np.array([1.0, -1.0]), xi, 1.0, 6)  # corners belong to Q (closed box)
    assert not sat and i == 5 + 0 * 6
    i, sat = quantize_index(np.array([1.0 + 1e-9, 0.0]), xi, 1.0, 6)
    assert sat and i % 6 == 5  # clipped to the nearest box
    _, sat = quantize_index(np.array([np.nan, 0.0]), xi, 1.0, 6)
    assert sat


@pytest.mark.parametrize("n,M,resilient,bits", [(2, 6, False, 6), (2, 6, True, 6), (2, 4, False, 4),
                                                (2, 4, True, 5), (4, 6, False, 11), (1, 2, False, 1),
                                                (3, 10, True, 10)])
def test_bits_are_ceil_n_log2_M(n, M, resilient, bits):
    cb = Codebook(n, M, resilient)
    assert cb.bits == bits
    if not resilient:
        assert cb.bits == math.ceil(n * math.log2(M))


@pytest.mark.parametrize("n,M,resilient", [(2, 6, True), (2, 6, False), (4, 6, True), (2, 4, True), (1, 2, False)])
def test_packing_round_trips_every_code_and_rejects_invalid(n, M, resilient):
    cb = Codebook(n, M, resilient)
    for i in range(cb.n_codes):
        b = cb.pack(i)
        assert len(b) == cb.nbytes
        assert cb.unpack(b) == i
    if (2 ** (8 * cb.nbytes)) > cb.n_codes:
        with pytest.raises(InvalidSymbol, match="outside the codebook"):
            cb.unpack(cb.n_codes.to_bytes(cb.nbytes, "big"))
    with pytest.raises(InvalidSymbol, match="bytes, expected"):
        cb.unpack(b"\x00" * (cb.nbytes + 1))
    with pytest.raises(InvalidSymbol, match="bytes, expected"):
        cb.unpack(b"")
    with pytest.raises(InvalidSymbol):
        cb.pack(cb.n_codes)
    with pytest.raises(InvalidSymbol):
        cb.unpack("a string")


def test_paper_payload_is_one_byte():
    assert Codebook(2, 6, True).nbytes == 1


def _qp(mode="resilient", E0=0.1, **kw):
    return QuantizerParams(T=0.1, M=6, L=10.0, E0=E0, mode=mode, **kw)


@settings(max_examples=40, deadline=None)
@given(theta=st.lists(st.integers(0, 1), min_size=1, max_size=60),
       x0=st.tuples(st.floats(-0.1, 0.1), st.floats(-0.1, 0.1)),
       mode=st.sampled_from(["ideal", "resilient"]))
def test_encoder_decoder_lockstep_under_any_schedule(theta, x0, mode):
    """Encoder and decoder xi_k, E_k identical (bit for bit) at every sample, whatever the attacks."""
    r = simulate_loop(LIENARD, K_PAPER, _qp(mode), np.array(x0), len(theta),
                      OnlineAttacker(theta=np.array(theta), T=0.1))
    assert np.array_equal(r.xi_enc, r.xi_dec)
    assert np.array_equal(r.E_enc, r.E_dec)
    assert np.array_equal(r.theta, np.array(theta[: len(r.theta)], dtype=np.uint8))


@settings(max_examples=30, deadline=None)
@given(theta=st.lists(st.integers(0, 1), min_size=1, max_size=80))
def test_E_sequence_is_the_closed_form_product(theta):
    """(E): E_k = E0 prod_{j<k} (Lambda/M)^{1-theta_j} Lambda^{theta_j} (no saturation, no floor)."""
    qp = _qp("ideal", E0=0.1)
    r = simulate_loop(LIENARD, K_PAPER, qp, np.array([0.05, -0.05]), len(theta),
                      OnlineAttacker(theta=np.array(theta), T=0.1))
    th = np.array(theta[: len(r.E_enc)])
    logE = np.log(0.1) + np.concatenate([[0.0], np.cumsum(np.where(th[:-1] == 1, np.log(qp.Lambda),
                                                                    np.log(qp.Lambda / 6)))])
    np.testing.assert_allclose(np.log(r.E_enc), logE, rtol=1e-12, atol=1e-9)


def test_ideal_quantizer_keeps_the_state_in_the_box_for_the_paper(paper):
    """In the ideal mode the state stays in Q(xi_k, E_k) for the paper scenario."""
    import dataclasses

    qp = dataclasses.replace(paper.quantizer, mode="ideal")
    r = simulate_loop(paper.make_plant(), paper.K, qp, paper.x0, paper.n_steps,
                      OnlineAttacker(theta=paper.theta(), T=paper.T))
    assert r.saturations == 0
    ulp = 4 * np.spacing(np.max(np.abs(r.x), axis=1))
    assert np.all(np.max(np.abs(r.x - r.xi_enc), axis=1) <= r.E_enc + ulp)
    assert np.all(np.max(np.abs(r.x - r.q_enc), axis=1) <= r.E_enc / 6 + ulp)
    assert r.final_norm < 1e-4


def test_invalid_symbol_is_a_counted_loss_and_keeps_lockstep():
    qp = _qp()
    enc = PAPER.make_encoder(LIENARD, K_PAPER, qp)
    dec = PAPER.make_decoder(LIENARD, K_PAPER, qp)
    x = np.array([0.05, 0.02])
    for k in range(20):
        sym, _ = enc.encode(x)
        sent = 999 if k in (3, 4, 11) else sym
        u, q, th = dec.step(sent)
        assert th == (1 if k in (3, 4, 11) else 0)
        enc.ack(th)
        assert np.array_equal(enc.xi, dec.xi) and enc.E == dec.E
        x, _ = phi_T(LIENARD, x, u, 0.1)
    assert dec.invalid == 3


def _run_with_kick(mode, kick_at=15, kick=np.array([0.2, -0.2]), N=300, **kw):  # noqa: B008 - never written
    """A loop whose plant is kicked once: model mismatch puts x_k outside Q(xi_k, E_k)."""
    qp = _qp(mode, **kw)
    enc = PAPER.make_encoder(LIENARD, K_PAPER, qp)
    dec = PAPER.make_decoder(LIENARD, K_PAPER, qp)
    x = np.array([0.05, 0.05])
    sats, overflow_seen, inside = 0, 0, []
    for k in range(N):
        if k == kick_at:
            x = x + kick
        sym, sat = enc.encode(x)
        sats += sat
        overflow_seen += sym == enc.codebook.overflow
        u, q, th = dec.step(sym)
        enc.ack(th)
        assert np.array_equal(enc.xi, dec.xi) and enc.E == dec.E
        inside.append(np.max(np.abs(x - enc.xi)) <= enc.E)
        x, _ = phi_T(LIENARD, x, u, 0.1)
    return x, sats, overflow_seen, dec


def test_resilient_protocol_recovers_from_saturation():
    x, sats, overflows, dec = _run_with_kick("resilient")
    assert sats >= 1 and overflows == sats == dec.overflows
    assert np.max(np.abs(x)) < 1e-4  # re-captured and converged


def test_ideal_quantizer_loses_track_after_the_same_kick():
    x, sats, overflows, _ = _run_with_kick("ideal")
    assert overflows == 0
    assert sats > 20  # the paper's quantizer keeps zooming in on the wrong place


def test_E_floor():
    x, sats, _, dec = _run_with_kick("resilient", kick_at=-1, E_min=1e-6)
    assert dec.E >= 1e-6


def test_overflow_recovers_even_after_E_underflowed_to_zero():
    """A long run at small T can underflow E to 0; OVERFLOW must still zoom out (both ends alike)."""
    qp = _qp()
    enc = PAPER.make_encoder(LIENARD, K_PAPER, qp)
    dec = PAPER.make_decoder(LIENARD, K_PAPER, qp)
    enc.E = dec.E = 0.0
    x = np.array([0.01, -0.01])
    for _k in range(300):
        sym, _ = enc.encode(x)
        u, q, th = dec.step(sym)
        enc.ack(th)
        assert np.array_equal(enc.xi, dec.xi) and enc.E == dec.E
        x, _ = phi_T(LIENARD, x, u, 0.1)
    assert dec.overflows >= 1
    assert np.max(np.abs(x)) < 1e-4
