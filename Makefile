# NeuMatEx: `make demo` and `make test` set up everything they need on a fresh machine.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
SYSSTAMP := $(VENV)/.sysdeps
SHARED ?= $(abspath ../shared)
# Mitsuba 3 (the reference renderer in tests and benchmarks) needs LLVM 19: Debian's LLVM 15 aborts it.
LLVM19 := /usr/lib/x86_64-linux-gnu/libLLVM.so.19.1
export DRJIT_LIBLLVM_PATH ?= $(LLVM19)

.PHONY: install sysdeps demo test lint bench clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

# System packages from apt (root on these machines; sudo elsewhere).
$(SYSSTAMP): | $(STAMP)
	@if [ ! -e $(LLVM19) ]; then \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -q && $$SUDO apt-get install -y -q libllvm19; \
	fi
	touch $(SYSSTAMP)

sysdeps: $(SYSSTAMP)

demo: install
	$(VENV)/bin/neumatex render --mesh $(SHARED)/data/meshes/suzanne.obj \
	  --envmap $(SHARED)/data/envmaps/courtyard.exr --out out/demo --resolution 192 --spp 64 \
	  --base-color 0.75 0.35 0.2 --roughness 0.35 --metallic 0.0
	@echo "demo: open out/demo/views.png (23 preset views; EXR + PNG per view in out/demo/)"

test: install sysdeps
	$(VENV)/bin/ruff check neumatex_core tests bench
	$(VENV)/bin/mypy neumatex_core
	NEUMATEX_SHARED=$(SHARED) $(PY) -m pytest -q

lint: install
	$(VENV)/bin/ruff check neumatex_core tests bench
	$(VENV)/bin/mypy neumatex_core

bench: install sysdeps
	$(PY) bench/render.py

clean:
	rm -rf out .pytest_cache .mypy_cache .ruff_cache
