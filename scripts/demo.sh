#!/usr/bin/env bash
# Sets up (Debian packages, CMake and Python packages, build) and runs the main job
# on the built-in phantom: prepares the patient and writes its preview into out/demo/,
# then palpates along the lumbar spine and shows the force profile, and records a press
# over the L3 spinous process as the server renders it: an MP4 and a contact sheet of
# the frames (out/demo/palpation/).
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
# tips and writes spine_profile.png and the batch outputs; then, on the same server
# (the scene asks for frames, bone preset, 1280x720), it watches a session of its own and
# presses over L3 in 3 mm steps to 15 mm and back, keeping one rendered frame a step
# (press.mp4, press_contact_sheet.png, press.json; about 25 s on a 2-core CPU, where
# Mesa llvmpipe renders a frame in about a second), and stops the server
echo "[demo] palpating along the lumbar spine and recording a press over L3 (palpsim-server + palpsim-demo)"
"$root/.venv/bin/python" -m palpsim.demo --server "$build_dir/palpsim-server" \
  --scene "$root/config/scenes/lumbar_phantom.textproto" --patient "$out/patient" \
  --out "$out/palpation"

# what the deformation did meanwhile (the scene asks for ChainMail, relaxation and
# inversion; the server steps them on each session's newest contact, beside the poses)
if grep -q "deformation (" "$out/palpation/server.log" 2>/dev/null; then
  echo "[demo] deformation, per session (from $out/palpation/server.log):"
  grep -o "session [0-9a-f]* closed after .*" "$out/palpation/server.log" | sed 's/^/  /'
fi
if [ -f "$out/palpation/press.mp4" ]; then
  echo "[demo] the recorded press: $out/palpation/press.mp4 and $out/palpation/press_contact_sheet.png"
fi
