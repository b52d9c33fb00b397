# lbo: make help lists the targets.
SHELL := /bin/bash
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
SCALE ?= paper
STUDY ?= paper
TRAINER ?= cpu
LAUNCHER ?= null
JOBS ?= 2
ARGS ?=
TEST_JOBS ?= 2
MLFLOW_PORT ?= 5000
MLFLOW_BACKEND ?= sqlite:///$(CURDIR)/mlflow-server.db
MLFLOW_ARTIFACTS ?= $(CURDIR)/mlflow-server-artifacts

.PHONY: help install test test-fast coverage slurm-check data reproduce ablation fleet real-drive receiver-study side-slip bench readme-tables lint clean mlflow-server ui

help:  ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-10s %s\n", $$1, $$2}'

install: $(STAMP)  ## create .venv and install lbo with everything it needs (CPU torch)

$(STAMP): pyproject.toml constraints.txt examples/plugin/pyproject.toml
	$(PYTHON) -m venv $(VENV)
	# torch first, at constraints.txt's version: an unpinned torch pulls gigabytes of CUDA packages
	$(PY) -m pip install -q -c constraints.txt torch
	$(PY) -m pip install -q -c constraints.txt -e ".[dev,launchers,cluster,real]"
	# the plug-in example (docs/plugins.md), which its tests train, tune, observe and export
	$(PY) -m pip install -q --no-deps -e examples/plugin
	touch $@

test: install  ## run every test, the slow ones included, in TEST_JOBS processes (pytest-xdist)
	$(PY) -m pytest -q -n $(TEST_JOBS) --dist loadfile

test-fast: install  ## run the tests without the slow marker
	$(PY) -m pytest -q -n $(TEST_JOBS) --dist loadfile -m "not slow"

coverage: install  ## the whole suite with line and branch coverage of src/lbo (code run by the tests' subprocesses not counted)
	$(PY) -m pytest -q -n $(TEST_JOBS) --dist loadfile --cov=lbo --cov-branch --cov-report=term

slurm-check: install  ## tests/test_slurm.py: sweeps, make reproduce, a killed job on a one-node SLURM cluster it starts (slurm-wlm, munge, root)
	OMP_NUM_THREADS=1 $(PY) -m pytest -q -s -p no:cacheprovider tests/test_slurm.py

data: install  ## generate the data sets: make data SCALE=smoke|quick|paper
	$(PY) -m lbo.datagen data=$(SCALE)

reproduce: install  ## the paper's study, resumable: make reproduce SCALE=paper|quick [STUDY=paper|dynamic|all] [TRAINER=gpu] [LAUNCHER=joblib JOBS=4] [ARGS="models=[cnn] windows=[20]"]
	$(PY) -m lbo.reproduce scale=$(SCALE) study=$(STUDY) "train_overrides=['trainer=$(TRAINER)']" \
		launcher=$(LAUNCHER) jobs=$(JOBS) $(ARGS)

ablation: install  ## the paper's protocol variant by variant at quick scale, resumable -> reports/ablation/
	$(PY) -m lbo.ablation "overrides=['trainer=$(TRAINER)']"

fleet: install  ## train on your own logs, worked example: a simulated fleet -> train -> score -> observe
	PY=$(CURDIR)/$(PY) bash examples/fleet.sh

ui: install  ## mlflow ui at http://127.0.0.1:5000 (MLFLOW_PORT=...): every run in the repo's mlflow.db, each data set's runs side by side at the address it prints
	@$(PY) -m lbo.tracking.view sqlite:///$(CURDIR)/mlflow.db | sed 's|127.0.0.1:5000|127.0.0.1:$(MLFLOW_PORT)|'
	$(VENV)/bin/mlflow ui --host 127.0.0.1 --port $(MLFLOW_PORT) \
		--backend-store-uri sqlite:///$(CURDIR)/mlflow.db

mlflow-server: install  ## a shared MLflow tracking server on 127.0.0.1:$(MLFLOW_PORT) [MLFLOW_BACKEND=postgresql://...]
	$(VENV)/bin/mlflow server --host 127.0.0.1 --port $(MLFLOW_PORT) \
		--backend-store-uri "$(MLFLOW_BACKEND)" --artifacts-destination "$(MLFLOW_ARTIFACTS)"

real-drive: install  ## the onavdata hill drive as lbo logs, the gyro EKF's noise learned on it, every classical observer on its test span and each drive left out in turn -> reports/realdrive/
	$(PY) -m lbo.realdrive

receiver-study: install  ## simulated single-antenna logs at alpha 1, 3, 6: every observer beside an oracle gyro EKF -> reports/receiver_study/
	$(PY) -m lbo.receiver_study

side-slip: install  ## the side-slip observers trained on the MBDS run's train span (a rerun reuses them), every estimate of beta scored on each span, their streams timed -> reports/sideslip/
	$(PY) -m lbo.train model=slip_gru data=sideslip resume=true hydra.run.dir=reports/sideslip/run
	$(PY) -m lbo.train model=slip_filter data=sideslip batch_size=32 optimizer.lr=0.005 nll=0.3 trainer.max_epochs=40 resume=true hydra.run.dir=reports/sideslip/filter
	$(PY) benchmarks/sideslip.py --slip reports/sideslip/run/checkpoints/best.ckpt --filter reports/sideslip/filter/checkpoints/best.ckpt reports/sideslip/sideslip.png

bench: install  ## benchmarks: data generation, filters, training throughput, latency (medians)
	$(PY) benchmarks/bench_datagen.py
	$(PY) benchmarks/bench_filters.py
	$(PY) benchmarks/bench_train.py
	$(PY) benchmarks/bench_latency.py
	$(PY) benchmarks/bench_threads.py

readme-tables: install  ## the measured tables of README.md and docs/results.md rebuilt from docs/results/ (TAKE="results=reports/quick/nrmse.csv" takes a fresh one in)
	$(PY) benchmarks/readme_tables.py $(foreach t,$(TAKE),--take $(t))

lint: install  ## ruff, and mypy over src/lbo ([tool.mypy] in pyproject.toml)
	$(VENV)/bin/ruff check src tests benchmarks examples
	$(VENV)/bin/mypy

clean:  ## remove generated outputs (keeps .venv, data/ and the MLflow/Optuna stores)
	rm -rf outputs multirun .pytest_cache
