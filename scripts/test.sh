#!/usr/bin/env bash
# Sets up (Debian packages, CMake and Python packages, build) and runs every test
# that runs without a GPU: the C++ suites through CTest (label gpu excluded: those
# run on the GPU machine, see docs/gpu-tests.md), the Python package's tests, and the
# fuzzers for a bounded time (scripts/fuzz.sh; PALPSIM_FUZZ_SECONDS each, default 30).
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
. "$root/scripts/setup.sh"
build_dir=${PALPSIM_BUILD_DIR:-$root/build}

echo "[test] C++ tests (ctest -LE gpu)"
(cd "$build_dir" && ctest -LE gpu --output-on-failure -j "$(nproc)" --timeout 900)

if [ -d "$root/clients/python/tests" ]; then
  echo "[test] Python tests (pytest)"
  PALPSIM_BUILD_DIR="$build_dir" "$root/.venv/bin/python" -m pytest -q "$root/clients/python/tests"
fi

echo "[test] fuzzers (scripts/fuzz.sh)"
bash "$root/scripts/fuzz.sh" --seconds "${PALPSIM_FUZZ_SECONDS:-30}"
