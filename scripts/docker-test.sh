#!/usr/bin/env bash
# Builds palpsim's container images and palpates from one container to another over a
# container network with CURVE keys (docs/containers.md). Not part of scripts/test.sh:
# it needs root, Docker's engine and a quarter of an hour of builds.
#
#   bash scripts/docker-test.sh [--no-gpu-build] [--keep]
#
# 1. Docker's engine from Debian (docker.io) where dockerd is missing, dockerd started
#    where none answers; debian:12 made with debootstrap and `docker import` where none
#    can be pulled.
# 2. The images palpsim-server:cpu (docker/server.Dockerfile, VARIANT=cpu) and
#    palpsim-clients (docker/clients.Dockerfile), then palpsim-server:gpu, which is only
#    built here (running it needs an NVIDIA GPU; --no-gpu-build skips it).
# 3. Keys by palpsim-keys (server, station1 on the allow-list, intruder not on it), a
#    network, a server container with the keys mounted, and a client container that
#    presses with palpsim-haptic, runs a small palpsim-batch plan, watches two frames with
#    palpsim-view and asks the server's stats, then is refused with the intruder's key.
# 4. Checks: every pose answered, force in the body, the batch's presses in contact, frames
#    received, the server's stats count station1's connections admitted and the
#    intruder's refused.
# 5. The browser station: palpsim-web in a clients container on the network, beyond its
#    loopback (TLS with a self-signed certificate, a station token), published on the
#    host's loopback; the host's headless chromium logs in, sees a frame, clicks the back,
#    and sees the frames change while the depth moves (screenshots, pose to frame).
# 6. Slicer's stand-in: palpsim-igtl in a clients container on the host's network (it
#    serves OpenIGTLink on loopback), and a pyigtl client on the host that receives the
#    IMAGE and TRANSFORMs. Containers and the network are removed at exit (--keep keeps them).
#
# Writes out/docker-test/: summary.txt (date, commit, image sizes, build times, the result),
# logs/ (dockerd, each build, server, client, gateway, browser, bridge), client/ (the
# clients' outputs) and web-1-first-frame.png, web-2-pressed.png (the browser's screenshots).
# Steps 5 and 6 need the host's .venv (scripts/setup.sh: selenium, pyigtl, palpsim) and
# Debian's chromium and chromium-driver.
# Environment: PALPSIM_DOCKER_JOBS (compile jobs in the builds; default all cores),
# PALPSIM_DEBIAN_MIRROR (for debootstrap; default http://deb.debian.org/debian).
# Safe to run again: images and the build cache are reused, leftovers of an earlier run removed.
set -Eeuo pipefail

root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
out=$root/out/docker-test
logs=$out/logs
gpu_build=1
keep=0
for a in "$@"; do
  case "$a" in
    --no-gpu-build) gpu_build=0 ;;
    --keep) keep=1 ;;
    -h|--help) sed -n '2,36p' "$0"; exit 0 ;;
    *) echo "docker-test: unknown argument '$a' (expected --no-gpu-build, --keep)" >&2; exit 2 ;;
  esac
done

net=palpsim-dtest
server_ctr=palpsim-dtest-server
client_ctr=palpsim-dtest-client
web_ctr=palpsim-dtest-web
igtl_ctr=palpsim-dtest-igtl
mkdir -p "$logs"
summary=$out/summary.txt
: > "$summary"

say() { printf '[docker-test] %s\n' "$*"; }
# a line for the summary as well as the screen
note() { say "$*"; printf '%s\n' "$*" >> "$summary"; }
# stops with what failed and where its log is
die() {
  printf '[docker-test] FAILED: %s\n' "$1" >&2
  if [ -n "${2:-}" ]; then
    printf '[docker-test] log: %s (last lines below)\n' "$2" >&2
    tail -n 25 "$2" 2>/dev/null | sed 's/^/    /' >&2
  fi
  printf 'FAILED: %s%s\n' "$1" "${2:+ (log: $2)}" >> "$summary"
  exit 1
}
# any other failing command (once: not again in the subshell of a $(...) it failed in)
trap 'rc=$?; if [ "$BASH_SUBSHELL" -eq 0 ]; then die "line $LINENO of scripts/docker-test.sh: $BASH_COMMAND (exit $rc)"; fi' ERR

[ "$(id -u)" -eq 0 ] || die "needs root: it installs Docker's engine and starts dockerd (run it as root)"

