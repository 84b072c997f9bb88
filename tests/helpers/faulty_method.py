"""A user method that faults on purpose, for the verdict tests (simulated and live): its decoder raises at
sample RAISE_AT, or its encoder's E drifts so that the two ends leave lockstep."""

#: a method whose ends raise (decoder at sample RAISE_AT) or break lockstep (the encoder's E drifts)
FAULTY = '''
import numpy as np
from testbed.methods import DecoderEnd, EncoderEnd, IntCodebook, Method

RAISE_AT = {raise_at}
DRIFT = {drift}


class Enc(EncoderEnd):
    def symbol(self, x):
        return 0, False, np.zeros(self.plant.n)

    def update(self, theta, symbol):
        self.E += DRIFT


class Dec(DecoderEnd):
    def control(self, symbol):
        if self.k == RAISE_AT:
            raise ZeroDivisionError("boom")
        return np.zeros(self.plant.m), np.zeros(self.plant.n)


class Faulty(Method):
    encoder_class, decoder_class = Enc, Dec

    def codebook(self, n, qp):
        return IntCodebook(2)
'''
