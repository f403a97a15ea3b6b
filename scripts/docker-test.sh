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
#    intruder's refused. Containers and the network are removed at exit (--keep keeps them).
#
# Writes out/docker-test/: summary.txt (date, commit, image sizes, build times, the result),
# logs/ (dockerd, each build, server, client) and client/ (the clients' outputs).
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
    -h|--help) sed -n '2,26p' "$0"; exit 0 ;;
    *) echo "docker-test: unknown argument '$a' (expected --no-gpu-build, --keep)" >&2; exit 2 ;;
  esac
done

net=palpsim-dtest
server_ctr=palpsim-dtest-server
client_ctr=palpsim-dtest-client
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
  dk rm -f "$client_ctr" "$server_ctr" >/dev/null 2>&1 || true
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

# start_server IMAGE LOG RUN-ARGS...: runs container $server_ctr (`docker run -d RUN-ARGS`,
# which name IMAGE) and waits for the server's 'ready on' line, its output in LOG
start_server() {
  local image=$1 log=$2; shift 2
  dk run -d --name "$server_ctr" "$@" > /dev/null || die "starting container $server_ctr from $image"
  for _ in $(seq 180); do
    dk logs "$server_ctr" > "$log" 2>&1 || true
    grep -q 'ready on' "$log" && return 0
    [ "$(dk inspect -f '{{.State.Running}}' "$server_ctr")" = true ] ||
      die "container $server_ctr ($image) exited before it was ready" "$log"
    sleep 1
  done
  die "container $server_ctr ($image) printed no 'ready on' within 180 s" "$log"
}

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
dk stop -t 10 "$server_ctr" > /dev/null
dk logs "$server_ctr" > "$logs/server.log" 2>&1 || true
dk rm -f "$server_ctr" > /dev/null
note "palpation across containers with CURVE: PASSED"

# ---- the GPU server image: built here, run in full only on a machine with an NVIDIA GPU;
# here it must start on the built-in scene (no frames: no EGL vendor without the driver)
if [ $gpu_build -eq 1 ]; then
  build palpsim-server:gpu docker/server.Dockerfile VARIANT=gpu
  start_server palpsim-server:gpu "$logs/server-gpu.log" palpsim-server:gpu --bind tcp://127.0.0.1:7420
  dk rm -f "$server_ctr" > /dev/null
  note "palpsim-server:gpu: starts here on the built-in scene (all libraries found, patient prepared); deformation on CUDA and frames through the NVIDIA EGL need a GPU host"
fi
say "summary in $summary"
