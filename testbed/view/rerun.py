"""Rerun view of a run: live (``testbed run --rerun``), replayed (``testbed replay``) or simulated.

One core, :func:`log_samples`, logs plain per-sample arrays; a whole run (a ``testbed.Run``:
``testbed simulate --rrd`` and the replay of an MCAP recording, :func:`log_run`) and the
live nodes all go through it, so they produce the same entities and the same blueprint.

Timelines
---------
``k``  sequence, the sample index k;
``t``  duration, the nominal sample instant t_k = k T (seconds since t0).

Entities (one recording; in a live run each process logs its own subtree into the
same recording id, the launcher logs the static parts and the blueprint)

=========================  ==================  ==========================================
entity                     archetype           what (logged by, live)
=========================  ==================  ==========================================
``plant/x``                Scalars (n)         state x_k (plant; the last row is x_N)
``plant/u``                Scalars (m)         input u_k applied over [t_k, t_k+1) (plant)
``encoder/E``              Scalars             E_k at the encoder, Algorithm 1 (encoder)
``encoder/log10_E``        Scalars             log10 E_k, the plotted one (encoder)
``encoder/xi``             Scalars (n)         xi_k at the encoder (encoder)
``encoder/saturated``      Scalars             1 when x_k is outside Q(xi_k, E_k) (encoder)
``controller/E``           Scalars             E_k at the decoder, Algorithm 2 (controller)
``controller/log10_E``     Scalars             log10 E_k at the decoder (controller)
``controller/xi``          Scalars (n)         xi_k at the decoder (controller)
``controller/theta``       Scalars             theta_k, 1 = the symbol of sample k was lost (controller)
``attacker/attack_on``     Scalars             1 while a DoS interval is on (attacker)
``phase/trajectory``       LineStrips2D        segment x_{k-1} -> x_k; the view shows all of them (plant)
``phase/x``                Points2D            x_k, current state (plant)
``phase/xi``               Points2D            xi_k at the encoder (encoder)
``phase/box``              Boxes2D             Q(xi_k, E_k): centre xi_k, half-width E_k (inf-norm box) (encoder)
``phase/roa``              LineStrips2D        static: outline of the nominal region of attraction (launcher)
``scenario``               TextDocument        static: the scenario file (launcher)
=========================  ==================  ==========================================

The phase plane shows components ``(0, 1)`` of the state; for n > 2 (the
cart-pole) it is a projection and no region-of-attraction outline is drawn (the
region is a 4-D set; its grid is a slice over other coordinates).

E_k spans many decades (down to 1e-90 in the paper's example) and the 0.41
time-series view has no logarithmic axis, so the plot shows ``log10_E``; the
exact E_k is logged beside it (``encoder/E``, ``controller/E``).

Rerun is imported only inside the functions: importing this module is cheap.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .phase import PHASE_DIMS, RoaOutline, phase_bounds, roa_outline

if TYPE_CHECKING:
    from ..scenario import Scenario

APP_ID = "testbed"
TIMELINE_K = "k"
TIMELINE_T = "t"

COLOR_X = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40)]
COLOR_ENC = (31, 119, 180)
COLOR_DEC = (214, 39, 40)
COLOR_BOX = (255, 165, 0)
COLOR_ROA = (128, 128, 128)


# ============================================================================ core: arrays -> entities
def _times(k: np.ndarray, T: float) -> list:
    import rerun as rr

    k = np.asarray(k, dtype=np.int64)
    return [rr.TimeColumn(TIMELINE_K, sequence=k), rr.TimeColumn(TIMELINE_T, duration=k * float(T))]


def _scalars(rec: Any, path: str, k: np.ndarray, T: float, values: np.ndarray) -> None:
    import rerun as rr

    values = np.asarray(values, dtype=np.float64)
    if values.shape[0] == 0:
        return
    rr.send_columns(path, indexes=_times(k, T), columns=rr.Scalars.columns(scalars=values), recording=rec)


def _log10(E: np.ndarray) -> np.ndarray:
    E = np.asarray(E, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.log10(E)
    return np.where(np.isfinite(out), out, np.nan)


def log_samples(rec: Any, k: np.ndarray, T: float, *, x: np.ndarray | None = None, u: np.ndarray | None = None,
                E_enc: np.ndarray | None = None, xi_enc: np.ndarray | None = None, saturated: np.ndarray | None = None,
                E_dec: np.ndarray | None = None, xi_dec: np.ndarray | None = None, theta: np.ndarray | None = None,
                attack_on: np.ndarray | None = None, x_prev: np.ndarray | None = None,
                dims: tuple[int, int] = PHASE_DIMS) -> None:
    """Log samples ``k`` (int array) of whatever arrays are given (rows aligned with ``k``).

    Parameters
    ----------
    rec : rerun.RecordingStream.
    k : sample indices (N,); T : sampling period (for the ``t`` timeline).
    x (N, n), u (N, m) : plant state and input; E_enc (N,), xi_enc (N, n), saturated (N,) :
        encoder (Algorithm 1); E_dec, xi_dec : decoder (Algorithm 2); theta (N,) : 1 = lost;
        attack_on (N,) : 1 = DoS interval on.
    x_prev : the state before ``k[0]`` (starts the first trajectory segment; batches of a live run).
    dims : the two state components of the phase plane.
    """
    import rerun as rr

    k = np.asarray(k, dtype=np.int64)
    if k.size == 0:
        return
    a, b = dims
    if x is not None:
        x = np.asarray(x, dtype=np.float64)
        _scalars(rec, "plant/x", k, T, x)
        rr.send_columns("phase/x", indexes=_times(k, T), columns=rr.Points2D.columns(positions=x[:, [a, b]]),
                        recording=rec)
        pts = x[:, [a, b]]
        if x_prev is not None:
            pts = np.vstack([np.asarray(x_prev, dtype=np.float64)[[a, b]], pts])
            ks = k
        else:
            ks = k[1:]
        if len(pts) >= 2:
            seg = np.stack([pts[:-1], pts[1:]], axis=1)
            rr.send_columns("phase/trajectory", indexes=_times(ks, T),
                            columns=rr.LineStrips2D.columns(strips=list(seg)), recording=rec)
    if u is not None:
        u = np.asarray(u, dtype=np.float64)
        _scalars(rec, "plant/u", k[:len(u)], T, u)
    if E_enc is not None:
        _scalars(rec, "encoder/E", k, T, E_enc)
        _scalars(rec, "encoder/log10_E", k, T, _log10(E_enc))
    if xi_enc is not None:
        xi_enc = np.asarray(xi_enc, dtype=np.float64)
        _scalars(rec, "encoder/xi", k, T, xi_enc)
        rr.send_columns("phase/xi", indexes=_times(k, T), columns=rr.Points2D.columns(positions=xi_enc[:, [a, b]]),
                        recording=rec)
        if E_enc is not None:
            E = np.asarray(E_enc, dtype=np.float64)
            rr.send_columns("phase/box", indexes=_times(k, T),
                            columns=rr.Boxes2D.columns(centers=xi_enc[:, [a, b]], half_sizes=np.c_[E, E]),
                            recording=rec)
    if saturated is not None:
        _scalars(rec, "encoder/saturated", k, T, np.asarray(saturated, dtype=np.float64))
    if E_dec is not None:
        _scalars(rec, "controller/E", k, T, E_dec)
        _scalars(rec, "controller/log10_E", k, T, _log10(E_dec))
    if xi_dec is not None:
        _scalars(rec, "controller/xi", k, T, xi_dec)
    if theta is not None:
        _scalars(rec, "controller/theta", k, T, np.asarray(theta, dtype=np.float64))
    if attack_on is not None:
        _scalars(rec, "attacker/attack_on", k, T, np.asarray(attack_on, dtype=np.float64))


def log_styles(rec: Any, n: int, m: int, roles: Iterable[str] = ("plant", "encoder", "controller", "attacker")) -> None:
    """Static series names and colours of the entities of ``roles``."""
    import rerun as rr

    names_x = [f"x{i + 1}" for i in range(n)]
    cols_x = [COLOR_X[i % len(COLOR_X)] for i in range(n)]
    st: dict[str, dict] = {
        "plant": {"plant/x": rr.SeriesLines(names=names_x, colors=cols_x),
                  "plant/u": rr.SeriesLines(names=[f"u{i + 1}" for i in range(m)]),
                  "phase/trajectory": rr.LineStrips2D.from_fields(colors=[(60, 60, 60)], radii=[-1.5]),
                  "phase/x": rr.Points2D.from_fields(colors=[(0, 0, 0)], radii=[-4.0], labels=["x_k"])},
        "encoder": {"encoder/log10_E": rr.SeriesLines(names=["log10 E_k encoder"], colors=[COLOR_ENC], widths=[3.0]),
                    "encoder/E": rr.SeriesLines(names=["E_k encoder"], colors=[COLOR_ENC]),
                    "encoder/xi": rr.SeriesLines(names=[f"xi{i + 1} encoder" for i in range(n)]),
                    "encoder/saturated": rr.SeriesPoints(names=["saturated"], markers=["cross"]),
                    "phase/xi": rr.Points2D.from_fields(colors=[COLOR_BOX], radii=[-4.0], labels=["xi_k"]),
                    "phase/box": rr.Boxes2D.from_fields(colors=[COLOR_BOX], radii=[-1.5])},
        "controller": {"controller/log10_E": rr.SeriesPoints(names=["log10 E_k decoder"], colors=[COLOR_DEC],
                                                             markers=["circle"], marker_sizes=[1.5]),
                       "controller/E": rr.SeriesLines(names=["E_k decoder"], colors=[COLOR_DEC]),
                       "controller/xi": rr.SeriesLines(names=[f"xi{i + 1} decoder" for i in range(n)]),
                       "controller/theta": rr.SeriesPoints(names=["theta_k (1 = lost)"], colors=[COLOR_DEC],
                                                           markers=["circle"], marker_sizes=[3.0])},
        "attacker": {"attacker/attack_on": rr.SeriesLines(names=["DoS on"], colors=[(120, 120, 120)],
                                                          widths=[2.0])},
    }
    for role in roles:
        for path, arch in st.get(role, {}).items():
            rr.log(path, arch, static=True, recording=rec)


def flip_y(rec: Any) -> None:
    """Rerun's 2D space has y pointing down: a static transform of ``phase`` makes x2 point up (values unchanged)."""
    import rerun as rr

    rr.log("phase", rr.Transform3D(mat3x3=[[1, 0, 0], [0, -1, 0], [0, 0, 1]]), static=True, recording=rec)


