"""How the tests fail closed: the one rerun policy of the live tests, and the capability helper.

**Reruns.**  A live run whose nodes were starved of CPU for tens of milliseconds (a shared
2-core machine) turns that sample into a loss, and the loop then rightly leaves the simulator's
path.  The run says so itself (``stalled``).  ``rerun_while_stalled`` runs such a run again, up
to ``STALL_RERUNS`` times, and hands back the LAST run, which the test then compares whatever it
reports: five stalled runs in a row fail as any mismatch does, and a change that makes every
run stall fails too.  No test turns a comparison into a skip.

In a test whose subject is an attacker (``attacker=True``) the stall criterion leaves out what an
attacker can cause: late and superseded symbols, and messages from the future.  Otherwise a
partial break-in (a forged symbol that reaches the controller after its sample was decided)
would read as a stall and be run again until a run without it came along.

A rerun runs the nodes under SCHED_FIFO (``rerun_flags``: ``--realtime``) where the machine
permits it: the first run always tests the default, and a rerun no longer waits for a quiet minute
of a machine whose other processes starve the nodes (a clean-clone CI run stalled five runs of one
test in a row, each missing the plant's deadline for a dropped sample by a few milliseconds).

**Capabilities.**  A test that needs something of the machine (SCHED_FIFO, network namespaces,
npm, ...) calls ``require(capability, reason)`` when it is missing: the test is skipped with the
reason, unless the capability is named in ``TESTBED_REQUIRE`` (comma-separated; ``all``: every
one), where it fails with the reason.  CI (``.ci/run``) requires every capability, so a machine
that lacks one cannot turn CI green; on a user's machine the README's test command skips with
the reason.  ``tests/repo/test_failclosed.py`` fails when a test calls ``pytest.skip`` (or
``importorskip``, ``skipif``) anywhere but here.
"""

from __future__ import annotations

import os
import warnings

import pytest

from testbed.nodes.process import fifo_permitted
from testbed.record.degraded import ATTACKER_CAUSED, timing_faults

#: every capability a test may require, and what it is
CAPABILITIES = {
    "fifo": "SCHED_FIFO for the node processes (root or CAP_SYS_NICE)",
    "netns": "network namespaces joined by veth links (root, iproute2)",
    "npm": "npm and node, and npm install of @mcap/core, protobufjs, fzstd (the Foxglove decoding test)",
    "rerun": "the rerun CLI next to this Python (rerun-sdk)",
    "port9876": "the Rerun viewer's port 9876 free on loopback (the --rerun spawn test)",
    "foxglove": "foxglove-sdk (pip install '.[foxglove]')",
    "dask": "dask.distributed (pip install '.[dask]')",
    "mount": "mount a small tmpfs (root): the recording that fills its disk",
    "zenoh-pico": "cmake, make, pkg-config and a C compiler, and the Mbed TLS 3.6 and zenoh-pico 1.9 sources "
                  "(../shared/vendor, or MBEDTLS_SRC and ZENOH_PICO_SRC): the C plant device (devices/pico-plant)",
}

REQUIRE_ENV = "TESTBED_REQUIRE"


def required() -> set[str]:
    """The capabilities ``TESTBED_REQUIRE`` names (``all``: every one); an unknown name is a usage error."""
    names = {c.strip() for c in os.environ.get(REQUIRE_ENV, "").split(",") if c.strip()}
    if "all" in names:
        return set(CAPABILITIES)
    unknown = names - set(CAPABILITIES)
    if unknown:
        raise pytest.UsageError(f"{REQUIRE_ENV}: unknown capabilities {sorted(unknown)} "
                                f"(known: {', '.join(CAPABILITIES)}, all)")
    return names


def require(capability: str, reason: str) -> None:
    """``capability`` is missing here (``reason``): fail if it is required, else skip with the reason."""
    __tracebackhide__ = True  # the skip or failure is reported at the test's line
    if capability not in CAPABILITIES:
        raise ValueError(f"unknown capability {capability!r}")
    if capability in required():
        pytest.fail(f"required capability {capability!r} ({CAPABILITIES[capability]}) is missing: {reason} "
                    f"[{REQUIRE_ENV}={os.environ.get(REQUIRE_ENV)}]", pytrace=False)
    pytest.skip(f"{reason} [capability {capability!r}; {REQUIRE_ENV}={capability} makes this a failure]")


def import_or_require(module: str, capability: str):
    """``import module``, or ``require(capability, ...)`` when it cannot be imported."""
    __tracebackhide__ = True
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as e:
        require(capability, f"cannot import {module}: {e}")


# ---------------------------------------------------------------------------------------------- reruns
#: how often a stalled run is run again: on these shared 2-core machines a busy hour stalled three
#: runs in a row of one test (clean-clone CI runs; the physical-timing loop's u_k late for its
#: instant).  The last run is compared whatever it reports.
STALL_RERUNS = 4


def stalled(summary: dict, *, attacker: bool = False) -> dict | None:
    """The timing faults a run reports about itself (a machine that stalled a node), or None.

    The product's own criterion (``testbed.record.degraded.timing_faults``, the run's ``timing_degraded``):
    deadline misses, overruns, sensor samples that reached the encoder out of order, (physical
    timing, scheduled actuation) a u_k that arrived after its instant, (ideal ack) an ack that
    missed the encoder's grace window, which only a stall of about one sampling period can cause
    (less what a ``[network]`` channel model lost on purpose: u_k on the actuation link, acks);
    and, unless ``attacker``: late symbols, symbols superseded by a later one, and genuine messages
    a node took for ones from the future (its run clock read during a stall at the start); a node the launcher found stalled.
    """
    tm = summary.get("timing", {})
    stall = {k: v for k, v in timing_faults(summary).items() if not (attacker and k in ATTACKER_CAUSED)}
    if not any(stall.values()):
        return None
    stall = {k: v for k, v in stall.items() if v}
    stall["missed_at"] = summary.get("deadline_missed_at")
    stall["withheld_at"] = summary.get("withheld_at")
    stall["sampling_jitter_max_us"] = (tm.get("sampling_jitter_us") or {}).get("max")
    return stall


def rerun_flags(attempt: int, args=()) -> tuple[str, ...]:
    """What attempt ``attempt`` of a live run adds to its ``testbed run`` command: nothing for the first
    run; for a rerun, ``--realtime`` where SCHED_FIFO is permitted (and not asked for already)."""
    if attempt and "--realtime" not in args and fifo_permitted():
        return ("--realtime",)
    return ()


def rerun_while_stalled(run, what: str, *, attacker: bool = False, reruns: int = STALL_RERUNS):
    """``run(attempt)`` -> ``(rc, summary, stderr)`` for attempt 0, 1, ...: the first run, run again while
    it reports a stall (``stalled``), at most ``reruns`` times.  Returns the last run, for the caller to
    compare whatever it reports (never to skip)."""
    res = run(0)
    for attempt in range(1, reruns + 1):
        stall = stalled(res[1], attacker=attacker)
        if not stall:
            break
        warnings.warn(f"{what}: the run reports {stall} (machine stalled); rerun {attempt} of {reruns}", stacklevel=2)
        res = run(attempt)
    return res
