#!/usr/bin/env bash
# Runs on the GPU machine from a bundle made by ../shared/tools/device-pack (see
# ../shared/docs/DEVICE.md): the GPU test suites, compute-sanitizer on the render
# interop, and the deform and render benchmarks, writing everything into OUT_DIR.
#
#   here:  cmake -S . -B build-gpu -G Ninja -DCMAKE_BUILD_TYPE=Release -DCMAKE_CUDA_ARCHITECTURES=90
#          cmake --build build-gpu
#          ../shared/tools/device-pack build-gpu/palpsim-gpu-tests build-gpu/palpsim-gpu-render-tests \
#            build-gpu/palpsim-gpu-stability-tests \
#            build-gpu/palpsim-bench build-gpu/palpsim-test-render build-gpu/palpsim-test-net-stream
#          git describe --always --dirty > .device/commit   # what the bundle was built from
#   there: bash scripts/gpu-check.sh "$OUT" [quick|elastic]
#
# `elastic` runs the elastic model's checks and figures alone (issue 25: the deform bench's
# elastic rows twice (once with ONCE=1), and with ALT_DEGREES=F,C,L once with those V-cycle degrees; its GPU
# cases and the stability catalogue against the CPU, a traced run, the accuracy report's GPU
# column, the sanitizers on the clipped VOIs); the bundle then needs palpsim-gpu-tests,
# palpsim-gpu-stability-tests and palpsim-bench.
set -uo pipefail
out=${1:?usage: scripts/gpu-check.sh OUT_DIR [quick|elastic]}
quick=${2:-}
mkdir -p "$out"
# every step's whole output, here and appended to the one $out/logs.txt as it ends: the
# device brings back at most 8 files a call, so the logs travel as one file beside the JSON
logs=/tmp/gpu-check-logs
rm -rf "$logs" && mkdir -p "$logs"
tar xzf .device/bundle.tgz -C /tmp && . /tmp/bundle/env.sh || { echo "gpu-check: no bundle in .device/" >&2; exit 2; }
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee "$out/logs.txt"
# the commit the bundle was built from (the GPU machine's copy of .git may be stale)
commit=$(cat .device/commit 2>/dev/null || echo "unknown (no .device/commit)")
echo "commit $commit" | tee -a "$out/logs.txt"

