#!/usr/bin/env bash
# Check lightprobe's EXR output with OpenImageIO's command-line tools (external oracle).
#
# Usage: scripts/check_exr_oiio.sh [RENDER_DIR]
#
#   RENDER_DIR   a `lightprobe render-reference` output folder (with render.json).
#                Without it, the bundled scene is rendered into a temp dir first:
#                lightprobe render-reference SCENE --spp $SPP --aov depth,normal,albedo --quiet
#
# For every *.exr: `iinfo -v` must read it with the camera's size (`lightprobe info`) and
# float channels R,G,B,A (beauty) or R,G,B (AOVs); `oiiotool --printstats` averages of
# R,G,B must match lightprobe's mean (render.json views[].mean_rgb for beauty images,
# the Mitsuba-read mean for AOVs) within 1e-5 relative + 1e-7 absolute.
# Details: scripts/check_exr_oiio.py.
#
# Environment: LIGHTPROBE (binary, default target/release/lightprobe),
#   SCENE (sidecar; default scenes/tabletop/tabletop.ron when rendering, else render.json's),
#   SPP (default 16), KEEP=1 keeps the temp render dir.
# Needs iinfo/oiiotool (Debian package openimageio-tools: installed automatically when
# running as root with apt-get, otherwise install it yourself) and the project venv
# (bash scripts/setup-venv.sh).
# Exit status: 0 = pass, 1 = failure.
set -euo pipefail

SCRIPT_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
REPO="$(cd "$SCRIPT_DIR/.." && pwd)"
LIGHTPROBE="${LIGHTPROBE:-$REPO/target/release/lightprobe}"
DEFAULT_SCENE="$REPO/scenes/tabletop/tabletop.ron"
SPP="${SPP:-16}"
PY="$REPO/.venv/bin/python"

die() { echo "check_exr_oiio: ERROR: $*" >&2; echo "RESULT: FAIL (check could not run)"; exit 1; }

case "${1:-}" in
    -h|--help) sed -n '2,/^set -euo/p' "${BASH_SOURCE[0]}" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
esac
[ $# -le 1 ] || die "too many arguments (usage: $0 [RENDER_DIR])"

# ---- OpenImageIO tools
if ! command -v iinfo >/dev/null 2>&1 || ! command -v oiiotool >/dev/null 2>&1; then
    if [ "$(id -u)" -eq 0 ] && command -v apt-get >/dev/null 2>&1; then
        echo "check_exr_oiio: iinfo/oiiotool missing; installing openimageio-tools with apt-get" >&2
        export DEBIAN_FRONTEND=noninteractive
        apt-get update -qq >&2 || echo "check_exr_oiio: warning: apt-get update failed" >&2
        apt-get install -y -qq --no-install-recommends openimageio-tools >&2 \
            || die "apt-get install openimageio-tools failed"
    else
        die "iinfo/oiiotool not found. Install OpenImageIO's tools (Debian/Ubuntu: \
'sudo apt-get install openimageio-tools') or put them on PATH."
    fi
    command -v iinfo >/dev/null 2>&1 && command -v oiiotool >/dev/null 2>&1 \
        || die "openimageio-tools installed but iinfo/oiiotool still not on PATH"
fi

# ---- Python (Mitsuba's EXR reader for the AOV means)
[ -x "$PY" ] || die "no project venv at $REPO/.venv (run: bash scripts/setup-venv.sh)"

wait_for_binary() {
    local i
    for i in $(seq 1 30); do
        [ -x "$LIGHTPROBE" ] && return 0
        [ "$i" -eq 1 ] && echo "check_exr_oiio: waiting up to 30 s for $LIGHTPROBE ..." >&2
        sleep 1
    done
    die "lightprobe binary not found: $LIGHTPROBE (cargo build --release, or set LIGHTPROBE=...)"
}

start=$(date +%s.%N)
tmp=""
cleanup() { if [ -n "$tmp" ] && [ "${KEEP:-0}" != 1 ]; then rm -rf "$tmp"; fi; }
trap cleanup EXIT

scene_args=()
if [ $# -eq 1 ]; then
    RENDER_DIR="$1"
    [ -d "$RENDER_DIR" ] || die "not a directory: $RENDER_DIR"
    [ -n "${SCENE:-}" ] && scene_args=(--scene "$SCENE")
else
    SCENE="${SCENE:-$DEFAULT_SCENE}"
    [ -f "$SCENE" ] || die "scene not found: $SCENE"
    wait_for_binary
    tmp="$(mktemp -d "${TMPDIR:-/tmp}/lp_check_exr_oiio.XXXXXX")"
    RENDER_DIR="$tmp"
    echo "rendering $SCENE at $SPP spp (+ depth, normal, albedo AOVs) into $RENDER_DIR"
    t0=$(date +%s.%N)
    "$LIGHTPROBE" render-reference "$SCENE" --out "$RENDER_DIR" --spp "$SPP" \
        --aov depth,normal,albedo --quiet </dev/null \
        || die "lightprobe render-reference failed (exit $?)"
    echo "rendered in $(awk -v a="$t0" -v b="$(date +%s.%N)" 'BEGIN{printf "%.2f", b-a}') s"
    scene_args=(--scene "$SCENE")
    [ "${KEEP:-0}" = 1 ] && echo "(KEEP=1: render dir kept)"
fi

set +e
"$PY" "$SCRIPT_DIR/check_exr_oiio.py" "$RENDER_DIR" --lightprobe "$LIGHTPROBE" \
    ${scene_args[@]+"${scene_args[@]}"} </dev/null
rc=$?
set -e
echo "check_exr_oiio: total $(awk -v a="$start" -v b="$(date +%s.%N)" 'BEGIN{printf "%.1f", b-a}') s, exit $rc"
exit "$rc"