# ============================================================================ static parts and blueprint
def log_scenario(rec: Any, sc: Scenario, *, roa: bool = True, roa_grid: int = 61) -> RoaOutline | None:
    """Static: the scenario text and the nominal region's outline (when ``roa`` and n = 2)."""
    import rerun as rr

    flip_y(rec)
    text = sc.source or f"scenario {sc.name}"
    rr.log("scenario", rr.TextDocument(text, media_type="text/plain"), static=True, recording=rec)
    out = roa_outline(sc, roa_grid) if roa else None
    if out is not None and out.lines:
        rr.log("phase/roa", rr.LineStrips2D(list(out.lines), colors=[COLOR_ROA], radii=[-1.0],
                                            labels=["nominal ROA"] + [""] * (len(out.lines) - 1)),
               static=True, recording=rec)
    return out


def blueprint(sc: Scenario, bounds: tuple[tuple[float, float], tuple[float, float]] | None = None) -> Any:
    """States and input over time; log10 E_k at encoder and decoder; theta_k and DoS; the phase plane."""
    import rerun.blueprint as rrb

    all_history = [rrb.VisibleTimeRange(TIMELINE_K, start=rrb.TimeRangeBoundary.infinite(),
                                        end=rrb.TimeRangeBoundary.cursor_relative(seq=0)),
                   rrb.VisibleTimeRange(TIMELINE_T, start=rrb.TimeRangeBoundary.infinite(),
                                        end=rrb.TimeRangeBoundary.cursor_relative(seconds=0.0))]
    phase_kw: dict[str, Any] = {}
    if bounds is not None:
        (x0, x1), (y0, y1) = bounds
        phase_kw["visual_bounds"] = rrb.VisualBounds2D(x_range=[x0, x1], y_range=[y0, y1])
    phase = rrb.Spatial2DView(
        name="phase plane: x_k, xi_k, Q(xi_k, E_k), nominal ROA", origin="/",
        contents=["phase/**"],
        overrides={"phase/trajectory": [rrb.VisibleTimeRanges(all_history)]},
        **phase_kw)
    plots = rrb.Vertical(
        rrb.TimeSeriesView(name="state x_k", origin="/", contents=["plant/x"]),
        rrb.TimeSeriesView(name="input u_k", origin="/", contents=["plant/u"]),
        rrb.TimeSeriesView(name="log10 E_k: encoder and decoder", origin="/",
                           contents=["encoder/log10_E", "controller/log10_E"]),
        rrb.TimeSeriesView(name="theta_k and DoS intervals", origin="/",
                           contents=["controller/theta", "attacker/attack_on"],
                           axis_y=rrb.ScalarAxis(range=(-0.1, 1.1))),
    )
    return rrb.Blueprint(
        rrb.Horizontal(plots, phase, column_shares=[1, 1]),
        rrb.TimePanel(timeline=TIMELINE_T, expanded=False),
        collapse_panels=True,
    )


