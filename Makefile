# Two set-up-and-go commands: `make demo` and `make test`. Both build everything they
# need from nothing (venv, pinned pip packages, Debian's wordnet-base) and are idempotent.
SHELL := /bin/bash
.SHELLFLAGS := -eo pipefail -c
.DEFAULT_GOAL := help

PYTHON ?= python3.11
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
WORDNET := /usr/share/wordnet/data.noun
MKL_SHIM := $(VENV)/lib/libgscan_mkl_intel_cpu.so

# DDS stays on loopback; a distinct domain per run.
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export ROS_DOMAIN_ID ?= 57
export PYTHONUNBUFFERED := 1
export ROS_LOG_DIR ?= $(CURDIR)/.ros_log
export MPLBACKEND := Agg

.PHONY: help setup test test-quick lint demo bench clean

help:
	@echo "make demo   run the ROS stack on the shipped model and show the episode"
	@echo "make test   run the test suite"
	@echo "make bench  run the benchmarks in bench/ (prints figures; not bench/research/)"
	@echo "make test-quick  the tests not marked slow, e2e or packaging (setup.cfg)"
	@echo "make lint   ruff check (ruff.toml)"

setup: $(STAMP) $(WORDNET) $(MKL_SHIM)

$(STAMP): requirements.txt setup.py
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q -r requirements.txt 2>&1 | { grep -v "is ignored: it is neither" || true; }
	$(PY) -m pip install -q --no-deps --no-build-isolation -e . 2>&1 | { grep -v "is ignored: it is neither" || true; }
	touch $@

# MKL's fast kernels on AMD CPUs for the runner's trainings (gscan_ros/runtime.py:
# mkl_shim_env). Optional: without a C compiler MKL keeps its generic path.
$(MKL_SHIM): gscan_ros/mkl_intel_cpu.c | $(STAMP)
	cc -shared -fPIC -O2 -o $@ $< || echo "no C compiler: MKL keeps its generic path on AMD CPUs"

$(WORDNET):
	@if [ "$$(id -u)" = 0 ]; then SUDO=; else SUDO=sudo; fi; \
	$$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq wordnet-base

test: setup
	$(PY) -m pytest -q tests

test-quick: setup
	$(PY) -m pytest -q -m "not slow and not e2e and not packaging" tests

lint: setup
	$(VENV)/bin/ruff check .

demo: setup
	$(VENV)/bin/gscan-ros demo

# Each benchmark in bench/ once, with its defaults. The research probes in bench/research/
# (trained runs, arguments, hours) run only when asked.
bench: setup
	for b in bench/[a-z]*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) .ros_log build install log *.egg-info
