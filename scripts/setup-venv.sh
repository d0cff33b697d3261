#!/usr/bin/env bash
# Create/refresh the project's Python venv at <repo>/.venv.
# Idempotent: re-installs requirements only when scripts/requirements.txt
# changed since the last successful install (hash stamp inside .venv).
# Non-interactive; last line of output is the venv's python path.
set -euo pipefail

SCRIPT_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
REPO="$(cd "$SCRIPT_DIR/.." && pwd)"
VENV="$REPO/.venv"
REQ="$SCRIPT_DIR/requirements.txt"
STAMP="$VENV/.requirements.sha256"
PY="$VENV/bin/python"
BASE_PY="${PYTHON:-python3}"

export PIP_DISABLE_PIP_VERSION_CHECK=1
export PIP_NO_INPUT=1
export DEBIAN_FRONTEND=noninteractive

venv_ok() {
    [ -x "$PY" ] && "$PY" -c 'import sys' >/dev/null 2>&1 \
        && "$PY" -m pip --version >/dev/null 2>&1
}

make_venv() {
    rm -rf "$VENV"
    "$BASE_PY" -m venv "$VENV"
}

if ! venv_ok; then
    echo "setup-venv: creating $VENV with $("$BASE_PY" -c 'import sys; print(sys.executable, sys.version.split()[0])')" >&2
    if ! make_venv; then
        # Debian's python3 ships venv/ensurepip separately (python3-venv).
        rm -rf "$VENV"
        if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" -eq 0 ]; then
            echo "setup-venv: python3 -m venv failed; installing python3-venv via apt-get" >&2
            ver="$("$BASE_PY" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')"
            apt-get update -qq >&2 || true
            apt-get install -y -qq python3-venv "python${ver}-venv" >&2 \
                || apt-get install -y -qq python3-venv >&2
            make_venv
        else
            echo "setup-venv: '$BASE_PY -m venv' failed (install python3-venv)" >&2
            exit 1
        fi
    fi
    venv_ok || { echo "setup-venv: venv at $VENV is unusable" >&2; exit 1; }
    rm -f "$STAMP"
fi

"$PY" -m pip install --quiet --upgrade pip >&2 \
    || echo "setup-venv: warning: could not upgrade pip (offline?)" >&2

want="$(sha256sum "$REQ" | cut -d' ' -f1)"
have="$(cat "$STAMP" 2>/dev/null || true)"
if [ "$want" != "$have" ]; then
    echo "setup-venv: installing $REQ" >&2
    "$PY" -m pip install --quiet -r "$REQ" >&2
    echo "$want" > "$STAMP"
else
    echo "setup-venv: requirements unchanged, skipping install" >&2
fi

echo "$PY"
