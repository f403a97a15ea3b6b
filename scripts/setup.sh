#!/usr/bin/env bash
# Installs what palpsim needs on Debian 12 and builds it. Sourced by scripts/demo.sh
# and scripts/test.sh; safe to run again (each step checks whether it is done).
#
# Environment knobs:
#   PALPSIM_BUILD_DIR   build folder (default: build)
#   PALPSIM_BUILD_TYPE  CMake build type (default: Release)
#   PALPSIM_CUDA        ON/OFF to force the CUDA backend on or off (default: ON when nvcc is found)
set -euo pipefail

root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
build_dir=${PALPSIM_BUILD_DIR:-$root/build}
build_type=${PALPSIM_BUILD_TYPE:-Release}
venv=$root/.venv

say() { printf '[setup] %s\n' "$*"; }

# debian packages: compilers, ITK (with GDCM), ZeroMQ, protobuf, Catch2, spdlog, EGL and
# OpenGL (Mesa's llvmpipe renders where there is no GPU), libjpeg-turbo, zstd; clang and
# libFuzzer for the fuzzers (scripts/fuzz.sh); chromium and its driver for palpsim-web's
# browser test (clients/python/tests/test_web.py); Tk for palpsim-view's live window
# (matplotlib's TkAgg: python3-tk gives Debian's python3, hence the .venv made from it
# below, its _tkinter), and Xvfb with xdotool for the window's test (test_view.py)
debs=(build-essential ninja-build ccache git pkg-config python3 python3-venv python3-dev clang-14 libfuzzer-14-dev
      libinsighttoolkit5-dev libgdcm-dev libzmq3-dev cppzmq-dev libprotobuf-dev protobuf-compiler
      catch2 libspdlog-dev libpng-dev libjpeg-dev libturbojpeg0-dev libzstd-dev zlib1g-dev
      libegl-dev libgl-dev libopengl-dev libegl1-mesa libgl1-mesa-dri chromium chromium-driver
      python3-tk xvfb xdotool)
missing=()
for p in "${debs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'install ok installed' || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  say "installing Debian packages: ${missing[*]}"
  if [ "$(id -u)" -ne 0 ]; then
    echo "[setup] error: these Debian packages are missing and installing them needs root: ${missing[*]}" >&2
    exit 1
  fi
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq --no-install-recommends "${missing[@]}"
else
  say "Debian packages present"
fi

# python virtual environment: CMake from PyPI (Debian's 3.25 cannot find CUDA 13),
# the protobuf runtime that matches Debian's protoc 3.21, and the batch runner's needs
reqs=$root/scripts/requirements.txt
stamp=$venv/.palpsim-reqs
if [ ! -x "$venv/bin/python" ]; then
  say "creating $venv"
  /usr/bin/python3 -m venv "$venv"
fi
want=$(cat "$reqs" $(ls "$root/clients/python/pyproject.toml" 2>/dev/null) | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  say "installing Python packages into $venv"
  "$venv/bin/python" -m pip install -q --upgrade pip
  "$venv/bin/python" -m pip install -q -r "$reqs"
  echo "$want" > "$stamp"
  py_changed=1  # reinstall the palpsim package below (its pyproject.toml may have changed)
else
  say "Python packages present"
fi
export PATH="$venv/bin:$PATH"

# nvJPEG (the GPU JPEG encoder of frames) for a CUDA build: Debian's CUDA toolkit has
# no nvjpeg, so its header and library come from NVIDIA's PyPI wheel, pinned to the
# toolkit's major version (CMake finds it under .venv, cuda/CMakeLists.txt)
nvjpeg_whl=nvidia-nvjpeg==13.0.2.28
if [ "${PALPSIM_CUDA:-}" != "OFF" ] && { command -v nvcc >/dev/null || [ -x /usr/local/cuda/bin/nvcc ]; }; then
  if ! ls "$venv"/lib/python3*/site-packages/nvidia/cu13/include/nvjpeg.h >/dev/null 2>&1; then
    say "installing $nvjpeg_whl into $venv (nvJPEG for the CUDA build)"
    "$venv/bin/python" -m pip install -q "$nvjpeg_whl"
  fi
fi

# configure (once, or when CMakeLists change is picked up by ninja itself) and build
cuda_flag=()
if [ -n "${PALPSIM_CUDA:-}" ]; then
  cuda_flag=(-DPALPSIM_CUDA="$PALPSIM_CUDA")
fi
if [ -x /usr/local/cuda/bin/nvcc ] && ! command -v nvcc >/dev/null; then
  export PATH="$PATH:/usr/local/cuda/bin"
fi
# ccache keyed on paths relative to the checkout, so fresh clones (CI) reuse earlier builds
export CCACHE_BASEDIR="$root"
export CCACHE_MAXSIZE=${CCACHE_MAXSIZE:-5G}
if [ ! -f "$build_dir/build.ninja" ]; then
  say "configuring $build_dir ($build_type)"
  "$venv/bin/cmake" -S "$root" -B "$build_dir" -G Ninja -DCMAKE_BUILD_TYPE="$build_type" \
    -DCMAKE_C_COMPILER_LAUNCHER=ccache -DCMAKE_CXX_COMPILER_LAUNCHER=ccache \
    -DCMAKE_CUDA_COMPILER_LAUNCHER=ccache -DPython3_EXECUTABLE="$venv/bin/python" "${cuda_flag[@]}"
fi
say "building"
"$venv/bin/cmake" --build "$build_dir" -j "$(nproc)"

# the python package, with the generated protobuf code from the build
if [ -n "${py_changed:-}" ] || [ ! -x "$venv/bin/palpsim-demo" ] ||
   ! "$venv/bin/python" -c 'import palpsim' 2>/dev/null; then
  say "installing the palpsim Python package"
  "$venv/bin/python" -m pip install -q -e "$root/clients/python"
fi
