#!/usr/bin/env bash
# Fuzzes lightprobe's input parsers with libFuzzer (cargo fuzz, nightly toolchain):
#   sidecar  any bytes -> the RON sidecar parser
#   gltf     any bytes -> the glTF/GLB loader (geometry, materials, cameras)
#   envmap   any bytes -> the envmap.ron parser, then a lat-long export
#   exr      any bytes -> the EXR reader (header checks, then decoding)
#   reference  any bytes as a view's reference EXR -> reference loading and pixel checks
# Usage: scripts/fuzz.sh [SECONDS_PER_TARGET] [TARGET...]   (default 60 s, all targets)
# Crashes are left in fuzz/artifacts/<target>/; the summary prints executions and crashes,
# and the script exits 1 when a target crashed or its run failed (this run's files only).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
secs="${1:-60}"; shift || true
targets=("$@"); [ ${#targets[@]} -gt 0 ] || targets=(sidecar gltf envmap exr reference)
rustup toolchain list | grep -q nightly || rustup toolchain install nightly --profile minimal
command -v cargo-fuzz >/dev/null 2>&1 || cargo install cargo-fuzz --locked
export RUSTFLAGS=""   # the sanitizer build sets its own flags
summary=()
failed=0
started=$(mktemp); trap 'rm -f "$started"' EXIT
for t in "${targets[@]}"; do
  corpus="fuzz/corpus/$t"; mkdir -p "$corpus" "fuzz/artifacts/$t"
  cp -n fuzz/seeds/"$t"/* "$corpus"/ 2>/dev/null || true
  log="fuzz/artifacts/$t/last-run.log"
  set +e
  cargo +nightly fuzz run "$t" "$corpus" -- -max_total_time="$secs" -rss_limit_mb=2048 -timeout=10 2>&1 | tee "$log" | grep -E "^#[0-9]+ +(DONE|pulse)|ERROR|panicked" | tail -3
  status=${PIPESTATUS[0]}
  set -e
  execs=$(grep -oE "^#[0-9]+" "$log" | tail -1 | tr -d '#')
  crashes=$(find "fuzz/artifacts/$t" -newer "$started" \( -name 'crash-*' -o -name 'oom-*' -o -name 'timeout-*' \) | wc -l)
  summary+=("$t: ${execs:-0} executions in ${secs} s, exit $status, new crash/oom/timeout files: $crashes")
  if [ "$status" -ne 0 ] || [ "$crashes" -gt 0 ]; then failed=1; fi
done
printf '\n== fuzz summary ==\n'; printf '%s\n' "${summary[@]}"
if [ "$failed" -ne 0 ]; then
  echo "fuzz: a target crashed or failed (inputs in fuzz/artifacts/<target>/)" >&2
  exit 1
fi
