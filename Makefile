# The two commands of the README: `make demo` and `make test`. Both work on a fresh machine:
# they install the system library open3d's wheel needs, create .venv and install jaxmap into it.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.jaxmap-installed
DEMO_DATA ?= data/city_demo
DEMO_RUN ?= runs/demo
PYTEST_ARGS ?=
# The suite compiles into an empty XLA cache made for the run (deleted after it), as on a new machine: CI
# measures what a new user waits. TEST_CACHE=warm keeps the per-CPU cache between runs (about half the time).
TEST_CACHE ?= cold

.PHONY: demo test install sysdeps clean

# open3d's Linux wheel links against libusb-1.0; Debian/Ubuntu images often lack it. chromium (headless):
# tests/test_viewer.py loads the live viewer (viser, WebGL) in it and checks a screenshot.
sysdeps:
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  echo "[make] installing libusb-1.0-0 (needed by open3d)"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	fi
	@if ! command -v chromium >/dev/null 2>&1 && ! command -v chromium-browser >/dev/null 2>&1; then \
	  echo "[make] installing chromium (browser test of the viewer)"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq chromium >/dev/null; \
	fi

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	@touch $(STAMP)

install: sysdeps $(STAMP)

demo: install
	$(VENV)/bin/jaxmap demo --data $(DEMO_DATA) --out $(DEMO_RUN)

test: install
ifeq ($(TEST_CACHE),warm)
	$(PY) -m pytest -q -n 2 --dist loadfile $(PYTEST_ARGS)
else
	@cache=$$(mktemp -d "$${TMPDIR:-/tmp}/jaxmap-test-cache.XXXXXX"); trap 'rm -rf "$$cache"' EXIT; \
	echo "[make] an empty compile cache for this run: $$cache (TEST_CACHE=warm keeps ~/.cache/jaxmap's)"; \
	JAXMAP_CACHE_DIR=$$cache $(PY) -m pytest -q -n 2 --dist loadfile $(PYTEST_ARGS)
endif

clean:
	rm -rf $(VENV) build *.egg-info data runs
