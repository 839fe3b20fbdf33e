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

.PHONY: install sysdeps demo test lint bench clean serve cycles-env

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

# redis-server for the job service; chromium for the dashboard's browser test (tests/service/test_dashboard.py).
sysdeps: $(SYSSTAMP)
	@command -v redis-server >/dev/null || { SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -q && $$SUDO apt-get install -y -q redis-server; }
	@command -v chromium >/dev/null || { SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -q && $$SUDO apt-get install -y -q chromium; }
	@# PostgreSQL (the deployed database; tests/service run against it too), docker-compose (`config` validates
	@# docker-compose.yml in tests/test_deploy.py), wrk and hey (the load generators of bench/service.py), nginx
	@# (the reverse proxy that receives uploads: deploy/nginx/, services/proxy.py, tests/service/test_proxy.py).
	@missing=""; for p in postgresql:/usr/lib/postgresql docker-compose:/usr/bin/docker-compose wrk:/usr/bin/wrk \
	  hey:/usr/bin/hey nginx-light:/usr/sbin/nginx; do \
	  [ -e $${p#*:} ] || missing="$$missing $${p%%:*}"; done; \
	  if [ -n "$$missing" ]; then SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -q && $$SUDO apt-get install -y -q $$missing; fi

# Blender Cycles as a Python module (bpy from PyPI) in its own venv, for captures rendered by an outside
# renderer (tools/cycles_capture.py, bench/cycles_agreement.py). bpy pins its own numpy; nothing else goes in.
CYCLES_VENV := .venv-cycles
# bpy wheels of the 4.5 LTS line are built for CPython 3.11 only.
CYCLES_PYTHON ?= python3.11
BPY_VERSION := 4.5.15
CYCLES_STAMP := $(CYCLES_VENV)/.installed-bpy-$(BPY_VERSION)

$(CYCLES_STAMP):
	test -x $(CYCLES_VENV)/bin/python || $(CYCLES_PYTHON) -m venv $(CYCLES_VENV)
	$(CYCLES_VENV)/bin/python -m pip install -q bpy==$(BPY_VERSION)
	$(CYCLES_VENV)/bin/python -c "import bpy; print('bpy', bpy.app.version_string)"
	touch $(CYCLES_STAMP)

cycles-env: $(CYCLES_STAMP)

# A real extraction (CPU preset) of the bundled example capture (examples/README.md); rerunning resumes from
# out/demo/work. --init auto: the neural TTO from the PBR solution when the shipped LMRM checkpoint loads, else a
# random triplane.
demo: install
	$(VENV)/bin/neumatex extract examples/coat-teapot --out out/demo/coat-teapot-asset --work out/demo/work \
	  --preset cpu --init auto --threads 0
	@echo "demo: open out/demo/coat-teapot-asset/report/index.html (asset package in out/demo/coat-teapot-asset/)"

test: install sysdeps cycles-env
	$(VENV)/bin/ruff check neumatex_core neumatex_client services workers tests bench tools
	$(VENV)/bin/mypy neumatex_core neumatex_client services workers
	NEUMATEX_SHARED=$(SHARED) $(PY) -m pytest -q

lint: install
	$(VENV)/bin/ruff check neumatex_core neumatex_client services workers tests bench tools
	$(VENV)/bin/mypy neumatex_core neumatex_client services workers

bench: install sysdeps
	$(PY) bench/render.py

# The job service on this machine: redis-server (apt), the API and one worker; prints the dashboard URL.
serve: install sysdeps
	$(PY) -m services serve

clean:
	rm -rf out .pytest_cache .mypy_cache .ruff_cache
