"""The join file: everything a node from outside needs to join one run (``TESTBED_JOIN``).

``testbed run SCENARIO --external ROLE`` (and ``testbed conformance``) writes it, 0600, into
the run's folder and removes it at the end of the run; the node reads the path from the
environment variable ``TESTBED_JOIN``.  One JSON object; every field is listed in ``FIELDS``
(docs/protocol.md's table is generated from it).  It holds secrets (a password, or the paths of a
private key), so a reader refuses a file that others can read.
"""

from __future__ import annotations

import json
import os
import stat
from dataclasses import dataclass
from pathlib import Path

from . import transport
from .messages import PROTOCOL_VERSION

ENV = "TESTBED_JOIN"
#: the join file's own format version (a field added that a reader must use bumps it)
JOIN_VERSION = 1
MAX_BYTES = 1 << 20

#: every field of the join file: (name, JSON type, meaning); docs/protocol.md's table is made from it
FIELDS = (
    ("join_version", "integer", f"this file's format version ({JOIN_VERSION})"),
    ("protocol", "integer", "the wire protocol's version of the run (`Start.protocol`)"),
    ("role", "string", "the role the external node plays: plant, encoder, attacker or controller"),
    ("run_id", "string", "the run's id; every key is under `key_prefix`"),
    ("key_prefix", "string", "`testbed/<run_id>`: the prefix of every key of the run (Key expressions)"),
    ("ack_key", "string", "the key (after the prefix) that carries theta_k to the encoder: `loop/actuation`, "
                          "`loop/ack/tx` or `loop/ack/rx`"),
    ("topology", "string", "`peer` (mutual TLS, every process a Zenoh peer) or `router` (the launcher routes)"),
    ("mode", "string", "the Zenoh mode the node's session must use: `peer` or `client`"),
    ("connect", "array of strings", "Zenoh endpoints to connect to (the launcher's)"),
    ("listen", "array of strings", "Zenoh endpoints to listen on (the peer topology: the node's own listener, "
                                   "port 0 for any; empty in the router topology)"),
    ("low_latency", "boolean", "Zenoh's low-latency transport: the node's session must use it too"),
    ("credentials", "object", "how the node authenticates: `kind` `mutual_tls` with the paths `ca`, `cert`, `key` "
                              "(PEM; the certificate's common name is the role); `user_password` with `user`, "
                              "`password` and `secret_file` (a 0600 file of that one `user:password` line); "
                              "`none` (an --insecure run)"),
    ("T_ns", "integer", "the sampling period T in ns (`Start.T_ns` must say the same)"),
    ("n_steps", "integer", "N, the samples of the run (`Start.n_steps`)"),
    ("timing", "string", "`ideal` or `physical` (`Start.timing`)"),
    ("ack_via_attacker", "boolean", "`Start.ack_via_attacker`"),
    ("digest", "string", "the run's digest (`Start.digest`), for a node that computes it as the bundled ones do"),
    ("t0_ns", "null", "the start time is not known yet when the file is written: t0 comes in `Start` "
                      "(a plant picks it: now + `start_lead_ns` once every `ready/*` token is there)"),
    ("start_lead_ns", "integer", "an external plant: t0 = now + this, once the others are ready"),
    ("wait_ready", "array of strings", "bare names, not keys (`[\"plant\", \"encoder\", \"attacker\", "
                                       "\"controller\", \"collector\"]`): a plant waits for the liveliness token "
                                       "`<key_prefix>/ready/<name>` of each before it publishes Start"),
    ("ready_timeout_s", "number", "how long the run waits for the node to join (`--startup-timeout`)"),
    ("run_options", "object", "the run's options over the scenario (the flags of `testbed node`: duration, T, "
                              "timing, ..., ack_via_attacker, separate_ack); null: the scenario's value"),
    ("scenario", "object", "the scenario itself: `name`, `toml` (its text, as the run read it) and `base_dir` "
                           "(the folder its relative paths are relative to, or null for a bundled one); the "
                           "role's parameters (plant model, quantizer, K, attack, deadlines) are in it"),
)
NAMES = tuple(f[0] for f in FIELDS)
CREDENTIAL_KINDS = {"mutual_tls": ("kind", "ca", "cert", "key"),
                    "user_password": ("kind", "user", "password", "secret_file"), "none": ("kind",)}


def _bad(path, why: str):
    from ..common.errors import BadInput

    return BadInput(f"join file {path}: {why}")


@dataclass(frozen=True)
class JoinFile:
    """A read and checked join file (``read``); ``data`` is the JSON object, every field of ``FIELDS``."""

    path: Path
    data: dict

    def __getattr__(self, name):
        if name in NAMES:
            return self.data[name]
        raise AttributeError(name)


def write(path: str | Path, data: dict) -> Path:
    """Write ``data`` (exactly the fields of ``FIELDS``) to a new 0600 file ``path`` (never overwrites)."""
    if tuple(sorted(data)) != tuple(sorted(NAMES)):
        raise ValueError(f"join file fields {sorted(set(data) ^ set(NAMES))}")
    p = Path(path)
    fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        json.dump(data, f, indent=1)
        f.write("\n")
    return p