# ---- 1. the engine, the daemon, the base image
export DEBIAN_FRONTEND=noninteractive
apt_updated=0
apt_install() {
  [ $apt_updated -eq 1 ] || { apt-get update -qq >> "$logs/apt.log" 2>&1 || die "apt-get update" "$logs/apt.log"; apt_updated=1; }
  say "installing $* from Debian"
  apt-get install -y -qq --no-install-recommends "$@" >> "$logs/apt.log" 2>&1 || die "apt-get install $*" "$logs/apt.log"
}
command -v dockerd >/dev/null || apt_install docker.io
command -v iptables >/dev/null || apt_install iptables
command -v openssl >/dev/null || apt_install openssl

# the host's side of steps 5 and 6: the project's venv drives chromium and speaks OpenIGTLink
py=$root/.venv/bin/python
"$py" -c 'import selenium, pyigtl, palpsim.web' > "$logs/host-python.log" 2>&1 ||
  die "the host's $py cannot import selenium, pyigtl and palpsim.web (run scripts/setup.sh)" "$logs/host-python.log"

# a docker CLI that builds with BuildKit (the Dockerfiles use cache mounts): one with the
# buildx plugin, or a CLI older than 23 (Debian's docker.io 20.10), whose BuildKit is built in
export DOCKER_BUILDKIT=1
docker_cli=
for c in docker /usr/bin/docker; do
  command -v "$c" >/dev/null || continue
  if "$c" buildx version >/dev/null 2>&1; then docker_cli=$c; break; fi
  v=$("$c" version --format '{{.Client.Version}}' 2>/dev/null || true)
  if [ -n "$v" ] && [ "${v%%.*}" -lt 23 ] 2>/dev/null; then docker_cli=$c; break; fi
done
[ -n "$docker_cli" ] || die "no docker CLI that builds with BuildKit: install the buildx plugin or Debian's docker.io (its 20.10 CLI has BuildKit built in)"
dk() { "$docker_cli" "$@"; }

# the daemon: started here where none answers, with the MTU of the default route's link
# (a bridge at 1500 over a smaller link stalls large downloads in the builds)
if ! dk info >/dev/null 2>&1; then
  mtu_flag=()
  dev=$(ip -o route show default 2>/dev/null | awk '{print $5; exit}')
  if [ -n "$dev" ] && [ -r "/sys/class/net/$dev/mtu" ] && [ "$(cat "/sys/class/net/$dev/mtu")" -lt 1500 ]; then
    mtu_flag=(--mtu "$(cat "/sys/class/net/$dev/mtu")")
  fi
  say "starting dockerd ${mtu_flag[*]} (log: $logs/dockerd.log)"
  setsid nohup dockerd "${mtu_flag[@]}" >> "$logs/dockerd.log" 2>&1 < /dev/null &
  dockerd_pid=$!
  for _ in $(seq 60); do dk info >/dev/null 2>&1 && break; sleep 1; done
  dk info >/dev/null 2>&1 || die "dockerd (pid $dockerd_pid) did not answer within 60 s" "$logs/dockerd.log"
  say "dockerd runs as pid $dockerd_pid and keeps running after this script (stop it with: kill $dockerd_pid)"
fi

