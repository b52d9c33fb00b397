# lbo: make help lists the targets.
SHELL := /bin/bash
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
SCALE ?= paper
TRAINER ?= cpu

.PHONY: help install test test-fast data reproduce bench lint clean

help:  ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-10s %s\n", $$1, $$2}'

install: $(STAMP)  ## create .venv and install lbo with everything it needs (CPU torch)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	# torch is pinned in its own step: an unpinned torch pulls gigabytes of CUDA packages
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e ".[dev]"
	touch $@

test: install  ## run every test, the slow ones included
	$(PY) -m pytest -q

test-fast: install  ## run the tests without the slow marker
	$(PY) -m pytest -q -m "not slow"

data: install  ## generate the data sets: make data SCALE=smoke|quick|paper
	$(PY) -m lbo.datagen data=$(SCALE)

reproduce: install  ## the paper's study, resumable: make reproduce SCALE=paper|quick [TRAINER=gpu]
	$(PY) -m lbo.reproduce scale=$(SCALE) "train_overrides=['trainer=$(TRAINER)']"

bench: install  ## benchmarks: data generation, filters, training throughput, latency (medians)
	$(PY) benchmarks/bench_datagen.py
	$(PY) benchmarks/bench_filters.py
	$(PY) benchmarks/bench_train.py
	$(PY) benchmarks/bench_latency.py

lint: install  ## ruff
	$(VENV)/bin/ruff check src tests benchmarks

clean:  ## remove generated outputs (keeps .venv, data/ and the MLflow/Optuna stores)
	rm -rf outputs multirun .pytest_cache
