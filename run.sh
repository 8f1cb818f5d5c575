#!/usr/bin/env bash
# Set up (once) and run mitsuba-active from a clone.
#
#   ./run.sh plan [OPTIONS]    plan views on the bundled scene (or pass a scene), results in ./runs/
#   ./run.sh test [PYTEST...]  run the test suite (installs Chromium, for the reports' browser tests)
#   ./run.sh setup             only install: LLVM >= 19 (Debian's libllvm19), a virtualenv in .venv, the package
#   ./run.sh <command> ...     any other mitsuba-active command (scene, render, export, bench, ...)
#
# Needs python3 (>= 3.11). Installs missing system packages with apt-get (as root, or through sudo).
# Commands run from the folder you call this script from; the virtualenv lives in the clone.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")" && pwd)
VENV=${MITSUBA_ACTIVE_VENV:-$ROOT/.venv}

say() { echo "run.sh: $*" >&2; }

as_root() {
    if [ "$(id -u)" = 0 ]; then "$@"
    elif command -v sudo >/dev/null 2>&1; then sudo "$@"
    else return 1
    fi
}

apt_install() {  # apt_install WHAT-FOR PACKAGE...
    local why=$1; shift
    if ! command -v apt-get >/dev/null 2>&1; then
        say "missing $why: install $* with your package manager"; exit 1
    fi
    say "installing $* (apt-get) for $why"
    as_root apt-get update -qq >/dev/null &&
        as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null ||
        { say "could not install $* (needs root or sudo): ask an administrator to run 'apt-get install $*'"; exit 1; }
}

have_llvm() {  # an LLVM shared library of version >= 19, where Dr.Jit looks for one
    local f v
    for f in /usr/lib/x86_64-linux-gnu/libLLVM*.so* /usr/lib/aarch64-linux-gnu/libLLVM*.so* \
             /usr/lib/llvm-*/lib/libLLVM*.so* /usr/lib64/libLLVM*.so* /usr/local/lib/libLLVM*.so*; do
        [ -e "$f" ] || continue
        v=$(basename "$f" | grep -oE '[0-9]+' | head -n1)
        [ -n "$v" ] && [ "$v" -ge 19 ] && return 0
    done
    [ -n "${DRJIT_LIBLLVM_PATH:-}" ] && [ -e "$DRJIT_LIBLLVM_PATH" ]
}

have_chromium() {
    command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1 ||
        command -v google-chrome >/dev/null 2>&1 || command -v google-chrome-stable >/dev/null 2>&1
}

setup() {
    have_llvm || apt_install "LLVM >= 19 for Dr.Jit (or set DRJIT_LIBLLVM_PATH)" libllvm19
    command -v python3 >/dev/null 2>&1 || apt_install "Python 3" python3 python3-venv
    if [ ! -x "$VENV/bin/python" ]; then
        local fresh=0
        [ -e "$VENV" ] || fresh=1
        if ! python3 -m venv "$VENV" >/dev/null 2>&1; then
            [ "$fresh" = 1 ] && rm -rf "$VENV"  # only what this script just created
            apt_install "Python's venv module" python3-venv
            python3 -m venv "$VENV"
        fi
    fi
    # Reinstall only when the package metadata changed.
    local stamp="$VENV/.mitsuba-active-installed" want
    want=$(sha256sum "$ROOT/pyproject.toml" | cut -d' ' -f1)
    if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
        say "installing mitsuba-active and its dependencies into $VENV"
        "$VENV/bin/python" -m pip install -q --upgrade pip >/dev/null
        "$VENV/bin/python" -m pip install -q -e "$ROOT[test]"
        echo "$want" > "$stamp"
    fi
}

cmd=${1:-plan}
[ $# -gt 0 ] && shift
setup
case "$cmd" in
    setup) say "ready: $VENV/bin/mitsuba-active" ;;
    test)  # The reports' browser tests open their pages in headless Chromium; without one they are skipped.
           have_chromium || ( apt_install "the reports' browser tests" chromium ) || say "browser tests will be skipped"
           cd "$ROOT" && exec "$VENV/bin/python" -m pytest -q "$@" ;;
    *)     exec "$VENV/bin/mitsuba-active" "$cmd" "$@" ;;
esac
