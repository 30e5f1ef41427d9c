#!/usr/bin/env bash
# Idempotent set-up of the development environment (run by `make setup`, and
# so by `make demo`, `make test`, `make run`):
#
#   1. .venv: a plain venv of python3.11 with the pinned ROS 2 Jazzy wheels
#      (runtime + the build-time wheels for interfaces) and the pinned Python
#      dependencies (requirements/*.txt, every version in constraints.txt);
#   2. the soft_twin ROS package built by plain CMake in build/soft_twin and
#      installed into the venv prefix: generated soft_twin.msg/soft_twin.srv,
#      the hand-written soft_twin/ modules and soft_twin_core in
#      .venv/lib/python3.11/site-packages, the interface libraries in
#      .venv/lib, the commands soft_twin_node and soft-twin-sim in .venv/bin;
#   2b. tf2_msgs/TFMessage built the same way from interfaces/tf2_msgs when the
#      venv has no tf2_msgs (the ROS wheels on PyPI carry none);
#   3. on every run, a cheap re-install of the Python sources (cmake --install
#      copies changed files only) so code edits reach the venv;
#   4. the numba kernels compiled into their disk cache (soft_twin_core.warmup:
#      tens of seconds after a change of the kernels, about a second otherwise).
#
# Steps 1 and 2 are skipped when the hash of their inputs matches the stamp
# they left: a run with nothing changed takes a few seconds. The venv needs
# no environment variables: the ros-wheels-bootstrapper in it re-executes
# Python with LD_LIBRARY_PATH set.
#
# Environment: PYTHON (interpreter to build the venv from, default python3 or
# python3.11), SOFT_TWIN_VENV (default <repo>/.venv), SOFT_TWIN_BUILD (default
# <repo>/build/soft_twin).
set -euo pipefail

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
VENV=${SOFT_TWIN_VENV:-$ROOT/.venv}
BUILD=${SOFT_TWIN_BUILD:-$ROOT/build/soft_twin}
mkdir -p "$ROOT/build"
LOG=$ROOT/build/setup.log
REQ=$ROOT/requirements
T0=$(date +%s)

say() { echo "[setup] $*" >&2; }
fail() {
    say "FAILED: $*"
    if [ -s "$LOG" ]; then say "last lines of $LOG:"; tail -n 40 "$LOG" >&2; fi
    exit 1
}
# this machine's pip.conf adds file:// indexes that warn on every call: harmless
quiet_pip() { grep -v -e '^WARNING: Location' -e '^WARNING: Skipping' -e '^$' || true; }

# One set-up at a time per checkout (parallel `make` calls share .venv).
exec 9>"$ROOT/build/.setup.lock"
flock 9
: >"$LOG"

# ---- 0. build tools ---------------------------------------------------------
missing=()
for tool in cmake make gcc g++; do
    command -v "$tool" >/dev/null 2>&1 || missing+=("$tool")