# ============================================================================ offline: a whole run
def log_run(rec: Any, run: Any) -> None:  # run: a testbed.Run (a layer above)
    """Every entity of a whole run (the same ones a live run streams).

    ``run``: a ``testbed.Run`` (a simulation or a recording), read duck-typed (this layer sits below
    it): ``run.arrays`` (``x``, ``u``, ``E``, ``xi``, ``E_dec``, ``xi_dec``, ``theta``, ``attack_on``,
    ``saturated``; rows k = 0..N-1), ``run.scenario.T`` and ``run.summary["x_final"]`` (x_N, or None).
    NaN in E_k or xi_k marks a sample an end did not record: it is not logged.
    """
    a, T = run.arrays, float(run.scenario.T)
    x = np.asarray(a["x"], dtype=np.float64)
    N = len(x)
    k = np.arange(N)
    E_enc, xi_enc = np.asarray(a["E"], dtype=np.float64), np.asarray(a["xi"], dtype=np.float64)
    E_dec, xi_dec = np.asarray(a["E_dec"], dtype=np.float64), np.asarray(a["xi_dec"], dtype=np.float64)
    ok_e = np.isfinite(E_enc) & np.all(np.isfinite(xi_enc), axis=1)
    ok_d = np.isfinite(E_dec) & np.all(np.isfinite(xi_dec), axis=1)
    x_final = run.summary.get("x_final")
    xs = x if x_final is None else np.vstack([x, np.asarray(x_final, dtype=np.float64)[None, :]])
    log_samples(rec, np.arange(len(xs)), T, x=xs)
    log_samples(rec, k, T, u=a["u"], theta=a["theta"], attack_on=a["attack_on"], saturated=a["saturated"])
    log_samples(rec, k[ok_e], T, E_enc=E_enc[ok_e], xi_enc=xi_enc[ok_e])
    log_samples(rec, k[ok_d], T, E_dec=E_dec[ok_d], xi_dec=xi_dec[ok_d])


