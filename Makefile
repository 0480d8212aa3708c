# cloudgraph: the README's two commands are `make run` and `make test`; both start with setup.
SHELL := /bin/bash
APT_PACKAGES := libllvm19 python3-openvdb python3-venv redis-server chromium
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: setup apt run test lint bench clean

setup: apt $(STAMP)

# Installs the Debian packages that are missing; takes well under a second when none are.
apt:
	@missing=""; for p in $(APT_PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:$$missing"; \
	  if [ "$$(id -u)" != 0 ]; then echo "error: run as root to install:$$missing" >&2; exit 1; fi; \
	  apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q $$missing; \
	fi

# The venv sees Debian's pyopenvdb (system site packages), which needs numpy 1.x.
$(STAMP): pyproject.toml
	test -x $(PY) || /usr/bin/python3 -m venv --system-site-packages $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q "numpy<2" -e ".[test]"
	touch $(STAMP)

# Redis (append-only, data under ./data), one worker and the API + web page on :8000.
run: setup
	./bin/run-service

test: setup
	$(VENV)/bin/ruff check cloudgraph cloudgraph_service server worker tests
	$(VENV)/bin/python -m pytest -q --durations=25

lint: setup
	$(VENV)/bin/ruff check cloudgraph cloudgraph_service server worker tests
	$(VENV)/bin/ruff format --check cloudgraph cloudgraph_service server worker tests

bench: setup
	$(VENV)/bin/cloudgraph bench

clean:
	rm -rf $(VENV) build *.egg-info

# The cluster (compose.yaml; docs/cluster.md). Docker comes from Debian (docker.io,
# docker-compose, debootstrap: installed and dockerd started where missing, as root); the base
# image is made from Debian's archive (no image registry needed), then the image on it.
.PHONY: docker-ready base-image cluster-image cluster-test cluster-ready
docker-ready:
	./docker/ensure-docker.sh

# cloudgraph-base:bookworm: debootstrap --variant=minbase bookworm, then docker import (FORCE=1 remakes it).
base-image: docker-ready
	./docker/base-image.sh

# cloudgraph:latest from docker/Dockerfile (make setup inside; cached layers).
cluster-image: base-image
	./docker/build-image.sh

# Builds what it needs, then brings the cluster up, uploads, precomputes, renders and tears it down.
cluster-test: setup cluster-image
	$(VENV)/bin/python -m pytest -q -s tests/cluster

# `make test` runs the cluster test as well: it makes Docker and the images ready first. Where
# Docker cannot run, tests/cluster is skipped with the reason; CLOUDGRAPH_CLUSTER_TEST=0 leaves it out.
test: cluster-ready
cluster-ready:
	@if [ "$${CLOUDGRAPH_CLUSTER_TEST:-1}" = 0 ]; then echo "cluster test off (CLOUDGRAPH_CLUSTER_TEST=0)"; \
	elif ./docker/ensure-docker.sh; then $(MAKE) --no-print-directory cluster-image; \
	else echo "warning: Docker cannot run here: tests/cluster will be skipped" >&2; fi
