#!/usr/bin/env bash
# Copies executables and the shared libraries they link into a runtime folder for the
# images' last stage (docker/*.Dockerfile): DEST/bin gets the executables, DEST/lib every
# library ldd resolves for them (glvnd's EGL and OpenGL loader included), except those the
# runtime image has of its own: glibc, libstdc++ and libgcc_s (in debian:12 itself), and the
# EGL and GL vendors' libraries: Mesa's (installed from Debian in the CPU image) and the
# NVIDIA driver's (mounted by the NVIDIA container runtime).
#
#   docker/collect-libs.sh DEST BIN...
set -euo pipefail
[ $# -ge 2 ] || { echo "collect-libs: usage: collect-libs.sh DEST BIN..." >&2; exit 2; }
dest=$1; shift
mkdir -p "$dest/bin" "$dest/lib"
skip='^(libc|libm|libpthread|libdl|librt|libutil|libresolv|ld-linux-x86-64|libstdc\+\+|libgcc_s|libEGL_(mesa|nvidia)|libGLX_(mesa|nvidia)|libcuda|libnvidia-.*)\.so'
for bin in "$@"; do
  [ -x "$bin" ] || { echo "collect-libs: $bin is not an executable" >&2; exit 2; }
  cp -L "$bin" "$dest/bin/"
  # a library ldd cannot find would fail at run time: refuse here, naming it
  if ldd "$bin" | grep -q 'not found'; then
    echo "collect-libs: $bin needs libraries that are not found:" >&2
    ldd "$bin" | grep 'not found' >&2
    exit 1
  fi
  ldd "$bin" | awk '/=> \//{print $1, $3}' | while read -r soname path; do
    [[ "$soname" =~ $skip ]] && continue
    [ -e "$dest/lib/$soname" ] || cp -L "$path" "$dest/lib/$soname"
  done
done
echo "collect-libs: $# executables, $(ls "$dest/lib" | wc -l) libraries, $(du -sh "$dest" | cut -f1) in $dest"