# debian:12: pulled where a registry answers, else made from Debian's mirror
if ! dk image inspect debian:12 >/dev/null 2>&1; then
  if timeout 60 "$docker_cli" pull debian:12 >> "$logs/base.log" 2>&1; then
    say "pulled debian:12"
  else
    mirror=${PALPSIM_DEBIAN_MIRROR:-http://deb.debian.org/debian}
    command -v debootstrap >/dev/null || apt_install debootstrap
    rootfs=$(mktemp -d /tmp/palpsim-debian12.XXXXXX)
    say "no registry for debian:12: debootstrap bookworm from $mirror (log: $logs/base.log)"
    debootstrap --variant=minbase bookworm "$rootfs" "$mirror" >> "$logs/base.log" 2>&1 ||
      { rm -rf "$rootfs"; die "debootstrap of bookworm from $mirror" "$logs/base.log"; }
    # the apt sources of a debian:12 image (updates and security too), no package cache
    printf 'deb %s bookworm main\ndeb %s bookworm-updates main\ndeb %s-security bookworm-security main\n' \
      "$mirror" "$mirror" "$mirror" > "$rootfs/etc/apt/sources.list"
    rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/*
    tar -C "$rootfs" -c . | "$docker_cli" import -m "debootstrap --variant=minbase bookworm $mirror" \
      --change 'CMD ["bash"]' --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
      - debian:12 >> "$logs/base.log" 2>&1 || { rm -rf "$rootfs"; die "docker import of debian:12" "$logs/base.log"; }
    rm -rf "$rootfs"
  fi
fi

commit=$(git -C "$root" rev-parse --short HEAD 2>/dev/null || echo unknown)
[ -z "$(git -C "$root" status --porcelain 2>/dev/null)" ] || commit="$commit+changes"
note "palpsim docker-test, $(date -u '+%Y-%m-%d %H:%M UTC'), commit $commit, on $(nproc) cores"
note "docker: client $(dk version --format '{{.Client.Version}}'), engine $(dk version --format '{{.Server.Version}}')"

# ---- 2. the images
# CAs added to this machine (a TLS-inspecting proxy's) are handed to the build stages' pip
extra_ca=$(cat /usr/local/share/ca-certificates/*.crt 2>/dev/null || true)
jobs=${PALPSIM_DOCKER_JOBS:-$(nproc)}
# builds TAG DOCKERFILE [BUILD-ARG...]: its time and size into the summary
build() {
  local tag=$1 file=$2; shift 2
  local log=$logs/build-${tag//[:\/]/-}.log args=() t0
  for a in "$@"; do args+=(--build-arg "$a"); done
  say "building $tag from $file (log: $log)"
  t0=$(date +%s)
  dk build --progress=plain -f "$root/$file" -t "$tag" --build-arg JOBS="$jobs" \
    --build-arg EXTRA_CA_CERTS="$extra_ca" "${args[@]}" "$root" > "$log" 2>&1 ||
    die "building image $tag from $file" "$log"
  local size
  size=$(dk image inspect -f '{{.Size}}' "$tag")
  note "image $tag: $(( size / 1000000 )) MB, built in $(( $(date +%s) - t0 )) s"
}
build palpsim-server:cpu docker/server.Dockerfile VARIANT=cpu
build palpsim-clients docker/clients.Dockerfile

# ---- 3. keys, network, server, client
# removes this script's containers and network (leftovers of an earlier run too)
cleanup() {
  dk rm -f "$client_ctr" "$web_ctr" "$igtl_ctr" "$server_ctr" >/dev/null 2>&1 || true
  dk network rm "$net" >/dev/null 2>&1 || true
}
cleanup
if [ $keep -eq 0 ]; then trap cleanup EXIT; fi

keys=$out/keys
client_out=$out/client
rm -rf "$keys" "$client_out"
mkdir -p "$keys" "$client_out"
for who in server station1 intruder; do
  dk run --rm -v "$keys:/keys" palpsim-clients palpsim-keys "$who" --dir /keys >> "$logs/keys.log" 2>&1 ||
    die "palpsim-keys $who in image palpsim-clients" "$logs/keys.log"
done
cp "$keys/station1.key" "$keys/allowed"
note "keys: server, station1 (allowed), intruder (not allowed), by palpsim-keys in $keys"
# the gateway's TLS certificate (self-signed, for 127.0.0.1 and localhost) and station token
openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -days 2 -subj /CN=localhost \
  -addext 'subjectAltName=DNS:localhost,IP:127.0.0.1' -keyout "$keys/web.key" -out "$keys/web.crt" \
  >> "$logs/keys.log" 2>&1 || die "openssl: the gateway's TLS certificate" "$logs/keys.log"
python3 -c 'import secrets; print(secrets.token_urlsafe(24))' > "$keys/station.token"
chmod 600 "$keys/web.key" "$keys/station.token"

# start_ctr NAME IMAGE LOG LINE RUN-ARGS...: runs container NAME (`docker run -d RUN-ARGS`,
# which name IMAGE) and waits for LINE (a grep pattern) in its output, which goes to LOG
start_ctr() {
  local name=$1 image=$2 log=$3 line=$4; shift 4
  dk run -d --name "$name" "$@" > /dev/null || die "starting container $name from $image"
  for _ in $(seq 180); do
    dk logs "$name" > "$log" 2>&1 || true
    grep -q "$line" "$log" && return 0
    [ "$(dk inspect -f '{{.State.Running}}' "$name")" = true ] ||
      die "container $name ($image) exited before it printed '$line'" "$log"
    sleep 1
  done
  die "container $name ($image) printed no '$line' within 180 s" "$log"
}
# start_server IMAGE LOG RUN-ARGS...: container $server_ctr, ready at its 'ready on' line
start_server() {
  local image=$1 log=$2; shift 2
  start_ctr "$server_ctr" "$image" "$log" 'ready on' "$@"
}
# a free TCP port on the host's loopback
free_port() { python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }

dk network create "$net" > /dev/null || die "docker network create $net"
# the image's default command: the phantom scene on 0.0.0.0:7420 with /keys/server.key_secret and /keys/allowed
start_server palpsim-server:cpu "$logs/server.log" --network "$net" -v "$keys:/keys:ro" palpsim-server:cpu
note "server: $(grep -m1 'ready on' "$logs/server.log")"

# a small plan: 3 x 2 presses over the lumbar spine of the phantom, 20 mm deep
cat > "$client_out/plan.toml" <<'PLAN'
name = "docker-test grid"
sample_rate_hz = 400.0
repetitions = 1
[grid]
center_mm = [0.0, 110.0, -10.0]
axis_u = [1.0, 0.0, 0.0]
axis_v = [0.0, 0.0, 1.0]
size_u_mm = 20.0
size_v_mm = 40.0
count_u = 3
count_v = 2
[press]
direction = [0.0, -1.0, 0.0]
reference = "skin"
depth_mm = 20.0
speed_mm_per_s = 40.0
approach_mm = 10.0
max_travel_mm = 40.0
hold_s = 0.0
PLAN
# the client container's steps: press (and watch two frames of that session meanwhile),
# the batch plan, then the server's stats, with the intruder's key refused first
cat > "$client_out/run.sh" <<'RUN'
set -eu
addr=tcp://palpsim-dtest-server:7420
keys="--server-key /keys/server.key --client-key /keys/station1.key_secret"
palpsim-haptic --connect $addr $keys --device press --seconds 15 --log /out/haptic.csv > /out/haptic.txt &
haptic=$!
sleep 1
timeout 60 palpsim-view --connect $addr $keys --any --out /out/view --frames 2 > /out/view.txt 2>&1
wait $haptic
palpsim-batch /out/plan.toml --connect $addr $keys --sessions 2 --out /out/batch > /out/batch.txt 2>&1
python3 - <<'PY'
import json
from palpsim.client import Client, ServerTimeout
from palpsim.keys import CurveKeys
addr = "tcp://palpsim-dtest-server:7420"
# a key not on the allow-list: the handshake fails, the server never answers
try:
    Client(addr, timeout_s=2.0, curve=CurveKeys.from_files("/keys/server.key", "/keys/intruder.key_secret")).info()
    intruder = "answered"
except ServerTimeout:
    intruder = "refused"
s = Client(addr, curve=CurveKeys.from_files("/keys/server.key", "/keys/station1.key_secret")).stats().server
json.dump({"intruder": intruder, "curve_admitted": s.curve_admitted, "curve_refused": s.curve_refused},
          open("/out/stats.json", "w"))
PY
RUN
say "palpating from container $client_ctr (palpsim-clients) to $server_ctr (log: $logs/client.log)"
dk run --name "$client_ctr" --network "$net" -v "$keys:/keys:ro" -v "$client_out:/out" palpsim-clients \
  bash /out/run.sh > "$logs/client.log" 2>&1 ||
  die "the client container $client_ctr (palpsim-clients; outputs in $client_out)" "$logs/client.log"
dk logs "$server_ctr" > "$logs/server.log" 2>&1 || true

# ---- 4. checks, each from the clients' own outputs
cat "$client_out/haptic.txt" >> "$logs/client.log"
haptic_line=$(grep -m1 'steps at' "$client_out/haptic.txt" || true)
peak_line=$(grep -m1 'server peak' "$client_out/haptic.txt" || true)
[ -n "$haptic_line" ] && [ -n "$peak_line" ] || die "palpsim-haptic printed no summary" "$client_out/haptic.txt"
note "haptic: ${haptic_line#palpsim-haptic: }; $(grep -m1 'round trip p50' "$client_out/haptic.txt")"
read -r steps replies errors lost < <(sed -E 's/.*: ([0-9]+) steps at .*, ([0-9]+) replies, ([0-9]+) errors, ([0-9]+) lost.*/\1 \2 \3 \4/' <<< "$haptic_line")
peak=$(sed -E 's/.*server peak ([0-9.]+) N.*/\1/' <<< "$peak_line")
note "haptic: server force peak $peak N over the press"
[ "$replies" -gt 0 ] && [ "$errors" -eq 0 ] && [ "$lost" -eq 0 ] ||
  die "palpsim-haptic: $steps steps, $replies replies, $errors errors, $lost lost (expected every pose answered)" "$client_out/haptic.txt"
awk -v p="$peak" 'BEGIN { exit !(p > 0) }' || die "palpsim-haptic: no force in the body (server peak $peak N)" "$client_out/haptic.txt"

summary_json=$client_out/batch/summary.json
[ -f "$summary_json" ] || die "palpsim-batch wrote no $summary_json" "$client_out/batch.txt"
batch_line=$(python3 -c '
import json, sys
s = json.load(open(sys.argv[1]))
f = s["force"]
print(s["presses"], s["presses_without_contact"], format(f["peak_force_n_min"], ".3f"), format(f["peak_force_n_max"], ".3f"), s["poses"])
' "$summary_json")
read -r presses no_contact fmin fmax poses <<< "$batch_line"
note "batch: $presses presses ($poses poses) over 2 sessions, $no_contact without contact, peak force $fmin-$fmax N"
[ "$presses" -eq 6 ] && [ "$no_contact" -eq 0 ] ||
  die "palpsim-batch: $presses presses, $no_contact without contact (expected 6, all in contact)" "$client_out/batch.txt"
awk -v f="$fmin" 'BEGIN { exit !(f > 0) }' || die "palpsim-batch: a press felt no force (min peak $fmin N)" "$client_out/batch.txt"

frames=$(ls "$client_out/view"/*.png 2>/dev/null | wc -l)
note "view: $frames PNG frames; $(grep -m1 'frames received' "$client_out/view.txt" || true)"
[ "$frames" -ge 2 ] || die "palpsim-view received $frames frames (expected 2)" "$client_out/view.txt"

read -r intruder admitted refused < <(python3 -c '
import json, sys
s = json.load(open(sys.argv[1]))
print(s["intruder"], s["curve_admitted"], s["curve_refused"])
' "$client_out/stats.json")
note "server stats: curve_admitted $admitted, curve_refused $refused; the intruder's key was $intruder"
[ "$intruder" = refused ] && [ "$admitted" -gt 0 ] && [ "$refused" -gt 0 ] ||
  die "CURVE: expected station1 admitted and the intruder refused (stats in $client_out/stats.json)" "$logs/server.log"
note "palpation across containers with CURVE: PASSED"

# ---- 5. the browser station: the gateway in a container beyond its loopback (TLS, token),
# published on the host's loopback, and the host's headless chromium
web_w=640 web_h=360
web_port=$(free_port)
say "palpsim-web in container $web_ctr on https://127.0.0.1:$web_port (log: $logs/web.log)"
start_ctr "$web_ctr" palpsim-clients "$logs/web.log" 'serving on https://' --network "$net" \
  -p "127.0.0.1:$web_port:8080" -v "$keys:/keys:ro" palpsim-clients \
  palpsim-web --connect tcp://palpsim-dtest-server:7420 --server-key /keys/server.key \
  --client-key /keys/station1.key_secret --host 0.0.0.0 --port 8080 --tls-cert /keys/web.crt \
  --tls-key /keys/web.key --station-token-file /keys/station.token --size "${web_w}x$web_h"
note "gateway: $(grep -m1 'serving on' "$logs/web.log") in the container, published on https://127.0.0.1:$web_port"
rm -f "$out"/web-*.png "$client_out/web.json"
"$py" - "https://127.0.0.1:$web_port" "$keys/station.token" "$out" "$web_w" "$web_h" > "$logs/browser.log" 2>&1 <<'PY' ||
import io, json, sys, time
from pathlib import Path

import numpy as np
from PIL import Image

from palpsim.web import headless_chromium

url, token, out, w, h = sys.argv[1], Path(sys.argv[2]).read_text().split()[0], Path(sys.argv[3]), *map(int, sys.argv[4:6])


def wait(cond, timeout_s, what):
    """cond()'s first true value, polled every 0.1 s (llvmpipe on a loaded machine renders a few frames a second)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        v = cond()
        if v:
            return v
        time.sleep(0.1)
    raise SystemExit(f"no {what} within {timeout_s} s (page stats: {stats()})")


def canvas():
    png = driver.find_element("id", "frame").screenshot_as_png
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(float)


def pct(v, q):
    return sorted(v)[min(len(v) - 1, int(q * len(v)))] if v else float("nan")


driver = headless_chromium(w + 500, h + 300, accept_insecure_certs=True)
stats = lambda: driver.execute_script("return window.palpsimStats || null")  # noqa: E731
try:
    # the gateway beyond loopback asks for the station token once
    driver.get(url + "/")
    if not driver.current_url.endswith("/login"):
        raise SystemExit(f"no station login at {url}/: the browser shows {driver.current_url} "
                         f"({driver.title!r}; no gateway there, or one without a token)")
    field = driver.find_element("name", "token")
    field.send_keys(token)
    field.submit()
    wait(lambda: (stats() or {}).get("frames", 0) >= 1, 120, "frame in the page after the login")
    first = canvas()
    driver.save_screenshot(str(out / "web-1-first-frame.png"))
    # click the centre of the 3D view (the frame's left part; azimuth 0 looks at the back)
    driver.execute_script(f"window.palpsim.pick({(w - min(h // 3, w)) / 2}, {h / 2})")
    wait(lambda: (lambda s: s["contact"] and s["maxForce"] > 0)(stats()), 60, "contact with a force above 0")
    # the depth goal alternates between 3 and 9 mm for 10 s: the tip keeps moving
    s0 = stats()
    frames0, p2f0 = s0["frames"], len(s0["poseToFrame"])
    t0, depth = time.monotonic(), 3
    while time.monotonic() - t0 < 10:
        depth = 12 - depth
        driver.execute_script(f"window.palpsim.setDepth({depth})")
        time.sleep(0.25)
    wait(lambda: stats()["frames"] >= frames0 + 2, 60, "two frames during the press")
    s = stats()
    pressed = canvas()
    driver.save_screenshot(str(out / "web-2-pressed.png"))
    # two distinct frames: each has structure (a blank one has a pixel spread of 0), and
    # pixels more than 30 grey levels apart (far above JPEG noise; an unchanged view
    # re-encodes byte for byte) number at least 20, a quarter of the tip marker's disc
    changed = int((np.abs(pressed - first).max(axis=2) > 30).sum())
    p2f = s["poseToFrame"][p2f0:]
    result = {"frames": s["frames"], "frames_during_press": s["frames"] - frames0,
              "frames_per_s": s["fps"], "changed_pixels": changed,
              "pixel_std": [round(first.std(), 1), round(pressed.std(), 1)],
              "max_force_n": s["maxForce"], "contact": s["contact"], "errors": s["errors"],
              "pose_to_frame_ms": {"p50": pct(p2f, 0.5), "p90": pct(p2f, 0.9), "n": len(p2f)}}
    (out / "client" / "web.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result))
    if s["errors"] or first.std() <= 10 or pressed.std() <= 10 or changed < 20:
        raise SystemExit(f"expected two distinct frames of the body and no page errors: {result}")
finally:
    driver.quit()
PY
  { dk logs "$web_ctr" > "$logs/web.log" 2>&1 || true
    die "step 5: headless chromium through the gateway container $web_ctr: $(tail -n 1 "$logs/browser.log") (browser: $logs/browser.log)" "$logs/web.log"; }
read -r web_frames web_changed web_fps p2f50 p2f90 p2fn force < <(python3 -c '
import json, sys
r = json.load(open(sys.argv[1]))
p = r["pose_to_frame_ms"]
print(r["frames"], r["changed_pixels"], format(r["frames_per_s"], ".1f"), format(p["p50"], ".0f"), format(p["p90"], ".0f"), p["n"], format(r["max_force_n"], ".2f"))
' "$client_out/web.json")
note "browser: $web_frames frames at ${web_w}x$web_h (${web_fps} frames/s), $web_changed pixels changed by the press, force up to $force N; pose to frame through the gateway p50 $p2f50 ms, p90 $p2f90 ms ($p2fn frames)"
dk stop -t 10 "$web_ctr" > /dev/null
dk logs "$web_ctr" > "$logs/web.log" 2>&1 || true
note "browser station through the gateway container (TLS, station token, CURVE): PASSED; screenshots $out/web-1-first-frame.png, $out/web-2-pressed.png"

# ---- 6. Slicer's stand-in: the bridge in a container on the host's network (OpenIGTLink
# on loopback), the server at its container address, a pyigtl client on the host
server_ip=$(dk inspect -f '{{range .NetworkSettings.Networks}}{{.IPAddress}}{{end}}' "$server_ctr")
igtl_port=$(free_port)
say "palpsim-igtl in container $igtl_ctr on 127.0.0.1:$igtl_port (log: $logs/igtl.log)"
start_ctr "$igtl_ctr" palpsim-clients "$logs/igtl.log" 'serving OpenIGTLink on' --network host \
  -v "$keys:/keys:ro" palpsim-clients palpsim-igtl --connect "tcp://$server_ip:7420" \
  --server-key /keys/server.key --client-key /keys/station1.key_secret --port "$igtl_port"
"$py" - "$igtl_port" "$client_out/igtl.json" > "$logs/slicer.log" 2>&1 <<'PY' ||
import collections, json, sys, time

import pyigtl


class Counter(dict):
    """pyigtl's table of the newest message per device name, counting arrivals."""

    def __init__(self):
        super().__init__()
        self.n = collections.Counter()

    def __setitem__(self, name, msg):
        self.n[name] += 1
        super().__setitem__(name, msg)


slicer = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=int(sys.argv[1]), start_now=False)
slicer.incoming_messages = got = Counter()
slicer.start()
try:
    image = slicer.wait_for_message("PalpsimVolume", timeout=120)
    if image is None:
        raise SystemExit(f"no IMAGE PalpsimVolume within 120 s (arrived: {dict(got.n)})")
    tip = slicer.wait_for_message("PalpsimTip", timeout=30)
    if tip is None:
        raise SystemExit(f"no TRANSFORM PalpsimTip within 30 s (arrived: {dict(got.n)})")
    n0, t0 = got.n["PalpsimTip"], time.monotonic()
    time.sleep(3.0)
    rate = (got.n["PalpsimTip"] - n0) / (time.monotonic() - t0)
    result = {"image_shape": list(image.image.shape), "image_dtype": str(image.image.dtype),
              "image_origin_ras_mm": [round(float(v), 2) for v in image.ijk_to_world_matrix[:3, 3]],
              "tip_ras_mm": [round(float(v), 2) for v in tip.matrix[:3, 3]],
              "tip_transforms_per_s": round(rate, 1), "arrived": dict(got.n)}
    json.dump(result, open(sys.argv[2], "w"), indent=2)
    print(json.dumps(result))
    if rate <= 0:
        raise SystemExit(f"the tip's TRANSFORM stopped after the first: {result}")
finally:
    slicer.stop()
PY
  { dk logs "$igtl_ctr" > "$logs/igtl.log" 2>&1 || true
    die "step 6: a pyigtl client through the bridge container $igtl_ctr: $(tail -n 1 "$logs/slicer.log") (client: $logs/slicer.log)" "$logs/igtl.log"; }
read -r igtl_shape igtl_rate < <(python3 -c '
import json, sys
r = json.load(open(sys.argv[1]))
print("x".join(map(str, r["image_shape"])) + "_" + r["image_dtype"], r["tip_transforms_per_s"])
' "$client_out/igtl.json")
dk stop -t 10 "$igtl_ctr" > /dev/null
dk logs "$igtl_ctr" > "$logs/igtl.log" 2>&1 || true
note "igtl: IMAGE PalpsimVolume ${igtl_shape/_/ } (k, j, i), TRANSFORM PalpsimTip at $igtl_rate a second; bridge: $(grep -v serving "$logs/igtl.log" | tail -1)"
note "Slicer's stand-in through the bridge container: PASSED"

dk stop -t 10 "$server_ctr" > /dev/null
dk logs "$server_ctr" > "$logs/server.log" 2>&1 || true
dk rm -f "$server_ctr" > /dev/null

# ---- the GPU server image: built here, run in full only on a machine with an NVIDIA GPU;
# here it must start on the built-in scene (no frames: no EGL vendor without the driver)
if [ $gpu_build -eq 1 ]; then
  build palpsim-server:gpu docker/server.Dockerfile VARIANT=gpu
  start_server palpsim-server:gpu "$logs/server-gpu.log" palpsim-server:gpu --bind tcp://127.0.0.1:7420
  dk rm -f "$server_ctr" > /dev/null
  note "palpsim-server:gpu: starts here on the built-in scene (all libraries found, patient prepared); deformation on CUDA and frames through the NVIDIA EGL need a GPU host"
fi
say "summary in $summary"
