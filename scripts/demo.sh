#!/usr/bin/env bash
# Sets up (Debian packages, CMake and Python packages, build) and runs the main job
# on the built-in phantom: prepares the patient and writes its preview into out/demo/,
# then palpates along the lumbar spine and shows the force profile (out/demo/palpation/).
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
. "$root/scripts/setup.sh"
build_dir=${PALPSIM_BUILD_DIR:-$root/build}
out=${PALPSIM_DEMO_OUT:-$root/out/demo}

echo "[demo] preparing the phantom patient (scene config/scenes/lumbar_phantom.textproto)"
"$build_dir/palpsim-prep" phantom --scene "$root/config/scenes/lumbar_phantom.textproto" --out "$out/patient"
echo "[demo] patient volumes, preview.png and prep.json are in $out/patient"

# the palpation: palpsim-demo starts palpsim-server on the same scene, presses a line of
# points along the lumbar spine, compares the force peaks with the bone mask's process
# tips, stops the server, and writes spine_profile.png and the batch outputs
echo "[demo] palpating along the lumbar spine (palpsim-server + palpsim-demo)"
"$root/.venv/bin/python" -m palpsim.demo --server "$build_dir/palpsim-server" \
  --scene "$root/config/scenes/lumbar_phantom.textproto" --patient "$out/patient" \
  --out "$out/palpation"

# what the deformation did meanwhile (the scene asks for ChainMail, relaxation and
# inversion; the server steps them on each session's newest contact, beside the poses)
if grep -q "deformation (" "$out/palpation/server.log" 2>/dev/null; then
  echo "[demo] deformation, per session (from $out/palpation/server.log):"
  grep -o "session [0-9a-f]* closed after .*" "$out/palpation/server.log" | sed 's/^/  /'
fi
