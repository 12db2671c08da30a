#!/usr/bin/env bash
# Check what the Docker image holds and does, without a Docker engine:
#
#   bash docker/check-rootfs.sh [DIR]        (default DIR: /var/tmp/rasterserver-rootfs)
#
# 1. base:  Debian bookworm (minbase) by debootstrap from the host's Debian mirror, plus what
#           python:3.11-slim-bookworm adds to Debian: a Python 3.11 (here Debian's python3,
#           3.11.2, behind /usr/local/bin/python), ca-certificates, netbase, tzdata. Kept in
#           DIR/base and reused by later runs (delete it to start over).
# 2. image: a fresh copy of the base in DIR/image, then docker/Dockerfile's instructions
#           carried out in it with chroot (RUN, COPY, ENV, WORKDIR, USER), as the builder would.
# 3. run:   in a network namespace of its own (a loopback, nothing else), as the image's user:
#           every shared library of the installed wheels resolves; `rasterserver demo` and
#           `verify`; the default command (`serve`) until the Dockerfile's HEALTHCHECK passes
#           and GET /health answers; a Dask scheduler and worker (checked as compose.yaml
#           checks them) computing `process --all-unprocessed --dask`.
#
# Needs root (debootstrap, chroot, mounts; re-runs itself with sudo if it can), the host's
# python3 and network access to the Debian mirror and PyPI for the build. Safe to repeat:
# every run rebuilds the image from the base. Mounts (/proc, /dev, /sys) are undone and
# every process started in the image is ended on exit, also on failure or Ctrl-C.
# MIRROR=URL and SECURITY_MIRROR=URL override the mirrors found in the host's apt sources.
set -euo pipefail

HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
REPO="$(dirname "$HERE")"
DIR="$(realpath -m "${1:-/var/tmp/rasterserver-rootfs}")"
SUITE=bookworm

if [ "$(id -u)" -ne 0 ]; then
  if command -v sudo >/dev/null; then
    exec sudo --preserve-env=MIRROR,SECURITY_MIRROR bash "$0" "$DIR"
  fi
  echo "check-rootfs: needs root (debootstrap, chroot and mounts), and sudo is not installed" >&2
  exit 2
