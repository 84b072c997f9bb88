#!/usr/bin/env bash
# Build tb-pico-plant: Mbed TLS 3.6, zenoh-pico (with TLS) and the device, each cached under OUT_DIR
# by the hash of its sources. The last line printed is the binary's path.
#
#   bash devices/pico-plant/build.sh OUT_DIR
#
# Sources: the tarballs in ../shared/vendor/ (relative to the project root; TESTBED_VENDOR names another
# folder), or unpacked upstream
# releases named by MBEDTLS_SRC (an Mbed TLS 3.6 tree) and ZENOH_PICO_SRC (a zenoh-pico 1.9 tree).
# Needs cmake, make, a C compiler (cc or gcc) and pkg-config; nothing is installed, nothing is
# written outside OUT_DIR.
set -euo pipefail

if [ $# -ne 1 ] || [ -z "$1" ]; then
    echo "usage: bash devices/pico-plant/build.sh OUT_DIR" >&2
    exit 2
fi
HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
ROOT=$(cd "$HERE/../.." && pwd)
# the vendored tarballs: ../shared/vendor of the project root (a git worktree one level deeper: ../../shared/vendor)
VENDOR="${TESTBED_VENDOR:-$ROOT/../shared/vendor}"
if [ -z "${TESTBED_VENDOR:-}" ] && [ ! -d "$VENDOR" ] && [ -d "$ROOT/../../shared/vendor" ]; then
    VENDOR="$ROOT/../../shared/vendor"
fi
mkdir -p "$1"
OUT=$(cd "$1" && pwd)
JOBS=${JOBS:-2}

for tool in cmake make pkg-config sha256sum tar; do
    command -v "$tool" >/dev/null 2>&1 || { echo "build.sh: $tool not found (Debian: apt-get install cmake make pkg-config)" >&2; exit 1; }
done
CC=${CC:-$(command -v cc || command -v gcc || true)}
[ -n "$CC" ] || { echo "build.sh: no C compiler (Debian: apt-get install gcc)" >&2; exit 1; }
export CC

# one build at a time per OUT_DIR (tests may run in parallel)
exec 9>"$OUT/.lock"
if command -v flock >/dev/null 2>&1; then flock 9; fi

hash_of() { # a file, or a folder's files (paths and contents)
    if [ -d "$1" ]; then
        (cd "$1" && find . -type f ! -path './.git/*' -print0 | LC_ALL=C sort -z | xargs -0 sha256sum) | sha256sum | cut -c1-16
    else
        sha256sum "$1" | cut -c1-16
    fi
}

# $1 name, $2 folder variable's value, $3 tarball; sets SRC_KIND/SRC_PATH/SRC_HASH
source_of() {
    if [ -n "$2" ]; then
        [ -d "$2" ] || { echo "build.sh: $1 source folder $2 does not exist" >&2; exit 1; }
        SRC_PATH=$(cd "$2" && pwd)
        SRC_KIND=dir
    else
        [ -f "$3" ] || { echo "build.sh: $3 not found: give the sources' folder in ${1^^}_SRC" >&2; exit 1; }
        SRC_PATH=$3
        SRC_KIND=tar
    fi
    SRC_HASH=$(hash_of "$SRC_PATH")
}

# unpack or copy a source into $2 (its top folder's contents)
materialise() {
    mkdir -p "$2"
    if [ "$SRC_KIND" = tar ]; then
        tar -xzf "$1" -C "$2" --strip-components=1
    else
        cp -a "$1/." "$2/"
    fi
    chmod -R u+w "$2"
}

T_START=$(date +%s)

# ---- Mbed TLS (static libraries; the library Makefile, no CMake needed)
source_of mbedtls "${MBEDTLS_SRC:-}" "$VENDOR/mbedtls-3.6.6.tar.gz"
MBED="$OUT/mbedtls-$SRC_HASH"
if [ ! -f "$MBED/.done" ]; then
    echo "build.sh: building Mbed TLS ($SRC_PATH) in $MBED" >&2
    rm -rf "$MBED" "$MBED.tmp"
    materialise "$SRC_PATH" "$MBED.tmp"
    make -C "$MBED.tmp/library" -j"$JOBS" libmbedcrypto.a libmbedx509.a libmbedtls.a >"$OUT/mbedtls.log" 2>&1 \
        || { tail -20 "$OUT/mbedtls.log" >&2; echo "build.sh: the Mbed TLS build failed (log: $OUT/mbedtls.log)" >&2; exit 1; }
    mv "$MBED.tmp" "$MBED"
    touch "$MBED/.done"
fi

# ---- zenoh-pico with TLS, against that Mbed TLS (its CMake finds Mbed TLS with pkg-config)
source_of zenoh_pico "${ZENOH_PICO_SRC:-}" "$VENDOR/zenoh-pico-1.9.0.tar.gz"
ZP_HASH=$(printf '%s %s' "$SRC_HASH" "$(basename "$MBED")" | sha256sum | cut -c1-16)
ZP="$OUT/zenoh-pico-$ZP_HASH"
if [ ! -f "$ZP/.done" ]; then
    echo "build.sh: building zenoh-pico ($SRC_PATH) in $ZP" >&2
    rm -rf "$ZP" "$ZP.tmp"
    materialise "$SRC_PATH" "$ZP.tmp/src"
    mkdir -p "$ZP.tmp/pkgconfig"
    for lib in mbedtls mbedx509 mbedcrypto; do
        printf 'Name: %s\nDescription: %s\nVersion: 3.6\nLibs: -L%s/library -l%s\nCflags: -I%s/include\n' \
            "$lib" "$lib" "$MBED" "$lib" "$MBED" >"$ZP.tmp/pkgconfig/$lib.pc"
    done
    PKG_CONFIG_PATH="$ZP.tmp/pkgconfig" cmake -S "$ZP.tmp/src" -B "$ZP.tmp/build" -DZ_FEATURE_LINK_TLS=1 \
        -DBUILD_SHARED_LIBS=OFF -DBUILD_TESTING=OFF -DBUILD_EXAMPLES=OFF -DBUILD_TOOLS=OFF -DCMAKE_BUILD_TYPE=Release \
        >"$OUT/zenoh-pico.log" 2>&1 \
        && cmake --build "$ZP.tmp/build" -j"$JOBS" >>"$OUT/zenoh-pico.log" 2>&1 \
        || { tail -20 "$OUT/zenoh-pico.log" >&2; echo "build.sh: the zenoh-pico build failed (log: $OUT/zenoh-pico.log)" >&2; exit 1; }
    # keep what the device needs: headers (the source's and the generated config) and the library
    mkdir -p "$ZP.tmp/include" "$ZP.tmp/lib"
    cp -a "$ZP.tmp/src/include/." "$ZP.tmp/include/"
    cp -a "$ZP.tmp/build/include/." "$ZP.tmp/include/"
    cp "$ZP.tmp/build/lib/libzenohpico.a" "$ZP.tmp/lib/"
    cp "$ZP.tmp/src/LICENSE" "$ZP.tmp/LICENSE" 2>/dev/null || true
    rm -rf "$ZP.tmp/src" "$ZP.tmp/build"
    mv "$ZP.tmp" "$ZP"
    touch "$ZP/.done"
fi

# ---- the device (C99)
DEV_HASH=$( (cat "$HERE"/src/*.c "$HERE"/src/*.h "$HERE/build.sh"; echo "$(basename "$ZP") $(basename "$MBED") $CC") \
    | sha256sum | cut -c1-16)
BIN="$OUT/tb-pico-plant-$DEV_HASH"
if [ ! -x "$BIN" ]; then
    echo "build.sh: building the device in $BIN" >&2
    COMPILER=GCC
    if "$CC" --version 2>/dev/null | grep -qi clang; then COMPILER=CLANG; fi
    "$CC" -std=c99 -O2 -Wall -Wextra -DZENOH_C_STANDARD=99 -DZENOH_LINUX -DZENOH_COMPILER_$COMPILER \
        -I"$ZP/include" -I"$MBED/include" "$HERE"/src/*.c -o "$BIN.tmp" \
        "$ZP/lib/libzenohpico.a" "$MBED/library/libmbedtls.a" "$MBED/library/libmbedx509.a" \
        "$MBED/library/libmbedcrypto.a" -lpthread -lm
    mv "$BIN.tmp" "$BIN"
fi
ln -sfn "$(basename "$BIN")" "$OUT/tb-pico-plant.tmp"
mv -T "$OUT/tb-pico-plant.tmp" "$OUT/tb-pico-plant"
echo "build.sh: done in $(( $(date +%s) - T_START )) s" >&2
echo "$OUT/tb-pico-plant"