def new_stream(recording_id: str | None = None) -> Any:
    import rerun as rr

    return rr.RecordingStream(APP_ID, recording_id=recording_id)


def run_to_rrd(path: str | Path, run: Any, *,  # run: a testbed.Run (a layer above)
               recording_id: str | None = None, roa: bool = True, spawn: bool = False) -> None:
    """Write (and/or show) a whole run (``log_run``): statics, blueprint and every sample.

    ``testbed simulate --rrd`` and ``testbed replay`` (the recording id: ``sim-NAME`` and the run id)."""
    import rerun as rr

    sc = run.scenario
    rec = new_stream(recording_id)
    out = roa_outline(sc) if roa else None
    x, u = np.asarray(run.arrays["x"]), np.asarray(run.arrays["u"])
    bp = blueprint(sc, phase_bounds(sc, x, out))
    sinks: list = []
    if path is not None:
        sinks.append(rr.FileSink(str(path)))
    if spawn:
        try:
            rr.spawn(connect=False, recording=rec)
        except (RuntimeError, OSError) as e:
            from ..common.errors import BadInput

            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise BadInput(f"no Rerun viewer to open ({first}); write the view to a file with --rrd PATH.rrd") \
                from None
        sinks.append(rr.GrpcSink())
    rec.set_sinks(*sinks)
    rec.send_blueprint(bp)
    log_styles(rec, x.shape[1], u.shape[1] if u.ndim == 2 else 1)
    log_scenario(rec, sc, roa=roa)
    log_run(rec, run)
    rec.flush()
    rec.disconnect()