fi
case "$DIR" in
  /|/bin*|/boot*|/dev*|/etc*|/lib*|/proc*|/sys*|/usr*|"$REPO"|"$REPO"/*)
    echo "check-rootfs: refusing to build in $DIR (give a folder of its own)" >&2; exit 2;;
esac
command -v python3 >/dev/null || { echo "check-rootfs: needs python3 on the host" >&2; exit 2; }

BASE="$DIR/base"
IMAGE="$DIR/image"
CONFIG="$DIR/image.json"
HELPER=(python3 "$HERE/rootfs_check.py")
MIRROR="${MIRROR:-$("${HELPER[@]}" mirror)}"
SECURITY_MIRROR="${SECURITY_MIRROR:-${MIRROR%/debian}/debian-security}"
mkdir -p "$DIR"

# --- clean-up: end what runs in the image, undo our mounts (deepest first) -----------------
cleanup() {
  local status=$?
  local pid root
  for pid in $(ls /proc | grep -E '^[0-9]+$'); do
    root="$(readlink "/proc/$pid/root" 2>/dev/null || true)"
    case "$root" in "$BASE"|"$BASE"/*|"$IMAGE"|"$IMAGE"/*) kill -9 "$pid" 2>/dev/null || true;; esac
  done
  local mounts
  mounts="$(awk -v d="$DIR/" 'index($2, d) == 1 {print $2}' /proc/mounts | sort -r)"
  for m in $mounts; do umount "$m" 2>/dev/null || umount -l "$m" || true; done
  return $status
}
trap cleanup EXIT
trap 'exit 130' INT TERM
cleanup  # what an interrupted earlier run may have left

mount_all() {  # ROOT: what the Docker engine gives a container: /proc, /dev, /dev/shm, /sys
  local root="$1"
  mount -t proc proc "$root/proc"
  mount --bind /dev "$root/dev"
  mount -t tmpfs -o mode=1777,size=512m shm "$root/dev/shm"
  mount -t sysfs -o ro sysfs "$root/sys"
}
umount_all() {
  local root="$1" m
  for m in sys dev/shm dev proc; do
    if mountpoint -q "$root/$m"; then umount "$root/$m" || umount -l "$root/$m"; fi
  done
}
seconds() { echo $(( $(date +%s) - $1 )); }

started=$(date +%s)
echo "check-rootfs: $DIR, Debian $SUITE from $MIRROR"

# --- 1. base ------------------------------------------------------------------------------
if [ ! -f "$BASE/.check-rootfs-base" ]; then
  command -v debootstrap >/dev/null || {
    echo "check-rootfs: installing debootstrap" >&2
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq debootstrap >/dev/null
  }
  t=$(date +%s)
  rm -rf "$BASE"
  debootstrap --variant=minbase --include=ca-certificates,netbase,tzdata,python3,python3-venv \
    "$SUITE" "$BASE" "$MIRROR" >"$DIR/debootstrap.log" 2>&1 \
    || { tail -20 "$DIR/debootstrap.log"; echo "FAIL  debootstrap (log: $DIR/debootstrap.log)"; exit 1; }
  # the suites python:3.11-slim-bookworm's apt uses, so the Dockerfile's apt-get sees the same
  cat >"$BASE/etc/apt/sources.list" <<EOF
deb $MIRROR $SUITE main
deb $MIRROR $SUITE-updates main
deb $SECURITY_MIRROR $SUITE-security main
EOF
  cp /etc/resolv.conf "$BASE/etc/resolv.conf"
  mount_all "$BASE"
  chroot "$BASE" /usr/bin/env -i PATH=/usr/sbin:/usr/bin:/sbin:/bin DEBIAN_FRONTEND=noninteractive \
    sh -c 'apt-get update -qq && apt-get upgrade -y -qq && apt-get clean && rm -rf /var/lib/apt/lists/*' \
    >>"$DIR/debootstrap.log" 2>&1
  umount_all "$BASE"
  # the python image's `python` and `python3` are /usr/local/bin's
  ln -sf /usr/bin/python3 "$BASE/usr/local/bin/python3"
  ln -sf /usr/bin/python3 "$BASE/usr/local/bin/python"
  touch "$BASE/.check-rootfs-base"
  echo "PASS  base: debootstrap $SUITE minbase + $(chroot "$BASE" python3 --version)  ($(seconds "$t") s)"
else
  echo "PASS  base: reused $BASE ($(chroot "$BASE" python3 --version); rm -rf it to rebuild)"
fi

# --- 2. image: the Dockerfile's steps on a fresh copy of the base ---------------------------
t=$(date +%s)
rm -rf "$IMAGE"
cp -a "$BASE" "$IMAGE"
rm -f "$IMAGE/.check-rootfs-base"
cp /etc/resolv.conf "$IMAGE/etc/resolv.conf"  # the builder's DNS, as Docker gives a build
# what Debian's Docker images (and so python:3.11-slim-bookworm) configure: apt deletes the
# packages it has installed from its cache, so they are not left in the image
cat >"$IMAGE/etc/apt/apt.conf.d/docker-clean" <<'EOF'
DPkg::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
APT::Update::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
Dir::Cache::pkgcache "";
Dir::Cache::srcpkgcache "";
EOF
# pip in the build trusts what pip on this host trusts (a proxy that re-signs TLS has its own
# CA); the bundle is removed again and is not part of the image
cp "${PIP_CERT:-/etc/ssl/certs/ca-certificates.crt}" "$IMAGE/tmp/check-rootfs-ca.crt"
mount_all "$IMAGE"
CHECK_ROOTFS_PIP_CERT=/tmp/check-rootfs-ca.crt \
  "${HELPER[@]}" replay "$REPO/docker/Dockerfile" "$IMAGE" "$REPO" "$CONFIG"
umount_all "$IMAGE"
rm -f "$IMAGE/tmp/check-rootfs-ca.crt"
size_total="$(du -sh "$IMAGE" | cut -f1)"
size_base="$(du -sh "$BASE" | cut -f1)"
size_venv="$(du -sh "$IMAGE/opt/venv" | cut -f1)"
echo "PASS  image built from the Dockerfile  ($(seconds "$t") s; root file system $size_total:" \
  "base $size_base, /opt/venv $size_venv)"

# --- 3. run, with no network but a loopback -------------------------------------------------
rm -f "$IMAGE/etc/resolv.conf"
: >"$IMAGE/etc/resolv.conf"
mount_all "$IMAGE"
t=$(date +%s)
set +e
unshare --net "${HELPER[@]}" run "$IMAGE" "$CONFIG"
status=$?
set -e
umount_all "$IMAGE"
echo "check-rootfs: run checks $(seconds "$t") s, whole check $(seconds "$started") s; logs in $DIR/logs"
exit $status
