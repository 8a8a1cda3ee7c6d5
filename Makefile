# The two commands of the README. Both create .venv if missing and install the pinned project.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test install system-deps bench peers clean

# open3d needs libusb-1.0 at import time; install it with apt when missing and we are root.
system-deps:
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	    echo "installing libusb-1.0-0 (needed by open3d)"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	  else \
	    echo "warning: libusb-1.0-0 is missing; install it (apt-get install libusb-1.0-0) for open3d" >&2; \
	  fi; \
	fi

$(PY):
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(PY)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,bench]'
	$(PY) -m slam.compile_kernels  # compile the numba kernels into their on-disk cache once
	@touch $(STAMP)

install: system-deps $(STAMP)

demo: install
	$(VENV)/bin/slam demo

test: install
	$(PY) -m pytest -n 2 --dist loadgroup -q

# The optional peer of benchmarks/peers.py. kiss-slam's map-closures dependency caps numpy, pydantic
# and typer below our pins (see pyproject.toml), so both go in without their dependency metadata.
# `make peers VENV=.venv-peers` keeps it out of the main environment.
peers: install
	$(PY) -m pip install --quiet -e '.[test,bench,peers]'
	$(PY) -m pip install --quiet --no-deps kiss-slam==0.0.2 map-closures==2.2.0

bench: install
	@for b in benchmarks/*.py; do echo "== $$b"; $(PY) $$b; done

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
