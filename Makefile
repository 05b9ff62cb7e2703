# volumesh: `make run` sets everything up and runs the service; `make test` sets up and tests.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip
APT_PACKAGES := libusb-1.0-0 libgomp1 redis-server chromium docker-compose
HOST ?= 127.0.0.1
PORT ?= 8000

.PHONY: setup run test lint unit bench clean stage-settings settings-table

setup: $(VENV)/.installed node_modules/.installed .apt-installed

# Debian packages the project needs (open3d's libusb, a Redis server for the tests, Chromium
# for the viewer's browser tests). Installed only when missing; needs root, as on CI.
.apt-installed:
	@missing=""; for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:$$missing"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null; \
	fi
	@touch $@

# torch==2.13.0 first: on this kind of machine pip takes the CPU build lying on disk.
$(VENV)/.installed: pyproject.toml
	test -x $(PY) || python3 -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q -e '.[dev]'
	@touch $@

node_modules/.installed: package.json package-lock.json
	npm ci --no-audit --no-fund --loglevel=error
	@touch $@

run: setup
	$(VENV)/bin/volumesh serve --host $(HOST) --port $(PORT) --sample

stage-settings: setup  ## the gateway's copy of the pipeline's job option settings
	$(VENV)/bin/python -c "import json; from pipeline.stage_config import settings_kinds; print(json.dumps(settings_kinds(), indent=1, sort_keys=True))" > app/core/stage_settings.json

settings-table: setup  ## README's configuration table (between its settings markers)
	@$(PY) -m workers.settings_table

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy
	$(VENV)/bin/lint-imports

# Two processes: the service tests spend most of their time waiting on the processes they
# start, and each test starts its own services on free ports.
unit: setup
	$(VENV)/bin/pytest -q -n 2

test: lint unit

bench: setup
	$(PY) benchmarks/reconstruct.py

clean:
	rm -rf $(VENV) node_modules .apt-installed