# ============================================================================ live: testbed run --rerun
def rerun_binary() -> str:
    """The Rerun CLI shipped in the wheel (the binary itself: the Python wrapper does not forward signals)."""
    import shutil
    from pathlib import Path

    try:
        import rerun_cli

        p = Path(rerun_cli.__file__).parent / "rerun"
        if p.exists():
            return str(p)
    except ImportError:
        pass
    return shutil.which("rerun") or "rerun"


@contextmanager
def saving_server(path: str | Path, *, port: int = 0, startup_s: float = 30.0) -> Iterator[str]:
    """A headless Rerun gRPC server (``rerun --port P --save PATH``): it receives what a viewer's
    server would, without a window, and saves it (no footer: read it with ``RrdReader.stream()``).
    Yields the URL for ``--rerun connect``; stopped with SIGINT on exit (the test and the benchmark
    of the live-view sink).  ``port`` 0: a free one; 9876 stands in for the viewer ``--rerun spawn``
    would start (it reuses whatever listens there)."""
    import os
    import signal
    import socket
    import subprocess
    import time

    if not port:
        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            port = sock.getsockname()[1]
    srv = subprocess.Popen([rerun_binary(), "--port", str(port), "--save", str(path)], stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL, env=dict(os.environ, RERUN_ANALYTICS="0"),
                           start_new_session=True)
    try:
        end = time.monotonic() + startup_s
        while True:  # until it accepts connections (a loaded machine may take seconds)
            with socket.socket() as sock:
                if sock.connect_ex(("127.0.0.1", port)) == 0:
                    break
            if srv.poll() is not None or time.monotonic() > end:
                raise RuntimeError(f"rerun --port {port} --save {path}: no server "
                                   f"(exit code {srv.poll()}) after {startup_s:g} s")
            time.sleep(0.05)
        yield f"rerun+http://127.0.0.1:{port}/proxy"
    finally:
        srv.send_signal(signal.SIGINT)  # the server writes what it has and exits
        try:
            srv.wait(20)
        except subprocess.TimeoutExpired:
            srv.kill()
            srv.wait()


DEFAULT_URL = "rerun+http://127.0.0.1:9876/proxy"


def add_rerun_run_arguments(p: argparse.ArgumentParser) -> None:
    """The ``--rerun`` option group of ``testbed run``."""
    from ..common import cliargs

    g = p.add_argument_group("rerun (live view)")
    g.add_argument("--rerun", nargs="+", metavar="spawn | connect [URL] | save PATH.rrd",
                   help=f"stream the run to Rerun: spawn a viewer, connect to one (default {DEFAULT_URL}) "
                        "or save one .rrd; every node logs into one recording")
    cliargs.add_rrd(g, "write the run's Rerun view into this file (the same as --rerun save PATH.rrd)")
    cliargs.add_no_roa(g, aliases=("--rerun-no-roa",))


