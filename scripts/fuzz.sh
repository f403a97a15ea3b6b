#!/usr/bin/env bash
# Builds the libFuzzer targets (tests/fuzz) in a clang build tree of their own, build-fuzz/
# (every library they reach compiled with ASan, UBSan and libFuzzer's coverage; ccache
# keeps rebuilds short), and runs each on its corpus for a bounded time. scripts/test.sh
# runs it for 30 s a target; for longer, ask for more:
#
#   bash scripts/fuzz.sh                      # each target 30 s
#   bash scripts/fuzz.sh --seconds 3600       # each target an hour
#   bash scripts/fuzz.sh --target wire --seconds 0   # one target until stopped (Ctrl-C)
#
# Targets: ct-header (check_ct_header: NIfTI, NRRD/NHDR, MetaImage), scene (the scene text
# parser), wire (control and pose messages through an in-process server). The seed corpus
# in tests/fuzz/corpus/<target> is read, never written; what the fuzzers add goes to
# build-fuzz/corpus/<target>. A crash, a hang or a broken invariant stops the target, leaves
# its input in build-fuzz/artifacts/<target>/ and fails the script naming it; once fixed,
# copy the input into tests/fuzz/corpus/<target>/regression-<what> so every run replays it.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
seconds=30
targets=(ct-header scene wire)
while [ $# -gt 0 ]; do
  case "$1" in
    --seconds) seconds=$2; shift 2 ;;
    --target) targets=("$2"); shift 2 ;;
    -h|--help) sed -n '2,20p' "$0"; exit 0 ;;
    *) echo "fuzz.sh: unknown argument '$1' (--seconds S, --target ct-header|scene|wire)" >&2; exit 2 ;;
  esac
done

# Debian packages (clang-14, libfuzzer-14-dev among them), the venv's CMake, the main build
. "$root/scripts/setup.sh"
fuzz_dir=${PALPSIM_FUZZ_BUILD_DIR:-$root/build-fuzz}
say() { printf '[fuzz] %s\n' "$*"; }

export CCACHE_BASEDIR="$root"
if [ ! -f "$fuzz_dir/build.ninja" ]; then
  say "configuring $fuzz_dir (clang-14, ASan + UBSan + libFuzzer)"
  mkdir -p "$fuzz_dir"
  "$root/.venv/bin/cmake" -S "$root" -B "$fuzz_dir" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DPALPSIM_FUZZ=ON \
    -DPALPSIM_CUDA=OFF -DCMAKE_C_COMPILER=clang-14 -DCMAKE_CXX_COMPILER=clang++-14 \
    -DCMAKE_C_COMPILER_LAUNCHER=ccache -DCMAKE_CXX_COMPILER_LAUNCHER=ccache \
    -DPython3_EXECUTABLE="$root/.venv/bin/python" > "$fuzz_dir/configure.log" 2>&1 ||
    { cat "$fuzz_dir/configure.log" >&2; exit 1; }
fi
say "building ${targets[*]}"
"$root/.venv/bin/cmake" --build "$fuzz_dir" -j "$(nproc)" --target "${targets[@]/#/palpsim-fuzz-}"

failed=()
for t in "${targets[@]}"; do
  seeds=$root/tests/fuzz/corpus/${t//-/_}
  corpus=$fuzz_dir/corpus/$t
  artifacts=$fuzz_dir/artifacts/$t
  log=$fuzz_dir/logs/$t.log
  mkdir -p "$corpus" "$artifacts" "$(dirname "$log")"
  say "$t: $seconds s on $seeds (+ $corpus); log $log"
  # leaks are checked at exit only: the wire target's server threads allocate between inputs
  extra=()
  [ "$t" = wire ] && extra=(-detect_leaks=0)
  if "$fuzz_dir/palpsim-fuzz-$t" "$corpus" "$seeds" -max_total_time="$seconds" -timeout=60 -rss_limit_mb=4096 \
      -artifact_prefix="$artifacts/" -print_final_stats=1 "${extra[@]}" > "$log" 2>&1; then
    grep -E '^stat::number_of_executed_units|^stat::peak_rss_mb|^#[0-9]+.*DONE' "$log" | sed "s/^/[fuzz] $t: /" || true
  else
    grep -E 'ERROR: |SUMMARY: |fuzz_wire: |Test unit written to' "$log" | sed "s/^/[fuzz] $t: /" >&2 || tail -20 "$log" >&2
    failed+=("$t")
  fi
done
if [ ${#failed[@]} -gt 0 ]; then
  say "FAILED: ${failed[*]} (inputs in $fuzz_dir/artifacts/, logs in $fuzz_dir/logs/)"
  exit 1
fi
say "no crash in ${targets[*]}"
