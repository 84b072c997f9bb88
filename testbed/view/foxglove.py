"""Foxglove-native topics of a recording (and of ``testbed run --foxglove``): the Log and 3D panels.

=================  ========================  ==================================================
topic              schema                    content
=================  ========================  ==================================================
``/log``           ``foxglove.Log``          the run's start and end, attacks starting and
                                             ending, saturations, faults, every node event
``/phase``         ``foxglove.SceneUpdate``  one a sample: the phase plane at t_k (the
                                             trajectory so far, x_k, xi_k, the box Q(xi_k, E_k))
``/phase/roa``     ``foxglove.SceneUpdate``  once: the nominal region of attraction's outline
                                             (n = 2, T >= 10 ms)
=================  ========================  ==================================================

The schemas are Foxglove's own, as published by ``foxglove-sdk``
(``foxglove.messages.Log.get_schema()``) and shipped in
``testbed/view/foxglove_schemas/`` (``tools/gen_foxglove_schemas.py``), so a
recording needs no foxglove-sdk to carry them.  Log messages are built with the
protobuf classes of that descriptor set; the per-sample SceneUpdate is encoded
directly in the protobuf wire format with the field numbers read from the same
descriptor set (a few microseconds a sample instead of hundreds), and tests
decode it with protobuf and with Foxglove's JavaScript stack.

The phase plane uses one fixed frame, ``phase``, with x1 to the right and x2 up
(components ``PHASE_DIMS`` of x; a projection for n > 2).  Lines are
``scale_invariant`` (a width in pixels), so the box stays visible as E_k
shrinks by tens of decades.  The trajectory so far is kept at the resolution
of the view: a point is kept when it is more than 1/400 of the window from the
last one kept (at most ``MAX_POINTS``, coarser beyond), and the samples since
(the last ``TAIL`` of them) follow in full, so x_k is always the strip's end.
At T >= ``REFRESH_S`` every update carries that whole trajectory (entity
``trajectory``).  At faster rates it is sent every ``REFRESH_S`` of the run and
the updates between carry only entity ``recent``, the strip from its end to
x_k, so a 1 kHz run writes about a kilobyte a sample instead of ten; after a
seek, Foxglove shows the whole trajectory again from the next such update.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from functools import cache
from importlib import resources
from typing import TYPE_CHECKING, Any

from ..common.protobuf import varint as _varint
from ..wire import messages as msg
from .phase import PHASE_DIMS, RoaOutline, phase_bounds, roa_outline

if TYPE_CHECKING:
    import numpy as np

    from ..scenario import Scenario

TOPIC_LOG = "/log"
TOPIC_PHASE = "/phase"
TOPIC_ROA = "/phase/roa"
LOG = "foxglove.Log"
SCENE = "foxglove.SceneUpdate"
TOPICS = {TOPIC_LOG: LOG, TOPIC_PHASE: SCENE, TOPIC_ROA: SCENE}
FRAME = "phase"
MAX_POINTS = 512
TAIL = 16
ROA_MIN_T = 0.01   # the nominal region's outline is drawn at T >= 10 ms (its grid costs ~1/T)
REFRESH_S = 0.05   # at T < 50 ms the whole trajectory is sent every 50 ms of the run, only what is new between

# Log levels (foxglove.Log.Level)
DEBUG, INFO, WARNING, ERROR, FATAL = 1, 2, 3, 4, 5
_LEVEL_OF_KIND = {"saturation": WARNING, "peer_lost": ERROR, "killed": ERROR, "malformed": WARNING,
                  "crashed": ERROR}


@cache
def descriptor_set(name: str) -> bytes:
    """The serialized ``FileDescriptorSet`` of a Foxglove schema (``foxglove.Log``, ``foxglove.SceneUpdate``)."""
    return resources.files(__package__).joinpath("foxglove_schemas", f"{name}.fds").read_bytes()


@cache
def _numbers() -> dict[str, dict[str, int]]:
    """message full name -> field name -> field number, from the shipped descriptor sets."""
    from google.protobuf import descriptor_pb2

    out: dict[str, dict[str, int]] = {}
    for name in (LOG, SCENE):
        fds = descriptor_pb2.FileDescriptorSet.FromString(descriptor_set(name))
        for f in fds.file:
            for m in f.message_type:
                out[f"{f.package}.{m.name}"] = {fld.name: fld.number for fld in m.field}
    return out


@cache
def _log_class():
    from ..common.protobuf import classes_from

    return classes_from(descriptor_set(LOG))[LOG]


# ============================================================================ wire-format pieces
class _Enc:
    """Encoders of the few Foxglove messages the phase plane needs (field numbers from the descriptor)."""

    def __init__(self):
        N = _numbers()
        self.n = N
        self._d = struct.Struct("<d").pack
        self._keys: dict[tuple[str, str, int], bytes] = {}

    def key(self, msgname: str, field: str, wt: int) -> bytes:
        k = self._keys.get((msgname, field, wt))
        if k is None:  # a few dozen distinct keys, each encoded once
            k = self._keys[(msgname, field, wt)] = _varint((self.n[msgname][field] << 3) | wt)
        return k

    def dbl(self, msgname: str, field: str, v: float) -> bytes:
        return self.key(msgname, field, 1) + self._d(float(v))

    def sub(self, msgname: str, field: str, payload: bytes) -> bytes:
        return self.key(msgname, field, 2) + _varint(len(payload)) + payload

    def var(self, msgname: str, field: str, v: int) -> bytes:
        return self.key(msgname, field, 0) + _varint(int(v))

    def string(self, msgname: str, field: str, s: str) -> bytes:
        return self.sub(msgname, field, s.encode())

    # ---- messages
    def point(self, x: float, y: float) -> bytes:
        return self.dbl("foxglove.Point3", "x", x) + self.dbl("foxglove.Point3", "y", y)

    def color(self, rgba) -> bytes:
        r, g, b, a = rgba
        C = "foxglove.Color"
        return self.dbl(C, "r", r) + self.dbl(C, "g", g) + self.dbl(C, "b", b) + self.dbl(C, "a", a)

    def pose(self, x: float, y: float) -> bytes:
        V, Q, P = "foxglove.Vector3", "foxglove.Quaternion", "foxglove.Pose"
        return self.sub(P, "position", self.dbl(V, "x", x) + self.dbl(V, "y", y)) + \
            self.sub(P, "orientation", self.dbl(Q, "w", 1.0))

    def line(self, points_bytes: bytes, *, loop: bool, width_px: float, rgba) -> bytes:
        L = "foxglove.LinePrimitive"
        return (self.var(L, "type", 1 if loop else 0) + self.sub(L, "pose", self.pose(0.0, 0.0))
                + self.dbl(L, "thickness", width_px) + self.var(L, "scale_invariant", 1)
                + points_bytes + self.sub(L, "color", self.color(rgba)))

    def points(self, xy) -> bytes:
        k = self.key("foxglove.LinePrimitive", "points", 2)
        out = []
        for x, y in xy:
            p = self.point(x, y)
            out.append(k + _varint(len(p)) + p)
        return b"".join(out)

    def sphere(self, x: float, y: float, size: float, rgba) -> bytes:
        S, V = "foxglove.SpherePrimitive", "foxglove.Vector3"
        return (self.sub(S, "pose", self.pose(x, y))
                + self.sub(S, "size", self.dbl(V, "x", size) + self.dbl(V, "y", size) + self.dbl(V, "z", size))
                + self.sub(S, "color", self.color(rgba)))

    def stamp(self, msgname: str, field: str, t_ns: int) -> bytes:
        T = "google.protobuf.Timestamp"
        sec, ns = divmod(int(t_ns), 1_000_000_000)
        return self.sub(msgname, field, self.var(T, "seconds", sec) + self.var(T, "nanos", ns))

    def entity(self, eid: str, t_ns: int, *, lines=(), spheres=()) -> bytes:
        E = "foxglove.SceneEntity"
        out = [self.stamp(E, "timestamp", t_ns), self.string(E, "frame_id", FRAME), self.string(E, "id", eid)]
        out += [self.sub(E, "lines", ln) for ln in lines]
        out += [self.sub(E, "spheres", sp) for sp in spheres]
        return b"".join(out)

    def update(self, entities) -> bytes:
        return b"".join(self.sub("foxglove.SceneUpdate", "entities", e) for e in entities)


# ============================================================================ the phase plane
C_TRAJ = (0.25, 0.25, 0.25, 1.0)
C_X = (0.0, 0.0, 0.0, 1.0)
C_BOX = (1.0, 0.65, 0.0, 1.0)
C_ROA = (0.5, 0.5, 0.5, 1.0)


class PhaseScene:
    """The per-sample ``foxglove.SceneUpdate`` of the phase plane (state kept between samples)."""

    def __init__(self, window: float, dims=PHASE_DIMS, refresh: int = 1):
        self.enc = _Enc()
        self.dims = dims
        self.window = float(window) if window and math.isfinite(window) and window > 0 else 1.0
        self.eps = self.window / 400.0
        self.kept: list[tuple[float, float]] = []
        self.kept_bytes: list[bytes] = []
        self.tail: list[tuple[float, float]] = []
        self.size = 0.012 * self.window
        self.refresh = max(1, int(refresh))
        self.i = 0
        self.recent: list[tuple[float, float]] = []   # the samples since the last "trajectory" entity

    def _xy(self, v) -> tuple[float, float] | None:
        a, b = self.dims
        v = tuple(v)
        if not v:
            return None
        x = float(v[a])
        y = float(v[b]) if b < len(v) else 0.0
        return (x, y) if math.isfinite(x) and math.isfinite(y) else None

    def _keep(self, p) -> bool:
        if self.kept:
            q = self.kept[-1]
            if max(abs(p[0] - q[0]), abs(p[1] - q[1])) <= self.eps:
                return False
        self.kept.append(p)
        self.kept_bytes.append(self.enc.points([p]))
        if len(self.kept) > MAX_POINTS:   # coarser: every other point, twice the distance
            self.eps *= 2.0
            self.kept = self.kept[::2] + ([self.kept[-1]] if len(self.kept) % 2 == 0 else [])
            self.kept_bytes = [self.enc.points([q]) for q in self.kept]
        return True

    def sample(self, t_ns: int, x: Sequence[float] | np.ndarray, xi: Sequence[float] | np.ndarray | None = None,
               E: float | None = None) -> bytes:
        """The SceneUpdate at t_k (absolute ns): x_k, and xi_k with the box Q(xi_k, E_k) when known."""
        enc = self.enc
        p = self._xy(x)
        if p is not None:  # the tail: the samples since the last point kept (the last TAIL of them)
            self.tail = [] if self._keep(p) else (self.tail + [p])[-TAIL:]
        ents = []
        if self.i % self.refresh == 0:   # the whole trajectory so far (decimated); "recent" starts again
            traj = b"".join(self.kept_bytes) + enc.points(self.tail)
            ents.append(enc.entity("trajectory", t_ns, lines=[enc.line(traj, loop=False, width_px=2.0,
                                                                       rgba=C_TRAJ)]))
            self.recent = [p] if p is not None else self.recent[-1:]
            ents.append(enc.entity("recent", t_ns))
        else:                            # what is new since: a strip from the trajectory's end to x_k
            if p is not None:
                self.recent.append(p)
            ents.append(enc.entity("recent", t_ns, lines=[enc.line(enc.points(self.recent), loop=False,
                                                                   width_px=2.0, rgba=C_TRAJ)]))
        self.i += 1
        spheres, lines = [], []
        if p is not None:
            spheres.append(enc.sphere(p[0], p[1], self.size, C_X))
        c = self._xy(xi) if xi is not None else None
        if c is not None and E is not None and math.isfinite(E) and E >= 0:
            spheres.append(enc.sphere(c[0], c[1], 0.7 * self.size, C_BOX))
            box = [(c[0] - E, c[1] - E), (c[0] + E, c[1] - E), (c[0] + E, c[1] + E), (c[0] - E, c[1] + E)]
            lines.append(enc.line(enc.points(box), loop=True, width_px=2.0, rgba=C_BOX))
        ents.append(enc.entity("state", t_ns, lines=lines, spheres=spheres))
        return enc.update(ents)


def roa_update(outline: RoaOutline | None, t_ns: int) -> bytes | None:
    """The SceneUpdate of the nominal region of attraction's outline (``view.phase.roa_outline``), or None."""
    if outline is None or not outline.lines:
        return None
    enc = _Enc()
    lines = [enc.line(enc.points([(float(a), float(b)) for a, b in ln]), loop=False, width_px=1.5, rgba=C_ROA)
             for ln in outline.lines]
    return enc.update([enc.entity("roa", t_ns, lines=lines)])


