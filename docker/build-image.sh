#!/usr/bin/env bash
# Builds cloudgraph:latest (CLOUDGRAPH_IMAGE) from docker/Dockerfile on the base image that
# docker/base-image.sh made. The host's CA bundle goes along (docker/ca/host.crt), so that pip in
# the build trusts what the host trusts. Layers are cached: after a code change, seconds.
set -euo pipefail
cd "$(dirname "$0")/.."
IMAGE="${CLOUDGRAPH_IMAGE:-cloudgraph:latest}"
BASE_IMAGE="${BASE_IMAGE:-cloudgraph-base:bookworm}"
docker image inspect "$BASE_IMAGE" >/dev/null 2>&1 || {
  echo "error: no base image $BASE_IMAGE; make base-image makes it" >&2; exit 1
}
if [ -r /etc/ssl/certs/ca-certificates.crt ]; then
  cmp -s /etc/ssl/certs/ca-certificates.crt docker/ca/host.crt ||
    cp /etc/ssl/certs/ca-certificates.crt docker/ca/host.crt
fi
docker build ${QUIET:+-q} --force-rm --build-arg BASE_IMAGE="$BASE_IMAGE" -f docker/Dockerfile -t "$IMAGE" .