step() {  # name, command...: runs it, keeps its output, prints one status line
  local name=$1; shift
  local t0=$SECONDS
  "$@" > "$logs/$name.txt" 2>&1
  local rc=$?
  local line
  line=$(printf '%-22s rc=%d  %3ds' "$name" "$rc" $((SECONDS - t0)))
  echo "$line"
  { echo "=== $line: $*"; cat "$logs/$name.txt"; } >> "$out/logs.txt"
  return 0
}
# the elastic GPU cases on clipped and small VOIs (every level layout, short enough for the
# sanitizers)
elastic_case="gpu elastic steps equal the cpu's on clipped*"
if [ "$quick" = elastic ]; then
  # the figures first (a run cut short by the device's time limit still brings them back):
  # the elastic rows, and with ALT_DEGREES=F,C,L once more with those V-cycle degrees; then
  # the tests, the rows again (the 16 sessions' figure moves a few % from one run to the
  # next), a traced run (where a step's time goes), the accuracy report's GPU column, and
  # the sanitizers on the clipped VOIs last (the slowest)
  step bench-elastic-1 palpsim-bench deform --elastic --backend cuda --commit "$commit" --json "$out/deform-elastic-1.json"
  if [ -n "${ALT_DEGREES:-}" ]; then
    step bench-elastic-alt palpsim-bench deform --elastic --backend cuda --commit "$commit" \
      --elastic-degrees "$ALT_DEGREES" --json "$out/deform-elastic-alt.json"
  fi
  step gpu-elastic-tests palpsim-gpu-tests "[elastic]"
  # block 0's coarse levels on the small VOIs (by default only a VOI ending on 4^3 nodes has one)
  step gpu-elastic-block0 env PALPSIM_ELASTIC_BLOCK_NODES=1000 palpsim-gpu-tests "$elastic_case"
  step gpu-stability-tests palpsim-gpu-stability-tests
  # (ONCE=1: not again, when the device's time is short)
  [ -z "${ONCE:-}" ] &&
    step bench-elastic-2 palpsim-bench deform --elastic --backend cuda --commit "$commit" --json "$out/deform-elastic-2.json"
  step elastic-trace env PALPSIM_ELASTIC_TRACE=1 palpsim-bench deform --elastic --backend cuda --quick
  step accuracy-elastic palpsim-bench accuracy --elastic --json-only "$out/accuracy-elastic.json" --backend cuda \
    --commit "$commit"
  if command -v compute-sanitizer >/dev/null; then
    step racecheck-elastic compute-sanitizer --tool racecheck --error-exitcode 9 palpsim-gpu-tests "$elastic_case"
    step memcheck-elastic compute-sanitizer --tool memcheck --error-exitcode 9 palpsim-gpu-tests "$elastic_case"
  fi
  for f in "$logs"/*.txt; do
    echo "=== $(basename "$f")"
    grep -E "passed|failed|FAILED|ERROR SUMMARY|RACECHECK SUMMARY|elastic cuda" "$f" | cut -c1-300 | tail -16
  done
  exit 0
fi
step gpu-tests palpsim-gpu-tests
# block 0's coarse levels of the elastic model on the small VOIs (by default only a VOI ending on 4^3 nodes has one)
step gpu-elastic-block0 env PALPSIM_ELASTIC_BLOCK_NODES=1000 palpsim-gpu-tests "$elastic_case"
step gpu-render-tests palpsim-gpu-render-tests
# the stability catalogue's deformation cases on "cuda" (tests/stability/, issue 8 section 5)
command -v palpsim-gpu-stability-tests >/dev/null && step gpu-stability-tests palpsim-gpu-stability-tests
# the render and stream unit tests of CI, here on the NVIDIA driver (the compute-shader ray cast)
command -v palpsim-test-render >/dev/null && step render-tests palpsim-test-render
command -v palpsim-test-net-stream >/dev/null && step net-stream-tests palpsim-test-net-stream
if command -v compute-sanitizer >/dev/null; then
  step memcheck-render compute-sanitizer --tool memcheck --error-exitcode 9 palpsim-gpu-render-tests
  # the elastic kernels (cuda/relax_elastic.cu) on the case of clipped and small VOIs (every
  # level layout, short under the sanitizer): reads and writes out of bounds, and races on
  # shared memory
  step memcheck-elastic compute-sanitizer --tool memcheck --error-exitcode 9 palpsim-gpu-tests "$elastic_case"
  step racecheck-elastic compute-sanitizer --tool racecheck --error-exitcode 9 palpsim-gpu-tests "$elastic_case"
fi
if [ -z "$quick" ]; then
  step bench-render palpsim-bench render --scene config/scenes/lumbar_phantom.textproto --rounds 5 --json "$out/render.json"
  step bench-deform palpsim-bench deform --json "$out/deform.json"
  # the elastic rows again with two blocks a multiprocessor, and with coarse levels of up
  # to 64 nodes (not 512) in block 0 alone: which launch shape the step should keep
  step bench-elastic-bps2 env PALPSIM_ELASTIC_BLOCKS_PER_SM=2 palpsim-bench deform --elastic --backend cuda --quick
  step bench-elastic-bn64 env PALPSIM_ELASTIC_BLOCK_NODES=64 palpsim-bench deform --elastic --backend cuda --quick
  # the elastic study's GPU column for bench/results/accuracy.md (--elastic-gpu-json)
  step accuracy-elastic palpsim-bench accuracy --elastic --json-only "$out/accuracy-elastic.json" --backend cuda \
    --commit "$commit"
fi
# the tail of each: what passed, what the benchmarks measured
for f in "$logs"/*.txt; do
  echo "=== $(basename "$f")"
  grep -E "passed|failed|FAILED|ERROR SUMMARY|RACECHECK SUMMARY|render\+encode|server,|frames/s|skipped|median" "$f" | tail -25
done
