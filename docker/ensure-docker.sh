#!/usr/bin/env bash
# Makes sure Docker Engine and docker-compose are here and running: installs Debian's docker.io,
# docker-compose and debootstrap where missing (as root) and starts dockerd when nothing answers
# on its socket (log in /var/log/dockerd.log). Quick when all is in place.
set -euo pipefail
missing=""
command -v dockerd >/dev/null || missing="$missing docker.io"
command -v docker >/dev/null || missing="$missing docker.io"
command -v docker-compose >/dev/null || missing="$missing docker-compose"
command -v debootstrap >/dev/null || missing="$missing debootstrap"
if [ -n "$missing" ]; then
  [ "$(id -u)" = 0 ] || { echo "error: run as root to install:$missing" >&2; exit 1; }
  echo "installing Debian packages:$missing"
  apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q $missing
fi
if ! docker info >/dev/null 2>&1; then
  [ "$(id -u)" = 0 ] || { echo "error: dockerd is not running; run as root to start it" >&2; exit 1; }
  echo "starting dockerd (log: /var/log/dockerd.log)"
  nohup dockerd >/var/log/dockerd.log 2>&1 &
  for _ in $(seq 60); do docker info >/dev/null 2>&1 && break; sleep 0.5; done
  docker info >/dev/null 2>&1 || { tail -20 /var/log/dockerd.log >&2; exit 1; }
fi