def remove(path: str | Path | None) -> None:
    if path is not None:
        try:
            os.unlink(path)
        except FileNotFoundError:
            pass


def _check(p, d) -> None:
    def need(name, types, what):
        v = d[name]
        if not isinstance(v, types) or (isinstance(v, bool) and bool not in (types if isinstance(types, tuple)
                                                                             else (types,))):
            raise _bad(p, f"{name}: expected {what}, got {json.dumps(v)[:60]}")
        return v

    if need("join_version", int, "an integer") != JOIN_VERSION:
        raise _bad(p, f"join_version {d['join_version']}: this node reads version {JOIN_VERSION}")
    if need("protocol", int, "an integer") != PROTOCOL_VERSION:
        raise _bad(p, f"the run speaks protocol version {d['protocol']}, this node speaks {PROTOCOL_VERSION}")
    if need("role", str, "a role") not in transport.ROLES:
        raise _bad(p, f"role {d['role']!r}: not one of {', '.join(transport.ROLES)}")
    try:
        keys = transport.Keys.for_run(need("run_id", str, "a string"))
    except ValueError as e:
        raise _bad(p, str(e)) from None
    if need("key_prefix", str, "a string") != keys.prefix:
        raise _bad(p, f"key_prefix {d['key_prefix']!r} is not {keys.prefix!r}")
    need("ack_key", str, "a string")
    if need("topology", str, "a string") not in transport.TOPOLOGIES:
        raise _bad(p, f"topology {d['topology']!r}: not one of {', '.join(transport.TOPOLOGIES)}")
    if need("mode", str, "a string") not in ("peer", "client"):
        raise _bad(p, f"mode {d['mode']!r}: not peer or client")
    for name in ("connect", "listen", "wait_ready"):
        if not all(isinstance(e, str) for e in need(name, list, "a list of strings")):
            raise _bad(p, f"{name}: expected a list of strings")
    need("low_latency", bool, "true or false")
    need("ack_via_attacker", bool, "true or false")
    cred = need("credentials", dict, "an object")
    kind = cred.get("kind")
    if kind not in CREDENTIAL_KINDS:
        raise _bad(p, f"credentials.kind {kind!r}: not one of {', '.join(CREDENTIAL_KINDS)}")
    if set(cred) != set(CREDENTIAL_KINDS[kind]) or not all(isinstance(v, str) for v in cred.values()):
        raise _bad(p, f"credentials of kind {kind}: expected the strings {', '.join(CREDENTIAL_KINDS[kind])}")
    if need("T_ns", int, "an integer") <= 0 or need("n_steps", int, "an integer") <= 0:
        raise _bad(p, "T_ns and n_steps must be positive")
    if need("timing", str, "a string") not in ("ideal", "physical"):
        raise _bad(p, f"timing {d['timing']!r}: not ideal or physical")
    need("digest", str, "a string")
    if d["t0_ns"] is not None:
        need("t0_ns", int, "an integer or null")
    need("start_lead_ns", int, "an integer")
    need("ready_timeout_s", (int, float), "a number")
    need("run_options", dict, "an object")
    sc = need("scenario", dict, "an object")
    if set(sc) != {"name", "toml", "base_dir"} or not isinstance(sc.get("toml"), str) \
            or not isinstance(sc.get("name"), str) or not isinstance(sc.get("base_dir"), str | None):
        raise _bad(p, "scenario: expected name, toml (strings) and base_dir (a string or null)")


def read(path: str | Path | None = None) -> JoinFile:
    """Read and check the join file ``path`` (default: ``$TESTBED_JOIN``); ``BadInput`` names what is wrong."""
    if path is None:
        path = os.environ.get(ENV)
        if not path:
            from ..common.errors import BadInput

            raise BadInput(f"no SCENARIO and no {ENV}: give a scenario, or the join file of a run in {ENV} "
                           "(testbed run SCENARIO --external ROLE writes one)")
    p = Path(path)
    try:
        st = p.stat()
    except OSError as e:
        raise _bad(p, e.strerror or str(e)) from None
    if not stat.S_ISREG(st.st_mode):
        raise _bad(p, "not a regular file")
    if st.st_mode & 0o077:
        raise _bad(p, f"readable by others (mode {stat.S_IMODE(st.st_mode):o}): it holds the run's credentials")
    if st.st_size > MAX_BYTES:
        raise _bad(p, f"{st.st_size} bytes is not a join file")
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise _bad(p, f"not a JSON join file: {e}") from None
    if not isinstance(d, dict):
        raise _bad(p, "not a JSON object")
    missing, unknown = sorted(set(NAMES) - set(d)), sorted(set(d) - set(NAMES))
    if missing or unknown:
        raise _bad(p, (f"missing {', '.join(missing)}" if missing else "")
                   + ("; " if missing and unknown else "") + (f"unknown {', '.join(unknown)}" if unknown else ""))
    _check(p, d)
    return JoinFile(p, d)
