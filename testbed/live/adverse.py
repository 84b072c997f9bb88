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

A node that does what the spec says ignores all three.  Each case is judged from what the node did with
the message at the samples it targets (``targets``: the sample whose genuine message the copy followed,
and the next), never from equality with the simulator, so a node that is not bit-exact (a device with
its own integrator) gets pass or fail:

- **plant**: the u that acted there (its telemetry's ``u``) is the genuine u_k of the controller's
  actuation record (its telemetry), bit for bit (``plant_judge``);
- **encoder**: it sent at most one symbol for each of those samples, and the symbols (and xi_k, E_k, q_k) equal
  the testbed's nodes re-run on the plant's reported states (the replay, ``testbed resimulate --plant
  recorded``), which encodes the genuine x_k;
- **controller**: it sent at most one actuation for each, and theta_k, u_k (and its E_k, xi_k, q_k) equal the
  replay, which decodes the genuine symbol;
- **attacker**: what reached the controller there equals the replay, which forwards the genuine symbol
  as the attacker's recorded decisions say (an attacker may forward repeats: no count).

For the loop's nodes (``loop_judge``) a replay that differs before the targeted samples leaves the case
inconclusive; the plant's judgement needs no replay.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING

from ..wire import messages as msg
from ..wire import transport

if TYPE_CHECKING:
    import zenoh

#: the role whose certificate feeds the external ROLE, and the key (a ``Keys`` attribute) it feeds it on
FEEDER = {"plant": ("controller", "actuation"), "encoder": ("plant", "sensor"),
          "controller": ("attacker", "symbol_rx"), "attacker": ("encoder", "symbol_tx")}
#: the cases, in the order they are fed, and the sample at or after which each is fed
CASES = (("duplicate", 5), ("late", 9), ("invalid", 13))
LATE_BY = 3


class Feeder:
    """The peer that feeds the adverse cases (``start`` once the run listens, ``close`` after it)."""

    def __init__(self, role: str, run_id: str, tls_dir: str | None, endpoint: str, *, mode: str = "peer",
                 low_latency: bool = False):
        """``tls_dir`` None: an unauthenticated run (``--insecure``); ``endpoint``: the run's (the launcher's);
        ``mode``: "client" in the router topology."""
        self.role, self.tls_dir, self.endpoint = role, tls_dir, endpoint
        self.mode, self.low_latency = mode, low_latency
        self.keys = transport.Keys.for_run(run_id)
        self.user, attr = FEEDER[role]
        self.key = getattr(self.keys, attr)
        self.fed: dict[str, dict] = {}
        self._next = 0
        self._seen: dict[int, tuple[bytes, bytes]] = {}  # the last genuine messages by k (the late case's)
        self._sent: set[tuple[bytes, bytes]] = set()     # (payload, attachment) of the copies put here
        self._lock = threading.Lock()
        self._session: zenoh.Session | None = None
        self.error: str | None = None

    def start(self) -> None:
        import zenoh

        try:
            tls = None if self.tls_dir is None else transport.TlsCredentials(self.tls_dir).zenoh(self.user)
            conf = transport.make_config(connect=[self.endpoint], mode=self.mode, tls=tls,
                                         low_latency=self.low_latency)
            self._session = session = zenoh.open(conf)
            session.declare_subscriber(self.key, self._on)
        except Exception as e:  # noqa: BLE001 - reported as the adverse cases' evidence
            self.error = f"{type(e).__name__}: {e}"

    def _on(self, sample: zenoh.Sample) -> None:
        session = self._session
        assert session is not None  # subscribed to after the session opened
        att = sample.attachment
        raw = att.to_bytes() if att is not None else b""
        try:
            h = msg.Header.decode(raw)
        except msg.MessageError:
            return  # our own invalid copy
        if h.warmup:
            return
        payload = sample.payload.to_bytes()
        with self._lock:
            if self._next >= len(CASES) or (payload, raw) in self._sent:
                return  # done, or a copy this peer put (its own subscriber gets it too)
            self._seen.setdefault(h.k, (payload, raw))
            self._seen = {k: v for k, v in self._seen.items() if k > h.k - 2 * LATE_BY}
            case, k0 = CASES[self._next]
            if h.k < k0 or (case == "late" and h.k - LATE_BY not in self._seen):
                return
            self._next += 1
            old = self._seen.get(h.k - LATE_BY)
            if case == "duplicate":
                self._sent.add((payload, raw))
            elif case == "late":
                assert old is not None  # the guard above returned unless sample k - LATE_BY was seen
                self._sent.add(old)
        if case == "duplicate":
            session.put(self.key, payload, attachment=raw)
            k = h.k
        elif case == "late":
            k = h.k - LATE_BY
            assert old is not None
            session.put(self.key, old[0], attachment=old[1])
        else:
            k = h.k
            session.put(self.key, payload, attachment=raw[:msg.HEADER_SIZE - 1])
        self.fed[case] = {"k": k, "after_genuine_k": h.k, "key": self.key, "as": self.user,
                          "t_wall_ns": time.time_ns()}

    def close(self) -> None:
        if self._session is not None:
            try:
                self._session.close()
            except Exception:  # noqa: BLE001 - closing at the end
                pass


def targets(f: dict) -> tuple[int, int]:
    """The samples a fed case is judged at: the one whose genuine message it followed, and the next (a node
    that wrongly takes the copy acts on it at the sample it waits for then)."""
    k = int(f["after_genuine_k"])
    return k, k + 1


def plant_judge(acted: dict, sent: dict, n_steps: int, u_max: float) -> Callable[[str, dict], tuple[str, str]]:
    """A plant's judge (``verdicts``): at each targeted sample, the u that acted (its telemetry: ``acted``,
    k -> (u, flags)) is the controller's genuine u_k (its actuation record: ``sent``, k -> u), compared bit for
    bit after the plant's saturation at ``u_max``; where the plant reports u_k missing (flags bit 1) it acted
    u = 0 and took no copy for it."""
    from ..wire.messages import PlantTelemetry

    def clip(u: Iterable[float]) -> tuple[float, ...]:
        return tuple(min(max(float(v), -u_max), u_max) for v in u)

    def judge(case: str, f: dict) -> tuple[str, str]:
        ks = [j for j in targets(f) if j < n_steps]
        for j in ks:
            if j not in acted:
                return "fail", f"the plant recorded no telemetry for sample {j}"
            u, flags = acted[j]
            if flags & PlantTelemetry.FLAG_NO_U:
                if any(v != 0 for v in u):
                    return "fail", f"at sample {j} the plant reports u_k missing but u = {list(u)} acted, not 0"
                continue
            if j not in sent:
                return "inconclusive", f"the controller recorded no u for sample {j}"
            if clip(u) != clip(sent[j]):
                return "fail", (f"taken: at sample {j} u = {list(u)} acted, the controller's u_{j} is "
                                f"{list(sent[j])}")
        return "pass", (f"ignored: the u that acted at sample{'s' if len(ks) > 1 else ''} "
                        f"{' and '.join(map(str, ks))} is the controller's genuine u_k")

    return judge


def loop_judge(first: int | None, differs_in: list, repeated: dict,
               what: str) -> Callable[[str, dict], tuple[str, str]]:
    """The judge (``verdicts``) of a node of the loop (an encoder, a controller, an attacker): at the targeted
    samples, what the loop computed (``what``: the node's observable) equals the testbed's nodes re-run on
    the plant's reported states from the genuine messages (``first``: that replay's first differing sample,
    None: none; ``differs_in``: the quantities there), and the node sent one message per sample there
    (``repeated``: k -> why, where it sent more)."""

    def judge(case: str, f: dict) -> tuple[str, str]:
        ks = targets(f)
        bad = [repeated[j] for j in ks if j in repeated]
        if bad:
            return "fail", f"taken: {bad[0]}"
        if first is None or first > ks[-1]:
            return "pass", f"ignored: at samples {ks[0]} and {ks[1]} {what} equal the loop's replay on the genuine messages"
        where = f"the loop's replay on the genuine messages differs at sample {first} ({', '.join(differs_in)})"
        if first >= ks[0]:
            return "fail", f"taken: {where}"
        return "inconclusive", f"{where}, before it"

    return judge


def verdicts(fed: dict, error: str | None, judge: Callable[[str, dict], tuple[str, str]], *,
             node_counts: dict) -> list[dict]:
    """One verdict per case, from what the node did with the copy at the samples it targets (``targets``):
    ``judge(case, fed[case])`` -> (status, why) (``plant_judge``, ``loop_judge``); a case not fed is
    inconclusive."""
    out = []
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
        status, why = judge(case, f)
        out.append(_v(name, status, f"{evidence}: {why}"
                                    + (f" (the node counted: {counts})" if counts and status == "pass" else "")))
    return out


def _v(name: str, status: str, detail: str) -> dict:
    return {"name": name, "required": True, "passed": status == "pass", "status": status, "detail": detail}
