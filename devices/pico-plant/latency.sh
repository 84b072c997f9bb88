#!/usr/bin/env bash
# The latency a device costs against the Python plant: the paper's example run twice in the router
# topology over mutual TLS, once with the C device as the plant and once with the bundled Python plant
# (`testbed node plant`), both joined from outside through the join file; prints each run's timing
# (sampling jitter, sensor-to-actuator and its stages, from `testbed run --json`).
#
#   bash devices/pico-plant/latency.sh DEVICE TLS_DIR [testbed run options ...]
#
# DEVICE: the binary build.sh printed; TLS_DIR: from `testbed secret --tls TLS_DIR`.
set -euo pipefail
[ $# -ge 2 ] || { echo "usage: bash devices/pico-plant/latency.sh DEVICE TLS_DIR [testbed run options ...]" >&2; exit 2; }
DEVICE=$1 TLS=$2
shift 2
TESTBED=${TESTBED:-testbed}
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT

one() { # $1 label, $2... the plant's command
    local label=$1
    shift
    $TESTBED run paper --topology router --tls-dir "$TLS" --external plant --json --no-record "${EXTRA[@]}" \
        >"$WORK/$label.json" 2>"$WORK/$label.err" &
    local run=$!
    local join=""
    for _ in $(seq 600); do
        join=$(sed -n 's/^testbed run: join file for the external plant: //p' "$WORK/$label.err")
        [ -n "$join" ] && break
        kill -0 $run 2>/dev/null || break
        sleep 0.5
    done
    [ -n "$join" ] || { cat "$WORK/$label.err" >&2; exit 1; }
    TESTBED_JOIN=$join "$@" >"$WORK/$label.node.log" 2>&1 || true
    wait $run || true
    python3 - "$label" "$WORK/$label.json" <<'PY'
import json, sys
label, path = sys.argv[1], sys.argv[2]
s = json.load(open(path))
tm = s["timing"]
def f(p):
    return "n/a" if not p or p.get("p50") is None else f"p50 {p['p50']:.0f} us, p99 {p['p99']:.0f} us, max {p['max']:.0f} us"
print(f"{label}: outcome {s['outcome']}, converged {s['converged']}, deadline misses {tm.get('deadline_misses')}")
print(f"  sampling jitter     {f(tm.get('sampling_jitter_us'))}")
print(f"  sensor-to-actuator  {f(tm.get('sensor_to_actuator_us'))}")
for stage, p in (tm.get("stages_us") or {}).items():
    print(f"    {stage:<17} {f(p)}")
PY
}
EXTRA=("$@")
one device "$DEVICE"
one python "$TESTBED" node plant
