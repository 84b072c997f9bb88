"""A node's live Rerun stream (``testbed run --rerun``): its telemetry, logged off the control loop.

The loop only appends each telemetry record (the bytes it publishes anyway) to a
deque (``TelemetryOut.tap``); a daemon thread wakes every ``period`` seconds,
decodes what arrived and logs it in whole columns through
``testbed.view.rerun.log_samples``, the function the replay and the simulator use.
The stream joins the run's recording (``--recording-id``, the launcher's) and goes
to a gRPC URL (``--rerun-url``) or to a part file (``--rerun-save``) that the
launcher merges.
"""

from __future__ import annotations

import collections
import logging
import os
import threading
from typing import TYPE_CHECKING, Any

import numpy as np

from ..view import rerun as viewer
from ..wire import messages as msg

if TYPE_CHECKING:
    from ..scenario import Scenario
    from .options import NodeConfig

log = logging.getLogger("testbed.nodes")

_DECODE = msg.TELEMETRY_TYPES


NICE = 10  # the logging thread's (and Rerun's threads') nice value: the loop's threads stay at 0


class RerunTap:
    """Telemetry records of one node -> Rerun, from a background thread."""

    def __init__(self, role: str, sc: Scenario, recording_id: str | None, *, url: str | None = None,
                 save: str | None = None, period: float = 0.1, nice: int = NICE) -> None:
        self.role, self.T, self.period, self.nice = role, sc.T, period, nice
        plant = sc.make_model()
        self.n, self.m = plant.n, plant.m
        self._target = (recording_id, url, save)
        self.rec: Any = None  # the rerun RecordingStream, made in the tap's thread
        self.q: collections.deque = collections.deque()
        self.put = self.q.append  # the hook on the control path: one deque append
        self.x_prev = None
        self.logged = 0
        self.errors = 0
        self._stop = threading.Event()
        self._opened = threading.Event()
        self._open_error: BaseException | None = None
        self._thread = threading.Thread(target=self._loop, name=f"rerun-{role}", daemon=True)
        self._thread.start()
        self._opened.wait(60)
        if self._open_error is not None:
            raise RuntimeError(f"rerun stream of {role} not opened: {self._open_error}") from self._open_error

    def _open(self) -> None:
        """Runs on the logging thread, niced first: Rerun's own threads (batcher, sink) are created here
        and inherit its lower priority, so under CPU contention the control loop goes first."""
        import rerun as rr

        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), self.nice)
        except OSError:
            pass
        recording_id, url, save = self._target
        self.rec = rr.RecordingStream(viewer.APP_ID, recording_id=recording_id, send_properties=False)
        if save:
            self.rec.save(save)
        else:
            self.rec.connect_grpc(url or viewer.DEFAULT_URL)
        viewer.log_styles(self.rec, self.n, self.m, roles=(self.role,))

    def _loop(self) -> None:
        try:
            self._open()
        except BaseException as e:  # noqa: BLE001 - reported by __init__
            self._open_error = e
            self._opened.set()
            return
        self._opened.set()
        while not self._stop.wait(self.period):
            self.drain()
        self.drain()

    def drain(self) -> None:
        recs = []
        q = self.q
        while q:
            recs.append(q.popleft())
        if not recs:
            return
        try:
            self._log([_DECODE[self.role].decode(r) for r in recs])
            self.logged += len(recs)
        except Exception:
            self.errors += 1
            if self.errors <= 3:
                log.exception("%s: rerun logging failed", self.role)

    def _log(self, recs: list) -> None:
        T, rec = self.T, self.rec
        k = np.array([r.k for r in recs], dtype=np.int64)
        if self.role == "plant":
            xs = [r for r in recs if len(r.x) == self.n]
            if xs:
                x = np.array([r.x for r in xs])
                viewer.log_samples(rec, np.array([r.k for r in xs]), T, x=x, x_prev=self.x_prev)
                self.x_prev = x[-1]
            us = [r for r in recs if len(r.u) == self.m]
            if us:
                viewer.log_samples(rec, np.array([r.k for r in us]), T, u=np.array([r.u for r in us]))
        elif self.role == "encoder":
            ok = [r for r in recs if not r.silent and len(r.xi) == self.n]
            if ok:
                viewer.log_samples(rec, np.array([r.k for r in ok]), T, E_enc=np.array([r.E for r in ok]),
                                   xi_enc=np.array([r.xi for r in ok]),
                                   saturated=np.array([r.saturated for r in ok]))
        elif self.role == "controller":
            ok = [r for r in recs if len(r.xi) == self.n]
            if ok:
                viewer.log_samples(rec, np.array([r.k for r in ok]), T, E_dec=np.array([r.E for r in ok]),
                                   xi_dec=np.array([r.xi for r in ok]))
            th = [r for r in recs if r.theta != msg.THETA_NONE]
            if th:
                viewer.log_samples(rec, np.array([r.k for r in th]), T, theta=np.array([r.theta for r in th]))
        elif self.role == "attacker":
            viewer.log_samples(rec, k, T, attack_on=np.array([r.attack_on for r in recs]))

    def close(self, timeout: float = 5.0) -> dict:
        """Log what is left, flush and close the sink (the part file gets its footer)."""
        self._stop.set()
        self._thread.join(timeout)
        if self.rec is not None:
            try:
                self.rec.flush()
                self.rec.disconnect()
            except Exception:
                log.exception("%s: rerun flush failed", self.role)
        return {"rerun_logged": self.logged, "rerun_errors": self.errors}


def of(cfg: NodeConfig, role: str, sc: Scenario) -> RerunTap | None:
    """The tap a node's ``NodeConfig`` asks for (``--rerun-url`` / ``--rerun-save``, with ``--recording-id``), or None."""
    if not (cfg.rerun_url or cfg.rerun_save):
        return None
    return RerunTap(role, sc, cfg.recording_id or cfg.session.run_id, url=cfg.rerun_url, save=cfg.rerun_save)
