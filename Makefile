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
	$(VENV)/bin/ruff check cloudgraph server worker tests
	$(VENV)/bin/python -m pytest -q

lint: setup
	$(VENV)/bin/ruff check cloudgraph server worker tests
	$(VENV)/bin/ruff format --check cloudgraph server worker tests

bench: setup
	$(VENV)/bin/cloudgraph bench

clean:
	rm -rf $(VENV) build *.egg-info
