#!/usr/bin/env bash
# Makes the base image (default cloudgraph-base:bookworm) from Debian's own archive, since no
# image registry is reachable: debootstrap --variant=minbase bookworm into a temporary folder,
# then `tar | docker import`. Does nothing when the image exists, unless FORCE=1. Runs as root.
set -euo pipefail
IMAGE="${BASE_IMAGE:-cloudgraph-base:bookworm}"
MIRROR="${DEBIAN_MIRROR:-http://deb.debian.org/debian}"
SECURITY="${DEBIAN_SECURITY_MIRROR:-http://deb.debian.org/debian-security}"

if [ -z "${FORCE:-}" ] && docker image inspect "$IMAGE" >/dev/null 2>&1; then
  echo "base image $IMAGE exists (FORCE=1 makes it again)"
  exit 0
fi
command -v debootstrap >/dev/null || {
  [ "$(id -u)" = 0 ] || { echo "error: run as root to install debootstrap" >&2; exit 1; }
  apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q debootstrap
}

root="$(mktemp -d /var/tmp/cloudgraph-rootfs.XXXXXX)"
trap 'rm -rf "$root"' EXIT
echo "debootstrap --variant=minbase bookworm $root $MIRROR"
debootstrap --variant=minbase bookworm "$root" "$MIRROR" >"$root.log" 2>&1 || {
  tail -20 "$root.log" >&2; rm -f "$root.log"; exit 1
}
rm -f "$root.log"

# The same suites as the host: bookworm, its updates and security fixes; no recommends, no docs.
cat >"$root/etc/apt/sources.list" <<SOURCES
deb $MIRROR bookworm main
deb $MIRROR bookworm-updates main
deb $SECURITY bookworm-security main
SOURCES
cat >"$root/etc/apt/apt.conf.d/90container" <<'APT'
APT::Install-Recommends "false";
APT::Install-Suggests "false";
Acquire::Languages "none";
APT
cat >"$root/etc/dpkg/dpkg.cfg.d/90container" <<'DPKG'
path-exclude=/usr/share/doc/*
path-include=/usr/share/doc/*/copyright
path-exclude=/usr/share/man/*
path-exclude=/usr/share/info/*
path-exclude=/usr/share/locale/*
DPKG
rm -rf "$root"/var/cache/apt/archives/*.deb "$root"/var/lib/apt/lists/* "$root"/usr/share/doc/*/changelog* \
  "$root"/usr/share/man/* "$root"/usr/share/info/*

tar --numeric-owner -C "$root" -c . |
  docker import -c 'CMD ["/bin/bash"]' -c 'ENV LANG=C.UTF-8' -m "debootstrap --variant=minbase bookworm" - "$IMAGE"
docker image ls "$IMAGE"