def window_of(sc: Scenario, roa: RoaOutline | None = None) -> float:
    """The phase plane's width (``view.phase.phase_bounds`` of the live view)."""
    (x0, x1), _ = phase_bounds(sc, None, roa)
    return x1 - x0


# ============================================================================ the Log panel
def log_message(t_ns: int, level: int, text: str, name: str) -> bytes:
    """A ``foxglove.Log`` (t_ns absolute)."""
    m = _log_class()()
    sec, ns = divmod(int(t_ns), 1_000_000_000)
    m.timestamp.seconds, m.timestamp.nanos = sec, ns
    m.level = level
    m.message = text
    m.name = name
    return m.SerializeToString()


# ============================================================================ one tap for recorder and live server
class FoxgloveTopics:
    """Turns a run's messages into the Foxglove topics: ``(topic, schema, bytes, log_time)`` items.

    Fed the same messages by the recorder (``testbed.nodes.recorder``), by
    ``record_simulation`` and by the live WebSocket server; the plant's and the
    encoder's telemetry of one sample are joined by k (at most ``pending_max``
    samples wait for their partner; older ones go out with what they have).
    """

    def __init__(self, sc, *, roa: bool = True, background: bool = False, pending_max: int = 256):
        self.sc = sc
        self.T_ns = int(round(sc.T * 1e9))
        self.N = int(sc.n_steps)
        self.n = sc.make_model().n
        # the outline's grid costs about 1 s at T = 0.1 s and grows as 1/T (a minute at 1 ms): drawn at
        # T >= ROA_MIN_T only, and off the caller's thread when ``background`` (a recorder's writer)
        self.roa_wanted = roa and self.n == 2 and sc.T >= ROA_MIN_T
        self.roa = None
        self.roa_sent = False
        # None: computed on the caller's thread when first asked; a Thread: computing; False: computed
        self._roa_thread: Any = None
        if self.roa_wanted and background:
            import threading

            self._roa_thread = threading.Thread(target=self._compute_roa, name="roa-outline", daemon=True)
            self._roa_thread.start()
        self.scene: PhaseScene | None = None
        self.t0: int | None = None
        self.pending: dict[int, list] = {}
        self.pending_max = pending_max
        self.done: set[int] = set()       # samples whose scene went out (late partners are dropped)
        self.done_order: list[int] = []
        self.attack_on = False

    def _stamp(self, k: int) -> int:
        return (self.t0 or 0) + k * self.T_ns

    def _abs(self, t_ns: int, fallback: int) -> int:
        return fallback if self.t0 is None or t_ns == msg.NO_TIME else self.t0 + t_ns

    def _log(self, t: int, level: int, text: str, name: str, log_time: int):
        return (TOPIC_LOG, LOG, log_message(t, level, text, name), log_time)

    def busy(self) -> bool:
        """The outline's background thread is still running (in numba's compiler, for a plant whose
        kernels are not cached yet)."""
        return bool(self._roa_thread) and self._roa_thread.is_alive()

    def _compute_roa(self):
        try:
            self.roa = roa_outline(self.sc)
        except Exception:  # noqa: BLE001 - a picture only: never lose the recording over it
            self.roa = None

    def _roa_items(self, wait: float = 0.0) -> list:
        """The outline's one SceneUpdate (log time t0), once it is computed and t0 is known."""
        if not self.roa_wanted or self.roa_sent or self.t0 is None:
            return []
        if self._roa_thread is None:
            self._compute_roa()
            self._roa_thread = False
        elif self._roa_thread:
            self._roa_thread.join(wait)
            if self._roa_thread.is_alive():
                return []
        self.roa_sent = True
        r = roa_update(self.roa, self.t0)
        return [] if r is None else [(TOPIC_ROA, SCENE, r, self.t0)]

    def _ensure_scene(self):
        if self.scene is None:
            self.scene = PhaseScene(window_of(self.sc, None), refresh=round(REFRESH_S / self.sc.T))

    # ---- messages
    def start(self, s: msg.Start, log_time: int) -> list:
        if self.t0 is not None:  # the launcher repeats its Start until every node has it
            return []
        self.t0 = s.t0_ns
        self._ensure_scene()
        return [self._log(s.t0_ns, INFO, f"run {s.run_id} started: scenario {self.sc.name}, {s.n_steps} samples "
                          f"of T = {s.T_ns / 1e9:g} s, timing {s.timing}", "launcher", log_time)] + self._roa_items()

    def stop(self, s: msg.Stop, log_time: int) -> list:
        return [self._log(log_time, INFO, f"run ended: {s.reason} ({s.origin})", s.origin or "run", log_time)]

    def event(self, e: msg.Event, log_time: int) -> list:
        level = _LEVEL_OF_KIND.get(e.kind, ERROR if "kill" in e.kind or "fault" in e.kind else INFO)
        where = f" at k = {e.k}" if e.k >= 0 else ""
        return [self._log(self._abs(e.t_ns, log_time), level, f"{e.kind}{where}: {e.detail}", e.node, log_time)]

    def status(self, s: msg.AttackerStatus, log_time: int) -> list:
        if bool(s.attack_on) == self.attack_on:
            return []
        self.attack_on = bool(s.attack_on)
        text = (f"DoS attack starts at k = {s.k}" if s.attack_on else f"DoS attack ends at k = {s.k}") + \
            f" ({s.dropped} symbols dropped so far)"
        return [self._log(self._stamp(s.k), WARNING if s.attack_on else INFO, text, "attacker", log_time)]

    def plant(self, t: msg.PlantTelemetry, log_time: int) -> list:
        if t.flags & msg.PlantTelemetry.FLAG_FINAL or not 0 <= t.k < self.N or t.k in self.done:
            return []
        self.pending.setdefault(t.k, [None, None, log_time])[0] = t
        return self._ready(t.k, log_time)

    def encoder(self, t: msg.EncoderTelemetry, log_time: int) -> list:
        if not 0 <= t.k < self.N or t.k in self.done:
            return []
        self.pending.setdefault(t.k, [None, None, log_time])[1] = t
        return self._ready(t.k, log_time)

    def _ready(self, k: int, log_time: int) -> list:
        out = self._roa_items()
        p, e, _ = self.pending[k]
        if p is not None and e is not None:
            out += self._emit(k, log_time)
        while len(self.pending) > self.pending_max:
            out += self._emit(min(self.pending), log_time)
        return out

    def flush(self, log_time: int) -> list:
        """Everything still waiting for its partner (when the recorder or server closes)."""
        out = self._roa_items(wait=10.0)
        for k in sorted(self.pending):
            out += self._emit(k, log_time)
        return out

    def _emit(self, k: int, log_time: int) -> list:
        p, e, _ = self.pending.pop(k)
        self.done.add(k)
        self.done_order.append(k)
        if len(self.done_order) > 4 * self.pending_max:
            for old in self.done_order[:2 * self.pending_max]:
                self.done.discard(old)
            del self.done_order[:2 * self.pending_max]
        self._ensure_scene()
        assert self.scene is not None
        x = p.x if p is not None else ()
        xi = E = None
        if e is not None and not e.silent and e.xi:
            xi, E = e.xi, e.E
        return [(TOPIC_PHASE, SCENE, self.scene.sample(self._stamp(k), x, xi, E), log_time)]


