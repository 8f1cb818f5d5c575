#!/usr/bin/env bash
# Set up (once) and run mitsuba-active from a clone.
#
#   ./run.sh plan [OPTIONS]    plan views on the bundled scene (or pass a scene), results in ./runs/
#   ./run.sh test [PYTEST...]  run the test suite
#   ./run.sh setup             only install: LLVM >= 19 (Debian's libllvm19), a virtualenv in .venv, the package
#   ./run.sh <command> ...     any other mitsuba-active command (scene, render, export, bench, ...)
#
# Needs python3 (>= 3.10). Installs missing system packages with apt-get (as root, or through sudo).
set -euo pipefail
cd "$(dirname "$0")"
ROOT=$PWD
VENV=${MITSUBA_ACTIVE_VENV:-$ROOT/.venv}

say() { echo "run.sh: $*" >&2; }

as_root() {
    if [ "$(id -u)" = 0 ]; then "$@"
    elif command -v sudo >/dev/null 2>&1; then sudo "$@"
    else say "need root to run: $*"; exit 1
    fi
}

apt_install() {
    command -v apt-get >/dev/null 2>&1 || { say "cannot install $* without apt-get; install it with your package manager"; exit 1; }
    say "installing $* (apt-get)"
    as_root apt-get update -qq >/dev/null
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null
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

setup() {
    have_llvm || apt_install libllvm19
    command -v python3 >/dev/null 2>&1 || apt_install python3 python3-venv
    if [ ! -x "$VENV/bin/python" ]; then
        python3 -m venv "$VENV" 2>/dev/null || { rm -rf "$VENV"; apt_install python3-venv; python3 -m venv "$VENV"; }
    fi
    # Reinstall only when the package metadata changed.
    local stamp="$VENV/.mitsuba-active-installed" want
    want=$(cat pyproject.toml | sha256sum | cut -d' ' -f1)
    if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
        say "installing mitsuba-active and its dependencies into $VENV"
        "$VENV/bin/python" -m pip install -q --upgrade pip >/dev/null
        "$VENV/bin/python" -m pip install -q -e ".[test]"
        echo "$want" > "$stamp"
    fi
}

cmd=${1:-plan}
[ $# -gt 0 ] && shift
setup
case "$cmd" in
    setup) say "ready: $VENV/bin/mitsuba-active" ;;
    test)  exec "$VENV/bin/python" -m pytest -q "$@" ;;
    *)     exec "$VENV/bin/mitsuba-active" "$cmd" "$@" ;;
esac