class LiveRerun:
    """The launcher's side of a live Rerun stream.

    Every process of the run (the launcher and the four nodes) opens its own
    ``RecordingStream`` with the same ``recording_id`` (the run id), so Rerun shows
    one recording.  The launcher logs the statics (scenario, ROA outline, series
    styles) and the blueprint; each node logs its own entities from a background
    thread (``testbed.nodes.rerun_tap``).  Sinks:

    * ``spawn``: a viewer is spawned (or reused) on port 9876; everybody connects to it over gRPC;
    * ``connect URL``: everybody connects to ``URL`` over gRPC;
    * ``save PATH``: every process writes its own part file (one .rrd cannot take
      several writers), and the launcher merges the parts into ``PATH`` at the end
      (``rerun rrd optimize``): one recording, one file.
    """

    def __init__(self, mode: str, target: str | None, sc: Scenario, recording_id: str, roa: bool = True) -> None:
        self.mode, self.target, self.sc, self.recording_id, self.roa = mode, target, sc, recording_id, roa
        self.rec: Any = None                  # the launcher's rerun RecordingStream, from start()
        self.parts_dir: str | None = None
        self.merge_error: str | None = None

    @classmethod
    def from_options(cls, spec: Sequence[str] | None, rrd: str | None, roa: bool, sc: Scenario,
                     recording_id: str) -> LiveRerun | None:
        """From ``testbed run``'s ``--rerun`` words (``spec``), ``--rrd`` and not ``--no-roa``; None: no live view."""
        from ..common.errors import BadInput

        spec = list(spec) if spec else None
        if rrd:
            if spec and spec != ["save", rrd]:
                raise BadInput(f"--rrd {rrd} and --rerun {' '.join(spec)}: give one of them")
            spec = ["save", rrd]
        if not spec:
            return None
        mode, rest = spec[0], spec[1:]
        if mode == "spawn" and not rest:
            return cls("spawn", None, sc, recording_id, roa)
        if mode == "connect" and len(rest) <= 1:
            return cls("connect", rest[0] if rest else DEFAULT_URL, sc, recording_id, roa)
        if mode == "save" and len(rest) == 1:
            return cls("save", rest[0], sc, recording_id, roa)
        raise BadInput(f"--rerun takes 'spawn', 'connect [URL]' or 'save PATH.rrd', got {' '.join(spec)}")

    @property
    def url(self) -> str:
        return self.target if self.mode == "connect" and self.target is not None else DEFAULT_URL

    def part(self, who: str) -> str:
        from pathlib import Path

        assert self.parts_dir is not None  # prepare() made it
        return str(Path(self.parts_dir) / f"{who}.rrd")

    def prepare(self) -> None:
        """``save``: the folder of the part files, which the nodes' flags name (no rerun import here:
        the launcher forks its nodes after this, and importing rerun starts threads)."""
        import tempfile
        from pathlib import Path

        if self.mode == "save" and self.parts_dir is None and self.target is not None:
            out = Path(self.target).resolve()
            out.parent.mkdir(parents=True, exist_ok=True)
            self.parts_dir = tempfile.mkdtemp(prefix=f".{out.name}.parts-", dir=out.parent)

    def start(self) -> None:
        """Before the nodes start: open the launcher's stream, send the blueprint and the statics."""
        import rerun as rr

        self.prepare()
        roa = roa_outline(self.sc) if self.roa else None
        bp = blueprint(self.sc, phase_bounds(self.sc, None, roa))
        self.rec = new_stream(self.recording_id)
        if self.mode == "save":
            self.rec.save(self.part("launcher"), default_blueprint=bp)
        else:
            if self.mode == "spawn":
                rr.spawn(connect=False, recording=self.rec)
            self.rec.connect_grpc(self.url, default_blueprint=bp)
        self.rec.send_recording_name(f"{self.sc.name} (live)")
        plant = self.sc.make_model()
        log_styles(self.rec, plant.n, plant.m, roles=())
        log_scenario(self.rec, self.sc, roa=self.roa)
        self.rec.flush()

    def finish(self) -> None:
        """After the nodes have stopped: close the stream; ``save``: merge the parts into one file."""
        import os
        import shutil
        import subprocess
        from pathlib import Path

        if self.rec is not None:
            self.rec.flush()
            self.rec.disconnect()
            self.rec = None
        if self.mode != "save" or self.parts_dir is None or self.target is None:
            return
        parts = sorted(str(p) for p in Path(self.parts_dir).glob("*.rrd"))
        env = dict(os.environ, RERUN_ANALYTICS="0")
        r = subprocess.run([rerun_binary(), "rrd", "optimize", "--continue-on-error", *parts, "-o", str(self.target)],
                           stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env,
                           timeout=120)
        if r.returncode == 0 and Path(self.target).exists():
            shutil.rmtree(self.parts_dir, ignore_errors=True)
        else:
            self.merge_error = f"rerun rrd optimize exit {r.returncode}: {r.stderr.decode(errors='replace')[-300:]}"

    def info(self) -> dict:
        d = {"mode": self.mode, "recording_id": self.recording_id,
             "target": self.target if self.mode != "spawn" else self.url}
        if self.merge_error:
            d["error"] = self.merge_error
            d["parts"] = self.parts_dir
        return d