def telemetry_extra(name: str, t: Any, t0_ns: int | None, T_ns: int) -> dict | None:
    """The derived fields of a telemetry message: ``header`` (its stamp t0 + k T, absolute), ``log10_E``."""
    if t0_ns is None:
        return None
    out: dict[str, float] = {"header": t0_ns + int(t.k) * T_ns}
    E = getattr(t, "E", None)
    if E is not None and name in ("EncoderSample", "ControllerSample") and E > 0 and math.isfinite(E):
        out["log10_E"] = math.log10(E)
    return out


# ============================================================================ the layout file
def layout_json() -> str:
    """docs/foxglove-layout.json (``python -m testbed.view.foxglove``; needs foxglove-sdk).

    Plots of x, u, log10 E_k at encoder and decoder, theta_k with the attack on
    the x axis of the samples' header stamps; the 3D panel on the phase plane; the Log panel.
    """
    import json

    import foxglove.layouts as fl

    def plot(title, series, **cfg):
        return fl.PlotPanel(title=title, config=fl.PlotConfig(
            paths=[fl.PlotSeries(value=v, label=lab, timestamp_method="headerStamp", **kw) for v, lab, kw in series],
            show_legend=True, legend_display="top", **cfg))

    plots = [
        plot("state x_k", [("/telemetry/plant.x[0]", "x1", {}), ("/telemetry/plant.x[1]", "x2", {})]),
        plot("input u_k", [("/telemetry/plant.u[0]", "u1", {"line_interpolation": "step"})]),
        plot("log10 E_k: encoder and decoder", [("/telemetry/encoder.log10_E", "encoder", {}),
                                                ("/telemetry/controller.log10_E", "decoder",
                                                 {"line_style": "dashed"})]),
        plot("theta_k (1 = lost) and DoS on", [("/telemetry/controller.theta", "theta_k", {"line_interpolation": "step"}),
                                              ("/telemetry/attacker.attack_on", "attack on",
                                               {"line_interpolation": "step", "line_style": "dotted"})],
             min_y_value=-0.1, max_y_value=1.1),
    ]
    three = fl.ThreeDeePanel(title="phase plane: trajectory, x_k, xi_k, Q(xi_k, E_k), nominal ROA",
                             config=fl.ThreeDeeConfig(
                                 follow_tf=FRAME, follow_mode="follow-none",
                                 camera_state=fl.ThreeDeeCameraState(perspective=False, distance=3.0, phi=0.0,
                                                                     theta_offset=0.0, target=(0.0, 0.0, 0.0)),
                                 topics={TOPIC_PHASE: fl.BaseRendererSceneUpdateTopicSettings(visible=True),
                                         TOPIC_ROA: fl.BaseRendererSceneUpdateTopicSettings(visible=True)}))
    log = fl.LogPanel(title="events", config=fl.LogConfig(topic_to_render=TOPIC_LOG, show_name=True))
    lay = fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=1, content=fl.SplitContainer(direction="column",
                                                             items=[fl.SplitItem(content=p) for p in plots])),
        fl.SplitItem(proportion=1, content=fl.SplitContainer(direction="column", items=[
            fl.SplitItem(proportion=2, content=three), fl.SplitItem(proportion=1, content=log)])),
    ]))
    return json.dumps(json.loads(lay.to_json()), indent=2) + "\n"


__all__ = ["TOPICS", "TOPIC_LOG", "TOPIC_PHASE", "TOPIC_ROA", "LOG", "SCENE", "FRAME", "descriptor_set",
           "PhaseScene", "roa_update", "log_message", "FoxgloveTopics", "telemetry_extra", "layout_json"]


if __name__ == "__main__":
    import sys

    sys.stdout.write(layout_json())
