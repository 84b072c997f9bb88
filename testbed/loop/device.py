"""A plant that is a device: the sensor, the actuator and a process disturbance around the true plant.

Scenario tables (docs/scenarios.md, "A plant that is a device"):

* ``[plant.sensor]``: x_meas,k = step * round((x_k + v_k) / step), v_k measurement noise
  (``distribution`` "normal": v ~ N(0, scale^2) per entry; "uniform": v ~ U[-scale, scale]),
  ``resolution`` = step the ADC's step (0: none).  The encoder (and a greedy attacker that scores by
  the state) sees x_meas,k; the true x_k is what the plant integrates and the recording keeps.
* ``[plant.actuator]``: what arrives, u_k, acts as the physics of the plant allows: the DAC's
  ``resolution`` (u = step * round(u / step)), ``saturation`` (|u| <= saturation) and ``rate``
  (|u_k - u_{k-1}| <= rate * T, u_{k-1} the input that acted before), in that order.  Distinct
  from ``[controller] u_max``, the controller's software safety clamp applied to u_k before it
  acts (counted as ``inputs_clamped``): the actuator's limits are not counted, they are the plant.
* ``[plant.disturbance]``: a process disturbance on the state at each sample,
  x_k+1 = phi_T(x_k, u_k) + w_k, w_k = ``constant`` + noise (``distribution``, ``scale``).

Randomness is exact and prefix-stable: each noise has its own ``numpy.random.Generator``
(PCG64) seeded by ``SeedSequence([seed, stream])`` (stream 1: sensor, 2: disturbance) and
draws n numbers at every sample k in order, so sample k's draw is the same in the per-sample
simulator, the live plant node and ``testbed resimulate``, whatever happens later in the run.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..common import validate
from .distributions import draw, names

DISTRIBUTIONS = names("normal")  # the noise's distributions (testbed.loop.distributions), its default first
SENSOR_STREAM = 1
DISTURBANCE_STREAM = 2

SENSOR_KEYS = {"distribution", "scale", "seed", "resolution"}
ACTUATOR_KEYS = {"resolution", "saturation", "rate"}
DISTURBANCE_KEYS = {"distribution", "scale", "seed", "constant"}
#: the sub-tables of [plant] this module reads
TABLES = ("sensor", "actuator", "disturbance")


@dataclass(frozen=True)
class SensorSpec:
    """``[plant.sensor]``: noise (normal: sigma = scale; uniform: half-width scale) then an ADC step."""

    distribution: str = "normal"
    scale: float = 0.0
    seed: int = 0
    resolution: float = 0.0

    def bound(self) -> float:
        """A bound on |x_meas - x| per entry: the uniform noise's scale, 4 sigma for normal noise
        (exceeded with probability 6.3e-5 per entry and sample), plus half the ADC step."""
        b = self.scale if self.distribution == "uniform" else 4.0 * self.scale
        return b + 0.5 * self.resolution


@dataclass(frozen=True)
class ActuatorSpec:
    """``[plant.actuator]``: DAC step, |u| saturation and rate limit [units of u per second]."""

    resolution: float = 0.0
    saturation: float = math.inf
    rate: float = math.inf


@dataclass(frozen=True)
class DisturbanceSpec:
    """``[plant.disturbance]``: w_k = constant + noise, added to x after each period."""

    constant: tuple[float, ...] = ()
    distribution: str = "normal"
    scale: float = 0.0
    seed: int = 0


@dataclass(frozen=True)
class DeviceSpec:
    """The device around the true plant (any of the three may be absent)."""

    sensor: SensorSpec | None = None
    actuator: ActuatorSpec | None = None
    disturbance: DisturbanceSpec | None = None

    def make(self, n: int, m: int, T: float) -> Device:
        return Device(self, n, m, T)

    def describe(self) -> str:
        """One line: what the device does (``testbed simulate`` says it when it picks the loop)."""
        parts = [name for name in TABLES if getattr(self, name) is not None]
        return "[plant." + "], [plant.".join(parts) + "]"


def _stream(seed: int, stream: int) -> np.random.Generator:
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), stream])))


def _grid(v: np.ndarray, step: float) -> np.ndarray:
    return step * np.round(v / step) if step > 0.0 else v


class Device:
    """The sensor, actuator and disturbance of one run: a small state machine, sample by sample.

    ``measure(k, x)`` must be called for k = 0, 1, ... in order (once each), ``actuate(u)`` once
    per period with the u that arrived (zeros when none did), ``disturbance()`` once per period.
    """

    def __init__(self, spec: DeviceSpec, n: int, m: int, T: float):
        self.spec, self.n, self.m, self.T = spec, n, m, float(T)
        s, d = spec.sensor, spec.disturbance
        self._sensor_rng = _stream(s.seed, SENSOR_STREAM) if s is not None and s.scale > 0 else None
        self._dist_rng = _stream(d.seed, DISTURBANCE_STREAM) if d is not None and d.scale > 0 else None
        self._next_k = 0
        self.u_prev = np.zeros(m)
        self.saturated = 0      # periods in which the actuator's saturation cut u
        self.rate_limited = 0   # ... in which its rate limit did

    @property
    def has_sensor(self) -> bool:
        return self.spec.sensor is not None

    def measure(self, k: int, x: np.ndarray) -> np.ndarray:
        """x_meas,k = step * round((x_k + v_k) / step) (``[plant.sensor]``); x_k itself without a sensor."""
        s = self.spec.sensor
        if s is None:
            return x
        if k != self._next_k:
            raise ValueError(f"sensor sample {k} measured out of order (expected {self._next_k})")
        self._next_k += 1
        y = np.array(x, dtype=np.float64)
        if self._sensor_rng is not None:
            y = y + draw(self._sensor_rng, s.distribution, s.scale, self.n)
        return _grid(y, s.resolution)

    def actuate(self, u: np.ndarray) -> np.ndarray:
        """The input that acts over the period (``[plant.actuator]``): DAC step, saturation, rate limit."""
        a = self.spec.actuator
        if a is None:
            return u
        v = _grid(np.asarray(u, dtype=np.float64), a.resolution)
        if math.isfinite(a.saturation):
            c = np.clip(v, -a.saturation, a.saturation)
            self.saturated += int(not np.array_equal(c, v))
            v = c
        if math.isfinite(a.rate):
            du = a.rate * self.T
            c = self.u_prev + np.clip(v - self.u_prev, -du, du)
            self.rate_limited += int(not np.array_equal(c, v))
            v = c
        self.u_prev = v
        return v

    def disturbance(self) -> np.ndarray | None:
        """w_k for this period (``[plant.disturbance]``), or None without one."""
        d = self.spec.disturbance
        if d is None:
            return None
        w = np.zeros(self.n) if not d.constant else np.array(d.constant, dtype=np.float64)
        if self._dist_rng is not None:
            w = w + draw(self._dist_rng, d.distribution, d.scale, self.n)
        return w

    def counters(self) -> dict:
        return {"actuator_saturated": self.saturated, "actuator_rate_limited": self.rate_limited}


def parse(pt: dict, n: int, m: int, err: Callable[[str, str], Exception], fmu: bool = False) -> DeviceSpec | None:
    """The ``[plant.sensor]``, ``[plant.actuator]`` and ``[plant.disturbance]`` tables of a [plant]
    table ``pt`` (None when it has none).  ``err(key, message)`` makes the scenario's error."""
    if not any(t in pt for t in TABLES):
        return None

    def table(name: str, allowed: frozenset[str] | set[str]) -> dict | None:
        t = pt.get(name)
        if t is None:
            return None
        if not isinstance(t, dict):
            raise err(f"plant.{name}", "must be a table")
        bad = sorted(set(t) - allowed)
        if bad:
            raise err(f"plant.{name}", f"unknown key(s) {bad}; allowed: {sorted(allowed)}")
        return t

    def checked(key: str, check: Callable[..., Any], v: object, *args: Any, **kw: Any) -> Any:
        try:
            return check(v, *args, **kw)
        except validate.Invalid as e:
            raise err(key, str(e)) from None

    def num(key: str, v: object, *, positive: bool = False, allow_inf: bool = False) -> float:
        return checked(key, validate.number, v, lo=0, lo_open=positive, allow_inf=allow_inf)

    def seed(key: str, v: object) -> int:
        return checked(key, validate.count, v, 0)

    def dist(key: str, v: object) -> str:
        return checked(key, validate.choice, v, DISTRIBUTIONS)

    sensor = actuator = disturbance = None
    st = table("sensor", SENSOR_KEYS)
    if st is not None:
        sensor = SensorSpec(distribution=dist("plant.sensor.distribution", st.get("distribution", "normal")),
                            scale=num("plant.sensor.scale", st.get("scale", 0.0)),
                            seed=seed("plant.sensor.seed", st.get("seed", 0)),
                            resolution=num("plant.sensor.resolution", st.get("resolution", 0.0)))
    at = table("actuator", ACTUATOR_KEYS)
    if at is not None:
        actuator = ActuatorSpec(resolution=num("plant.actuator.resolution", at.get("resolution", 0.0)),
                                saturation=num("plant.actuator.saturation", at.get("saturation", math.inf),
                                               positive=True, allow_inf=True),
                                rate=num("plant.actuator.rate", at.get("rate", math.inf), positive=True,
                                         allow_inf=True))
    dt = table("disturbance", DISTURBANCE_KEYS)
    if dt is not None:
        if fmu:
            raise err("plant.disturbance", "needs a plant given by its equations (name = ...): an FMU's state "
                                           "cannot be set between its steps")
        c = dt.get("constant", ())
        if not isinstance(c, (list, tuple)) or (c and len(c) != n):
            raise err("plant.disturbance.constant", f"must be a list of n = {n} numbers, got {c!r}")
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in c):
            raise err("plant.disturbance.constant", f"must be a list of n = {n} finite numbers, got {c!r}")
        constant = tuple(float(v) for v in c)
        disturbance = DisturbanceSpec(constant=constant,
                                      distribution=dist("plant.disturbance.distribution",
                                                        dt.get("distribution", "normal")),
                                      scale=num("plant.disturbance.scale", dt.get("scale", 0.0)),
                                      seed=seed("plant.disturbance.seed", dt.get("seed", 0)))
    return DeviceSpec(sensor=sensor, actuator=actuator, disturbance=disturbance)


__all__ = ["Device", "DeviceSpec", "SensorSpec", "ActuatorSpec", "DisturbanceSpec", "parse", "TABLES"]
