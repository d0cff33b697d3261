#!/usr/bin/env bash
# Create/refresh the Blender-as-a-module venv at <repo>/.venv-blender, used by
# scripts/check_blender.py to render with Cycles.
#
# Why a venv of its own: bpy 5.0.1 (the newest wheel for Python 3.11) needs
# numpy < 2, while the main .venv (scripts/setup-venv.sh) pins numpy 2.
# Size: a 374 MB wheel, ~820 MB installed.
#
# Idempotent: re-installs only when the pinned requirements below changed
# since the last successful install (hash stamp inside the venv).
# Non-interactive; the last line of output is the venv's python path.
set -euo pipefail

SCRIPT_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
REPO="$(cd "$SCRIPT_DIR/.." && pwd)"
VENV="${BLENDER_VENV:-$REPO/.venv-blender}"
STAMP="$VENV/.requirements.sha256"
PY="$VENV/bin/python"

# bpy wheels exist for exactly one Python minor version per Blender release.
REQUIREMENTS='bpy==5.0.1
numpy<2'
NEED_PY="3.11"

export PIP_DISABLE_PIP_VERSION_CHECK=1
export PIP_NO_INPUT=1
export DEBIAN_FRONTEND=noninteractive

pick_python() {
    local c
    for c in "${PYTHON:-}" "python$NEED_PY" python3; do
        [ -n "$c" ] || continue
        command -v "$c" >/dev/null 2>&1 || continue
        if [ "$("$c" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")' 2>/dev/null)" = "$NEED_PY" ]; then
            echo "$c"
            return 0
        fi
    done
    return 1
}

venv_ok() {
    [ -x "$PY" ] && "$PY" -c "import sys; assert sys.version.startswith('$NEED_PY.')" >/dev/null 2>&1 \
        && "$PY" -m pip --version >/dev/null 2>&1
}

if ! venv_ok; then
    BASE_PY="$(pick_python)" || {
        echo "setup-blender-venv: bpy 5.0.1 needs Python $NEED_PY; none found (set PYTHON=...)" >&2
        exit 1
    }
    echo "setup-blender-venv: creating $VENV with $("$BASE_PY" -c 'import sys; print(sys.executable, sys.version.split()[0])')" >&2
    rm -rf "$VENV"
    if ! "$BASE_PY" -m venv "$VENV"; then
        rm -rf "$VENV"
        if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" -eq 0 ]; then
            echo "setup-blender-venv: venv failed; installing python$NEED_PY-venv via apt-get" >&2
            apt-get update -qq >&2 || true
            apt-get install -y -qq "python$NEED_PY-venv" >&2 || apt-get install -y -qq python3-venv >&2
            "$BASE_PY" -m venv "$VENV"
        else
            echo "setup-blender-venv: '$BASE_PY -m venv' failed (install python3-venv)" >&2
            exit 1
        fi
    fi
    venv_ok || { echo "setup-blender-venv: venv at $VENV is unusable" >&2; exit 1; }
    rm -f "$STAMP"
fi

want="$(printf '%s\n' "$REQUIREMENTS" | sha256sum | cut -d' ' -f1)"
have="$(cat "$STAMP" 2>/dev/null || true)"
if [ "$want" != "$have" ]; then
    echo "setup-blender-venv: installing $(echo "$REQUIREMENTS" | tr '\n' ' ')(374 MB download)" >&2
    "$PY" -m pip install --quiet --upgrade pip >&2 \
        || echo "setup-blender-venv: warning: could not upgrade pip (offline?)" >&2
    req="$(mktemp)"
    printf '%s\n' "$REQUIREMENTS" > "$req"
    "$PY" -m pip install --quiet -r "$req" >&2
    rm -f "$req"
    echo "$want" > "$STAMP"
else
    echo "setup-blender-venv: requirements unchanged, skipping install" >&2
fi

# bpy loads a few X11/GL client libraries even headless; on a minimal system
# install them (Debian names) if the import fails for a missing shared object.
if ! err="$("$PY" -c 'import bpy' 2>&1)"; then
    if echo "$err" | grep -q 'cannot open shared object' \
            && command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" -eq 0 ]; then
        echo "setup-blender-venv: import bpy failed ($(echo "$err" | tail -1)); installing X11/GL client libraries" >&2
        apt-get update -qq >&2 || true
        apt-get install -y -qq libxrender1 libxxf86vm1 libxfixes3 libxi6 libxkbcommon0 \
            libsm6 libice6 libx11-6 libxext6 libgl1 libegl1 libglu1-mesa >&2 || true
        err="$("$PY" -c 'import bpy' 2>&1)" || {
            echo "setup-blender-venv: import bpy still fails: $err" >&2; rm -f "$STAMP"; exit 1; }
    else
        echo "setup-blender-venv: import bpy fails: $err" >&2
        rm -f "$STAMP"
        exit 1
    fi
fi

echo "$PY"