done
if [ ${#missing[@]} -gt 0 ]; then
    say "missing build tools: ${missing[*]}"
    command -v apt-get >/dev/null 2>&1 || fail "install ${missing[*]} (cmake, a C/C++ compiler, make)"
    SUDO=""
    [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    say "installing cmake make gcc g++ with apt-get"
    $SUDO env DEBIAN_FRONTEND=noninteractive apt-get update -q >>"$LOG" 2>&1 || fail "apt-get update"
    $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -q cmake make gcc g++ >>"$LOG" 2>&1 \
        || fail "apt-get install cmake make gcc g++"
fi

# ---- 0b. headless Chromium for the browser tests of the live 3D view ----------
# Debian's chromium package (the test drives it over the DevTools protocol).
# Not needed to run the twin; without it those tests fail and say so.
if ! command -v chromium >/dev/null 2>&1 && ! command -v chromium-browser >/dev/null 2>&1; then
    if command -v apt-get >/dev/null 2>&1 && { [ "$(id -u)" -eq 0 ] || command -v sudo >/dev/null 2>&1; }; then
        SUDO=""
        [ "$(id -u)" -eq 0 ] || SUDO="sudo"
        say "installing Debian's chromium with apt-get (headless browser for the live-view tests; once)"
        if ! { $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium >>"$LOG" 2>&1 ||
            { $SUDO env DEBIAN_FRONTEND=noninteractive apt-get update -q >>"$LOG" 2>&1 &&
                $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium >>"$LOG" 2>&1; }; }; then
            say "WARNING: could not install chromium (see $LOG); the browser tests of the live view will fail"
        fi
    else
        say "WARNING: no chromium and no apt-get: install Debian's chromium for the live-view browser tests"
    fi
fi

# ---- 1. venv with pinned wheels ----------------------------------------------
# The ROS 2 Jazzy wheels exist for CPython 3.11 only.
pick_python() {
    local c
    for c in ${PYTHON:-} python3 python3.11; do
        if command -v "$c" >/dev/null 2>&1 &&
            "$c" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
            command -v "$c"
            return 0
        fi
    done
    return 1
}

hash_of() { cat "$@" | sha256sum | cut -c1-64; }

DEPS_FILES=("$REQ/ros.txt" "$REQ/dev.txt" "$REQ/constraints.txt")
DEPS_HASH=$( { hash_of "${DEPS_FILES[@]}"; uname -m; echo "deps-v1"; } | sha256sum | cut -c1-64)
DEPS_STAMP=$VENV/.soft_twin-deps.sha256

venv_ok() { [ -x "$VENV/bin/python" ] && "$VENV/bin/python" -c 'import sys' >/dev/null 2>&1; }

if ! venv_ok || [ "$(cat "$DEPS_STAMP" 2>/dev/null)" != "$DEPS_HASH" ]; then
    if ! venv_ok; then
        PY=$(pick_python) || fail "need CPython 3.11 (the ROS 2 Jazzy wheels are cp311); set PYTHON=/path/to/python3.11"
        say "creating $VENV with $PY ($("$PY" --version 2>&1))"
        rm -rf "$VENV"
        "$PY" -m venv "$VENV" >>"$LOG" 2>&1 || fail "python -m venv"
    fi
    say "installing pinned wheels (ROS 2 Jazzy + Python deps; first time: a few minutes)"
    T=$(date +%s)
    # PIP_CONSTRAINT (not -c) also pins the build backends of sdists (empy).
    PIP_CONSTRAINT="$REQ/constraints.txt" PIP_DISABLE_PIP_VERSION_CHECK=1 \
        "$VENV/bin/python" -m pip install -q -r "$REQ/ros.txt" -r "$REQ/dev.txt" \
        > >(quiet_pip >>"$LOG") 2>&1 || fail "pip install"
    say "  wheels installed in $(($(date +%s) - T)) s"

    # The wheels' exported *__rosidl_generator_py targets carry the wheel
    # builder's include folders (/opt/python/cp311-cp311/...): point them at
    # this Python's and this numpy's headers, or the interfaces do not build.
    "$VENV/bin/python" - "$VENV" >>"$LOG" 2>&1 <<'EOF' || fail "patching the ROS wheels' cmake exports"
import re, sys, sysconfig
from pathlib import Path
import numpy
venv = Path(sys.argv[1])
np_inc = numpy.get_include()
py_inc = sysconfig.get_paths()["include"]
n = 0
for f in (venv / "share").rglob("*.cmake"):
    text = f.read_text()
    if "/opt/python/" not in text:
        continue
    new = re.sub(r"/opt/python/cp3\d+-cp3\d+/lib/python3\.\d+/site-packages/numpy/(_core|core)/include", np_inc, text)
    new = re.sub(r"/opt/python/cp3\d+-cp3\d+/include/python3\.\d+", py_inc, new)
    if new != text:
        f.write_text(new)
        n += 1
print(f"patched {n} cmake files")
EOF
    rm -rf "$BUILD"   # the venv changed under it: configure again
    echo "$DEPS_HASH" >"$DEPS_STAMP"
fi

# ---- 2. build the ROS package (interfaces) into the venv prefix -------------
BUILD_FILES=("$ROOT/CMakeLists.txt" "$ROOT/package.xml" "$ROOT/setup.py"
    "$ROOT"/cmake/* "$ROOT"/msg/* "$ROOT"/srv/* "$ROOT/scripts/setup_env.sh")
BUILD_HASH=$( { echo "$DEPS_HASH"; echo "$VENV"; hash_of "${BUILD_FILES[@]}"; printf '%s\n' "${BUILD_FILES[@]#"$ROOT"/}"; } \
    | sha256sum | cut -c1-64)
BUILD_STAMP=$BUILD/.soft_twin-build.sha256

CMAKE_ENV=(env "PATH=$VENV/bin:$PATH" "CMAKE_PREFIX_PATH=$VENV")
if [ "$(cat "$BUILD_STAMP" 2>/dev/null)" != "$BUILD_HASH" ]; then
    say "building the soft_twin interfaces with cmake (build/soft_twin -> $VENV)"
    T=$(date +%s)
    # a cache from another checkout or venv cannot be reused
    if [ -f "$BUILD/CMakeCache.txt" ] &&
        ! grep -qx "CMAKE_INSTALL_PREFIX:PATH=$VENV" "$BUILD/CMakeCache.txt"; then
        rm -rf "$BUILD"
    fi
    {
        "${CMAKE_ENV[@]}" cmake -S "$ROOT" -B "$BUILD" \
            -DCMAKE_INSTALL_PREFIX="$VENV" \
            -DPython3_EXECUTABLE="$VENV/bin/python3" \
            -DCMAKE_BUILD_TYPE=Release \
            -DBUILD_TESTING=OFF \
            -DSOFT_TWIN_KERNEL_CACHES=OFF &&
            "${CMAKE_ENV[@]}" cmake --build "$BUILD" -j "$(nproc)"
    } >>"$LOG" 2>&1 || fail "cmake build"
    echo "$BUILD_HASH" >"$BUILD_STAMP"
    say "  built in $(($(date +%s) - T)) s"
fi

# ---- 2b. tf2_msgs (the /tf message) when the environment has none -----------
# The ROS 2 Jazzy wheels on PyPI carry no tf2_msgs: build TFMessage from its
# upstream definition (interfaces/tf2_msgs) into the venv prefix, like the
# package's own interfaces. An environment that has tf2_msgs (a ROS 2
# installation's) keeps its own: nothing is built.
TF_SRC=$ROOT/interfaces/tf2_msgs
TF_BUILD=$ROOT/build/tf2_msgs
TF_HASH=$( { echo "$DEPS_HASH"; echo "$VENV"; hash_of "$TF_SRC/CMakeLists.txt" "$TF_SRC/package.xml" "$TF_SRC"/msg/*; } \
    | sha256sum | cut -c1-64)
TF_STAMP=$TF_BUILD/.tf2_msgs-build.sha256
if [ "$(cat "$TF_STAMP" 2>/dev/null)" != "$TF_HASH" ]; then
    if [ ! -f "$TF_STAMP" ] && "$VENV/bin/python" -c 'import tf2_msgs.msg' >/dev/null 2>&1; then
        say "tf2_msgs: using the environment's own package"
    else
        say "building tf2_msgs/TFMessage with cmake (the ROS wheels have no tf2_msgs; build/tf2_msgs -> $VENV)"
        T=$(date +%s)
        if [ -f "$TF_BUILD/CMakeCache.txt" ] &&
            ! grep -qx "CMAKE_INSTALL_PREFIX:PATH=$VENV" "$TF_BUILD/CMakeCache.txt"; then
            rm -rf "$TF_BUILD"
        fi
        {
            "${CMAKE_ENV[@]}" cmake -S "$TF_SRC" -B "$TF_BUILD" \
                -DCMAKE_INSTALL_PREFIX="$VENV" \
                -DPython3_EXECUTABLE="$VENV/bin/python3" \
                -DCMAKE_BUILD_TYPE=Release \
                -DBUILD_TESTING=OFF &&
                "${CMAKE_ENV[@]}" cmake --build "$TF_BUILD" -j "$(nproc)" &&
                "${CMAKE_ENV[@]}" cmake --install "$TF_BUILD"
        } >>"$LOG" 2>&1 || fail "cmake build of tf2_msgs"
        echo "$TF_HASH" >"$TF_STAMP"
        say "  built in $(($(date +%s) - T)) s"
    fi
fi

# ---- 3. (re-)install: copies only what changed, then drops stale modules ----
# (SOFT_TWIN_KERNEL_CACHES=OFF above: the kernels compile once, in step 4, and the installed copy takes
# their caches; a colcon build gives its install space its caches itself)
"${CMAKE_ENV[@]}" cmake --install "$BUILD" >>"$LOG" 2>&1 || fail "cmake --install"
# A module deleted or renamed in the sources must not linger in the venv.
python3 - "$BUILD/install_manifest.txt" "$VENV" >>"$LOG" 2>&1 <<'EOF' || fail "pruning stale modules"
import sys
from pathlib import Path
manifest = set(Path(sys.argv[1]).read_text().split())
site = next(Path(sys.argv[2]).glob("lib/python3*/site-packages"))
for pkg in ("soft_twin", "soft_twin_core"):
    for f in (site / pkg).rglob("*"):
        if f.is_file() and "__pycache__" not in f.parts and str(f) not in manifest:
            print("removing stale", f)
            f.unlink()
EOF

# ---- 4. compile the numba kernels into their disk cache (seconds when cached) ----
# Once (issue 30: compile less): the checkout's kernels compile, and the copy
# installed in the venv -- which the commands import (soft-twin-sim and the
# Dask workers of its studies, soft_twin_node) -- takes their caches: numba
# 0.68 stamps a cache with its source's content hash, so a cache serves an
# identical file anywhere (soft_twin_core.warmup.copy_caches). Its own
# warm-up then loads in seconds; it compiles only what differs. The checkout's
# compile runs its parts in two lanes, one process per core
# (soft_twin_core.warmup.compile_side_by_side: 65 s on 2 cores; 171 s before).
say "kernels: compiling into numba's cache if needed (about a minute on 2 cores after a change of a kernel's sources, seconds otherwise)"
SITE_CORE=$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')/soft_twin_core
"$VENV/bin/python" -m soft_twin_core.warmup >"$LOG.warmup" 2>&1 ||
    { cat "$LOG.warmup" >>"$LOG"; fail "compiling the kernels (python -m soft_twin_core.warmup; its output: $LOG.warmup)"; }
"$VENV/bin/python" -m soft_twin_core.warmup --copy-to "$SITE_CORE" >>"$LOG.warmup" 2>&1 ||
    { cat "$LOG.warmup" >>"$LOG"; fail "copying the kernel caches to $SITE_CORE (its output: $LOG.warmup)"; }
(cd "$VENV" && "$VENV/bin/python" -m soft_twin_core.warmup) >"$LOG.warmup_installed" 2>&1 || {
    cat "$LOG.warmup_installed" >>"$LOG"
    fail "compiling the installed kernels (cd $VENV && python -m soft_twin_core.warmup; its output: $LOG.warmup_installed)"
}
cat "$LOG.warmup" "$LOG.warmup_installed" >>"$LOG"
say "kernels: $(grep 'compiled and cached' "$LOG.warmup" | head -n 1)"
say "kernels: $(tail -n 1 "$LOG.warmup")"
say "installed kernels: $(tail -n 1 "$LOG.warmup_installed")"

say "ready: $VENV ($(($(date +%s) - T0)) s)"
