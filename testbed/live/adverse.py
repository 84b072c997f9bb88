"""``testbed conformance``'s adverse cases: a late, a duplicated and an invalid message fed to the external node.

A Zenoh peer of the run holding the certificate of the role that feeds the node (the controller feeds a
plant, the plant an encoder, the attacker a controller, the encoder an attacker) watches the node's
input key and, once each, right after the genuine message of a sample at or after the case's sample:

- **duplicate**: puts the same message again (the spec: the first copy counts, later ones are late);
- **late**: puts the message of sample k - 3 again (its payload and header, as the feeder received it),
  a sample already past (ignored as late).  Not sample k's payload under k - 3's header: a node that
  wrongly kept it for the next sample would go unseen where u_k = u_{k+1} (both 0 inside a DoS
  interval), while an old u_{k-3} differs from u_{k+1} unless the attack spans all five samples;
- **invalid**: puts the genuine payload with an 11-byte header (malformed: dropped, counted, nothing
  else changes).

A node that does what the spec says ignores all three, so the run still equals the simulator bit for
bit; the first sample where it does not names the case that broke it (``verdicts``).
"""

from __future__ import annotations

import threading
import time

from ..wire import messages as msg
from ..wire import transport

#: the role whose certificate feeds the external ROLE, and the key (a ``Keys`` attribute) it feeds it on
FEEDER = {"plant": ("controller", "actuation"), "encoder": ("plant", "sensor"),
          "controller": ("attacker", "symbol_rx"), "attacker": ("encoder", "symbol_tx")}
#: the cases, in the order they are fed, and the sample at or after which each is fed
CASES = (("duplicate", 5), ("late", 9), ("invalid", 13))
LATE_BY = 3


class Feeder:
    """The peer that feeds the adverse cases (``start`` once the run listens, ``close`` after it)."""

    def __init__(self, role: str, run_id: str, tls_dir: str, port: int):
        self.role, self.tls_dir, self.port = role, tls_dir, port
        self.keys = transport.Keys.for_run(run_id)
        self.user, attr = FEEDER[role]
        self.key = getattr(self.keys, attr)
        self.fed: dict[str, dict] = {}
        self._next = 0
        self._seen: dict[int, tuple[bytes, bytes]] = {}  # the last genuine messages by k (the late case's)
        self._sent: set[tuple[bytes, bytes]] = set()     # (payload, attachment) of the copies put here
        self._lock = threading.Lock()
        self._session = None
        self.error: str | None = None

    def start(self) -> None:
        import zenoh

        try:
            conf = transport.make_config(connect=[f"tls/127.0.0.1:{self.port}"], mode="peer",
                                         tls=transport.TlsCredentials(self.tls_dir).zenoh(self.user))
            self._session = zenoh.open(conf)
            self._session.declare_subscriber(self.key, self._on)
        except Exception as e:  # noqa: BLE001 - reported as the adverse cases' evidence
            self.error = f"{type(e).__name__}: {e}"

    def _on(self, sample) -> None:
        att = sample.attachment
        try:
            h = msg.Header.decode(att.to_bytes() if att is not None else b"")
        except msg.MessageError:
            return  # our own invalid copy
        if h.warmup:
            return
        payload = sample.payload.to_bytes()
        with self._lock:
            if self._next >= len(CASES) or (payload, att.to_bytes()) in self._sent:
                return  # done, or a copy this peer put (its own subscriber gets it too)
            self._seen.setdefault(h.k, (payload, att.to_bytes()))
            self._seen = {k: v for k, v in self._seen.items() if k > h.k - 2 * LATE_BY}
            case, k0 = CASES[self._next]
            if h.k < k0 or (case == "late" and h.k - LATE_BY not in self._seen):
                return
            self._next += 1
            old = self._seen.get(h.k - LATE_BY)
            if case == "duplicate":
                self._sent.add((payload, att.to_bytes()))
            elif case == "late":
                self._sent.add(old)
        if case == "duplicate":
            self._session.put(self.key, payload, attachment=att.to_bytes())
            k = h.k
        elif case == "late":
            k = h.k - LATE_BY
            self._session.put(self.key, old[0], attachment=old[1])
        else:
            k = h.k
            self._session.put(self.key, payload, attachment=att.to_bytes()[:msg.HEADER_SIZE - 1])
        self.fed[case] = {"k": k, "after_genuine_k": h.k, "key": self.key, "as": self.user,
                          "t_wall_ns": time.time_ns()}

    def close(self) -> None:
        if self._session is not None:
            try:
                self._session.close()
            except Exception:  # noqa: BLE001 - closing at the end
                pass


def verdicts(fed: dict, error: str | None, first_diff: int | None, stall_again, *, node_counts: dict) -> list[dict]:
    """One verdict per case: pass when it was fed and the run equals the simulator at and after it.

    ``first_diff``: the first sample where the run left the simulator (None: it never did)."""
    out = []
    order = [(case, fed[case]["after_genuine_k"]) for case, _ in CASES if case in fed]
    culprit = None
    if first_diff is not None:
        before = [c for c, k in order if k <= first_diff]
        culprit = before[-1] if before else None
    names = [c for c, _ in order]
    for case, k0 in CASES:
        name = f"adverse_{case}"
        f = fed.get(case)
        if f is None:
            why = error or f"no message of a sample >= {k0} came on its input to feed it after"
            out.append(_v(name, "inconclusive", f"not fed: {why}"))
            continue
        what = {"duplicate": f"a second copy of sample {f['k']}'s message",
                "late": f"sample {f['k']}'s message again after sample {f['after_genuine_k']}'s (already past)",
                "invalid": f"sample {f['k']}'s payload with an 11-byte header"}[case]
        evidence = f"fed {what} on {f['key'].split('/', 2)[-1]} (as the {f['as']})"
        counts = ", ".join(f"{k} {v}" for k, v in node_counts.items() if v)
        if first_diff is None:
            out.append(_v(name, "pass", f"{evidence}: ignored, the run still equals the simulator"
                                        + (f" (the node counted: {counts})" if counts else "")))
        elif culprit is None:
            out.append(_v(name, "inconclusive", f"{evidence}; the run had left the simulator at sample "
                                                f"{first_diff}, before any case was fed"))
        elif case == culprit:
            out.append(_v(name, "inconclusive" if stall_again else "fail",
                          f"{evidence}: the run left the simulator at sample {first_diff}, after it"
                          + (f" (the run stalled twice: {stall_again})" if stall_again else "")))
        elif names.index(case) < names.index(culprit):
            out.append(_v(name, "pass", f"{evidence}: ignored, the run equals the simulator up to sample "
                                        f"{first_diff - 1}"))
        else:
            out.append(_v(name, "inconclusive", f"{evidence}; the run had left the simulator at sample "
                                                f"{first_diff}, before"))
    return out


def _v(name: str, status: str, detail: str) -> dict:
    return {"name": name, "passed": status == "pass", "status": status, "detail": detail}
